"""WeightedSampler: draws ∝ the weight written with each transition; the weights a DSAC-T run writes."""

import pytest
import torch
from tensordict import TensorDict
from test_training import tiny_cfg
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from daof.filters.learned import startup_feature
from daof.train.dsac import DSACTTrainer
from daof.train.sampling import ReplayPriority, WeightedSampler


def buffer_with(weights: list[float], capacity: int = 10) -> TensorDictReplayBuffer:
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(capacity), sampler=WeightedSampler(capacity), priority_key="w", batch_size=4000
    )
    n = len(weights)
    rb.extend(TensorDict({"i": torch.arange(n), "w": torch.tensor(weights)}, batch_size=[n]))
    return rb


def test_draws_follow_the_weights_and_skip_unfilled_slots():
    torch.manual_seed(0)
    rb = buffer_with([1.0, 3.0, 6.0])  # 3 of 10 slots filled
    counts = torch.bincount(rb.sample()["i"], minlength=3).double()
    assert counts.numel() == 3  # never an unfilled slot
    expected = torch.tensor([0.1, 0.3, 0.6]) * 4000
    se = (expected * (1 - expected / 4000)).sqrt()
    assert ((counts - expected).abs() < 4 * se).all(), counts


def test_state_round_trip_and_bad_weights():
    rb = buffer_with([1.0, 2.0])
    state = rb.state_dict()
    other = buffer_with([5.0, 5.0])
    other.load_state_dict(state)
    torch.testing.assert_close(other._sampler.weights, rb._sampler.weights)
    with pytest.raises(RuntimeError) as failed:  # TorchRL's extend wraps the sampler's error
        buffer_with([1.0, 0.0])
    assert "finite and > 0" in str(failed.value.__cause__)


def test_dsac_run_weights_transitions_by_their_start_up_step(tmp_path):
    k = 4.0
    cfg = tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 300, "buffer.startup_priority": k})
    trainer = DSACTTrainer(cfg)
    trainer.train()
    steps = trainer.buffer.storage.get(torch.arange(len(trainer.buffer)))["step"]
    expected = 1.0 + k * startup_feature(steps).squeeze(-1) ** 2
    torch.testing.assert_close(trainer.buffer._sampler.weights[: len(steps)], expected)
    assert expected.max() == 1.0 + k  # the data holds first steps
    with pytest.raises(ValueError, match="startup_priority must be finite and >= 0"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "b", **{"buffer.startup_priority": -1.0}))


def test_dsac_run_weights_transitions_by_their_previous_estimate(tmp_path):
    k, scale = 3.0, 0.1  # β only: veh2dof's default scale leaves r out
    cfg = tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 300, "buffer.estimate_priority": k})
    trainer = DSACTTrainer(cfg)
    trainer.train()
    stored = trainer.buffer.storage.get(torch.arange(len(trainer.buffer)))
    expected = 1.0 + k * (stored["prev_estimate"][:, 0] / scale) ** 2
    torch.testing.assert_close(trainer.buffer._sampler.weights[: len(expected)], expected)
    assert (expected > 1.0).any()  # the data holds non-zero slip estimates


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"buffer.estimate_priority": float("nan")}, "estimate_priority must be finite"),
        ({"buffer.estimate_priority": 1.0, "buffer.estimate_priority_scale": [0.1]}, "one scale"),
        ({"buffer.estimate_priority": 1.0, "buffer.estimate_priority_scale": [0.0, None]}, "> 0 or null"),
        ({"buffer.estimate_priority": 1.0, "buffer.estimate_priority_scale": [None, None]}, "every state out"),
    ],
)
def test_estimate_priority_rejects_bad_configs(tmp_path, overrides, message):
    with pytest.raises(ValueError, match=message):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **overrides))


def test_replay_priority_adds_both_terms():
    priority = ReplayPriority(startup=2.0, estimate=4.0, inverse_scale=(10.0, 0.0))
    step = torch.tensor([[1], [100]])
    prev = torch.tensor([[0.05, 9.0], [-0.2, 9.0]])  # r is left out
    rho = startup_feature(step).squeeze(-1)
    torch.testing.assert_close(priority(step, prev), 1.0 + 2.0 * rho**2 + 4.0 * torch.tensor([0.25, 4.0]))
