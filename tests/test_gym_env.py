"""The gymnasium env daof/Veh2DOF-v0 (envs.gym_env): API conformance and equality with the TorchRL env."""

from __future__ import annotations

import daof.envs as envs  # noqa: F401  (registers daof/Veh2DOF-v0)
import gymnasium
import numpy as np
import pytest
import torch
from daof.envs import make_env
from daof.envs.gym_env import GYM_ID, Veh2DOFGymEnv
from gymnasium.utils.env_checker import check_env


# The checker's advice (normalised action box, finite observation bounds) does not fit a filter:
# the action is a physical state estimate and the window holds raw measurements.
@pytest.mark.filterwarnings("ignore:.*(symmetric and normalized|infinity).*:UserWarning")
def test_passes_gymnasium_env_checker():
    env = gymnasium.make(GYM_ID)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.observation_space.shape == (20 * 6,) and env.observation_space.dtype == np.float32
    system = env.unwrapped.system  # the action box is the system's output range (from its data)
    np.testing.assert_array_equal(env.action_space.low, system.state_low.numpy())
    np.testing.assert_array_equal(env.action_space.high, system.state_high.numpy())


@pytest.mark.parametrize("scenario", ["nominal", "mismatch"])
def test_observation_and_reward_equal_the_torchrl_env_for_the_same_seed(scenario):
    seed, N, k = 7, 4, 6
    gym_env = gymnasium.make(GYM_ID, scenario=scenario, window=N).unwrapped
    trl_env = make_env("veh2dof", batch_size=1, window=N, scenario=scenario, seed=seed)
    obs, info = gym_env.reset(seed=seed)
    td = trl_env.reset()
    assert obs.dtype == np.float32 and obs.shape == (N * 6,)
    np.testing.assert_array_equal(obs, td["history"][0].numpy())
    np.testing.assert_array_equal(info["true_state"], td["true_state"][0].numpy())
    actions = np.random.default_rng(0).uniform(-0.05, 0.05, size=(k, 2)).astype(np.float32)
    for a in actions:
        obs, reward, terminated, truncated, info = gym_env.step(a)
        td["action"] = torch.from_numpy(a)[None]
        out, td = trl_env.step_and_maybe_reset(td)
        np.testing.assert_array_equal(obs, td["history"][0].numpy())
        assert reward == pytest.approx(float(out["next", "reward"]), rel=1e-6)
        assert not terminated and not truncated


def test_window_layout_and_reward_formula():
    N = 3
    env = Veh2DOFGymEnv(window=N, max_steps=4)
    obs0, info0 = env.reset(seed=1)
    frames = obs0.reshape(N, 6)
    # Reset: N copies of [x̂_0 = prior mean, y_1, u_1, u_0].
    np.testing.assert_array_equal(frames, np.repeat(frames[:1], N, 0))
    np.testing.assert_array_equal(frames[0, :2], [0.0, 0.0])
    a = np.array([0.02, -0.1], np.float32)
    obs1, reward, terminated, truncated, info1 = env.step(a)
    frames1 = obs1.reshape(N, 6)
    np.testing.assert_array_equal(frames1[:-1], frames[1:])  # oldest frame dropped
    np.testing.assert_array_equal(frames1[-1, :2], a)  # newest frame carries x̂_{t−1} = the action
    np.testing.assert_array_equal(frames1[-1, 5], frames[-1, 4])  # u_{t−1} of the new frame = old u_t
    w = 1.0 / (2 * env.system.error_scale.double().numpy() ** 2)  # default W = 1/(n·error_scale²)
    assert reward == pytest.approx(-float((w * (info0["true_state"] - a) ** 2).sum()), rel=1e-5)
    # Truncated (not terminated) after exactly max_steps estimates.
    flags = [env.step(a)[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]


def test_reset_seed_is_reproducible():
    env = Veh2DOFGymEnv(window=2)
    a, _ = env.reset(seed=3)
    a1 = env.step(np.zeros(2, np.float32))[0]
    b, _ = env.reset(seed=3)
    b1 = env.step(np.zeros(2, np.float32))[0]
    c, _ = env.reset(seed=4)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a1, b1)
    assert not np.array_equal(a, c)
    # Without a seed, successive resets continue the stream: a new episode each time.
    d, _ = env.reset()
    assert not np.array_equal(d, c)


def test_invalid_input_raises():
    env = Veh2DOFGymEnv(window=2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="not finite"):
        env.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match="window"):
        Veh2DOFGymEnv(window=0)
    with pytest.raises(ValueError, match="unknown scenario"):
        gymnasium.make(GYM_ID, scenario="icy")


def test_a_fresh_interpreter_makes_the_env_by_gymnasiums_module_prefixed_id():
    import subprocess
    import sys

    make = "gymnasium.make('daof.envs:daof/Veh2DOF-v0', window=3)"
    code = f"import gymnasium; env = {make}; print(env.reset(seed=0)[0].shape)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(18,)"


def test_torchrl_gymenv_wraps_the_registered_id():
    """TorchRL's GymEnv passes frameskip; an unknown keyword is a TypeError, so it drops it and wraps the env."""
    from torchrl.envs import GymEnv

    env = GymEnv(GYM_ID, window=3)
    rollout = env.rollout(4)
    assert rollout["observation"].shape == (4, 18)
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        Veh2DOFGymEnv(frameskip=2)
