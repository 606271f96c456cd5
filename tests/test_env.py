"""The batched filtering env (envs.filtering_env + envs.history): specs, window contents and padding,
partial resets, reward, truncation, seeding, input validation and use inside a Collector."""

from __future__ import annotations

import pytest
import torch
from daof.envs import make_env
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

FRAME = ["prev_estimate", "measurement", "control", "prev_control"]  # CatTensors order


def frame_of(td: TensorDict) -> torch.Tensor:
    return torch.cat([td[k] for k in FRAME], -1)


def expected_window(frames: list[torch.Tensor], n: int) -> torch.Tensor:
    """Last n frames oldest first, padded at the front with copies of the first frame."""
    last = frames[-n:]
    return torch.cat([frames[0]] * (n - len(last)) + last, -1)


def random_estimate(env, generator) -> torch.Tensor:
    spec = env.action_spec
    return spec.low + (spec.high - spec.low) * 0.1 * torch.rand(spec.shape, generator=generator)


def step(env, td, action):
    td["action"] = action
    out, td = env.step_and_maybe_reset(td)
    return out, td


@pytest.mark.parametrize(
    "name, scenario",
    [("veh2dof", "nominal"), ("veh2dof", "mismatch"), ("veh2dof", "outliers"), ("linear", "nominal")],
)
def test_check_env_specs(name, scenario):
    env = make_env(name, batch_size=4, window=3, scenario=scenario, seed=0)
    check_env_specs(env, seed=0)
    system = env.base_env.system
    frame = system.state_dim + system.measurement_dim + 2 * system.control_dim
    assert env.observation_spec["history"].shape == (4, 3 * frame)
    assert "truncated" in env.full_done_spec.keys()


def test_window_holds_the_last_n_frames_in_order_and_pads_after_reset():
    n, B = 4, 3
    env = make_env("veh2dof", batch_size=B, window=n, seed=0)
    gen = torch.Generator().manual_seed(0)
    td = env.reset()
    assert td["history"].shape == (B, n * 6)
    frames = [frame_of(td)]
    # Right after reset: N copies of the first frame (prior mean, y_1, u_1, u_0).
    torch.testing.assert_close(td["history"], frames[0].repeat(1, n), rtol=0, atol=0)
    torch.testing.assert_close(td["prev_estimate"], torch.zeros(B, 2), rtol=0, atol=0)
    for _ in range(6):
        action = random_estimate(env, gen)
        out, td = step(env, td, action)
        # The new frame's previous estimate is the action just taken.
        torch.testing.assert_close(td["prev_estimate"], action, rtol=0, atol=0)
        frames.append(frame_of(td))
        torch.testing.assert_close(td["history"], expected_window(frames, n), rtol=0, atol=0)
        torch.testing.assert_close(out["next", "history"], td["history"], rtol=0, atol=0)
    # The newest frame is last: its slice is [x̂_{t−1}, y_t, u_t, u_{t−1}].
    torch.testing.assert_close(td["history"][:, -6:-4], td["prev_estimate"])
    torch.testing.assert_close(td["history"][:, -4:-2], td["measurement"])


