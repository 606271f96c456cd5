"""WeightedSampler: draws ∝ the weight written with each transition; start-up weights of a DSAC-T run."""

import pytest
import torch
from tensordict import TensorDict
from test_training import tiny_cfg
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from daof.filters.learned import startup_feature
from daof.train.dsac import DSACTTrainer
from daof.train.sampling import WeightedSampler


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
    with pytest.raises(ValueError, match="startup_priority must be >= 0"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "b", **{"buffer.startup_priority": -1.0}))