def test_partial_reset_repads_only_the_reset_runs():
    n, B = 3, 3
    env = make_env("veh2dof", batch_size=B, window=n, seed=1)
    gen = torch.Generator().manual_seed(1)
    td = env.reset()
    for _ in range(5):
        _, td = step(env, td, random_estimate(env, gen))
    before = td.clone()
    mask = torch.tensor([[True], [False], [True]])
    td["_reset"] = mask  # what a collector passes for runs that are done
    after = env.reset(td)
    for i in (0, 2):
        torch.testing.assert_close(after["history"][i], frame_of(after)[i].repeat(n), rtol=0, atol=0)
        torch.testing.assert_close(after["prev_estimate"][i], torch.zeros(2), rtol=0, atol=0)
        assert not torch.equal(after["measurement"][i], before["measurement"][i])
    # The run that was not reset keeps its window and its observation.
    for key in ("history", "measurement", "prev_estimate", "control", "true_state"):
        torch.testing.assert_close(after[key][1], before[key][1], rtol=0, atol=0)
    # The env keeps simulating run 1 from where it was: its next frame extends its old window.
    action = random_estimate(env, gen)
    _, td = step(env, after.exclude("_reset"), action)
    old = before["history"][1].reshape(n, 6)
    torch.testing.assert_close(td["history"][1].reshape(n, 6)[:-1], old[1:], rtol=0, atol=0)
    torch.testing.assert_close(td["prev_estimate"][1], action[1], rtol=0, atol=0)
    # Its steering schedule continues (u_{t−1} of the new step is the u_t seen before the reset),
    # while the reset runs continue their new episodes.
    torch.testing.assert_close(td["prev_control"][1], before["control"][1], rtol=0, atol=0)
    torch.testing.assert_close(td["prev_control"][[0, 2]], after["control"][[0, 2]], rtol=0, atol=0)


@pytest.mark.parametrize("name", ["veh2dof", "linear"])
def test_reward_is_weighted_squared_error_of_the_same_row(name):
    B = 5
    env = make_env(name, batch_size=B, window=2, seed=2)
    system = env.base_env.system
    n = system.state_dim
    weights = 1.0 / (n * system.error_scale**2)
    gen = torch.Generator().manual_seed(2)
    actions = [random_estimate(env, gen) for _ in range(4)]
    it = iter(actions)
    data = env.rollout(4, lambda td: td.set("action", next(it)), break_when_any_done=False)
    expected = -((data["true_state"] - data["action"]) ** 2 * weights).sum(-1, keepdim=True)
    torch.testing.assert_close(data["next", "reward"], expected)
    # It is the state at the row where the estimate was made, not the next one.
    shifted = -((data["next", "true_state"] - data["action"]) ** 2 * weights).sum(-1, keepdim=True)
    assert not torch.allclose(data["next", "reward"], shifted)
    # A perfect estimate earns exactly zero.
    td = env.reset()
    td["action"] = td["true_state"].clone()
    assert torch.equal(env.step(td)["next", "reward"], torch.zeros(B, 1))


def test_custom_reward_weights():
    env = make_env("veh2dof", batch_size=2, window=1, seed=0, reward_weights=[1.0, 0.0])
    td = env.reset()
    td["action"] = td["true_state"] + torch.tensor([0.1, 5.0])
    torch.testing.assert_close(env.step(td)["next", "reward"], torch.full((2, 1), -0.01))
    with pytest.raises(ValueError, match="reward_weights"):
        make_env("veh2dof", batch_size=2, reward_weights=[1.0, -1.0])


def test_reward_weight_schedule_uses_the_row_of_the_estimated_step_and_holds_the_last():
    """A [S, n] schedule weighs the error of the estimate at step t (1..S) with row t; t > S uses row S."""
    S, T, B = 3, 6, 2
    schedule = torch.tensor([[1.0, 0.0], [2.0, 0.0], [0.0, 3.0]])
    env = make_env("veh2dof", batch_size=B, window=1, seed=0, max_steps=T, reward_weights=schedule)
    data = env.rollout(T, lambda td: td.set("action", torch.zeros(B, 2)), break_when_any_done=False)
    assert data["step"][0, :, 0].tolist() == list(range(1, T + 1))
    rows = schedule[torch.arange(T).clamp(max=S - 1)]  # [T, n]
    expected = -(data["true_state"] ** 2 * rows).sum(-1, keepdim=True)
    torch.testing.assert_close(data["next", "reward"], expected)
    for bad in (torch.ones(3, 3), torch.ones(0, 2), torch.ones(2, 2, 2), torch.full((2, 2), float("nan"))):
        with pytest.raises(ValueError, match="reward_weights"):
            make_env("veh2dof", batch_size=2, reward_weights=bad)


def test_episode_is_truncated_after_exactly_max_steps():
    T, B = 5, 2
    env = make_env("veh2dof", batch_size=B, window=2, seed=3, max_steps=T)
    data = env.rollout(2 * T + 2, lambda td: td.set("action", torch.zeros(B, 2)), break_when_any_done=False)
    truncated = data["next", "truncated"][:, :, 0]
    ends = torch.zeros(2 * T + 2, dtype=torch.bool)
    ends[T - 1] = ends[2 * T - 1] = True
    assert torch.equal(truncated, ends.expand(B, -1))
    assert torch.equal(data["next", "done"], data["next", "truncated"])
    assert not data["next", "terminated"].any()
    # After the automatic reset the next episode starts again from the prior mean.
    assert torch.equal(data["prev_estimate"][:, T], torch.zeros(B, 2))
    short = env.rollout(100, lambda td: td.set("action", torch.zeros(B, 2)))
    assert short.shape == (B, T)


def test_same_seed_same_rollout_different_seed_different():
    def run(seed):
        env = make_env("veh2dof", batch_size=3, window=3, seed=seed, scenario="mismatch")
        return env.rollout(8, lambda td: td.set("action", torch.full((3, 2), 0.01)), break_when_any_done=False)

    a, b, c = run(5), run(5), run(6)
    for key in ("history", "true_state", ("next", "reward")):
        assert torch.equal(a[key], b[key]), key
        assert not torch.equal(a[key], c[key]), key
    # set_seed re-seeds the env's generator.
    env = make_env("veh2dof", batch_size=3, window=3, seed=0, scenario="mismatch")
    env.set_seed(5)
    d = env.rollout(8, lambda td: td.set("action", torch.full((3, 2), 0.01)), break_when_any_done=False)
    assert torch.equal(d["history"], a["history"])


def test_invalid_input_raises():
    env = make_env("veh2dof", batch_size=2, window=2, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([[0.0, 0.0], [float("nan"), 0.0]])
    with pytest.raises(ValueError, match=r"not finite in run\(s\) \[1\]"):
        env.step(td)
    for bad in (0, (2, 2)):
        with pytest.raises(ValueError, match="batch size"):
            make_env("veh2dof", batch_size=bad)
    for bad in (0, 2.5):
        with pytest.raises(ValueError, match="window"):
            make_env("veh2dof", batch_size=2, window=bad)
    with pytest.raises(ValueError, match="max_steps"):
        make_env("veh2dof", batch_size=2, max_steps=0)


def test_env_works_in_a_collector():
    B, k, N = 4, 6, 3
    env = make_env("veh2dof", batch_size=B, window=N, seed=0, max_steps=10)
    policy = TensorDictModule(lambda h: torch.full((*h.shape[:-1], 2), 0.01), in_keys=["history"], out_keys=["action"])
    collector = Collector(
        env, policy, frames_per_batch=B * k, total_frames=2 * B * k, auto_register_policy_transforms=False
    )
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.batch_size == (B, k)
        assert batch["history"].shape == (B, k, N * 6)
        assert batch["next", "history"].shape == (B, k, N * 6)
        assert torch.equal(batch["action"], torch.full((B, k, 2), 0.01))
    # The two batches together are one continuous episode of 12 steps with a reset after step 10.
    trunc = torch.cat([b["next", "truncated"] for b in batches], 1)[..., 0]
    assert trunc.sum(1).tolist() == [1] * B and trunc[:, 9].all()
    second = batches[1]
    # Across the batch boundary and inside the second batch the window slides by one frame per step.
    first_last = batches[0]["history"][:, -1].reshape(B, N, 6)
    second_first = second["history"][:, 0].reshape(B, N, 6)
    torch.testing.assert_close(second_first[:, :-1], first_last[:, 1:], rtol=0, atol=0)
    # Step 10 (index 4 of the second batch) is the first of a new episode: padded with its frame.
    new = second["history"][:, 4].reshape(B, N, 6)
    torch.testing.assert_close(new, new[:, :1].expand(B, N, 6), rtol=0, atol=0)
