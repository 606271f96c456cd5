"""``FrameLayout`` (envs/history.py): the one description of the window, checked against env rollouts.

Closed loop and open loop, with and without controls (a system that has none, and controls left
out), with missing flags: the env's ``history`` is exactly what the layout says (its
fields, its newest frame, its first window after a reset, its sliding windows over an episode),
``of_env`` reads the layout back from the env, and the gymnasium env builds its window with it.
"""

import pytest
import torch
from daof.envs import history as history_module
from daof.envs import make_env, make_system
from daof.envs.filtering_env import FilteringEnv
from daof.envs.gaps import MISSING_KEY, GappySystem
from daof.envs.gym_env import FilteringGymEnv
from daof.envs.history import FRAME_KEY, HISTORY_KEY, FrameLayout, with_window
from torchrl.envs import CatFrames, CatTensors, Compose, TransformedEnv

B, T, N = 3, 9, 4

CASES = {
    # name: (system, layout options, gaps in the episodes)
    "closed-loop": ("veh2dof", {}, False),
    "open-loop": ("veh2dof", {"closed_loop": False}, False),
    "controls-left-out": ("veh2dof", {"include_controls": False}, False),
    "system-without-controls": ("veh14dof", {}, False),
    "open-loop-without-controls": ("veh14dof", {"closed_loop": False}, False),
    "missing-flags": ("veh2dof", {"missing_flags": True}, True),
    "open-loop-missing-flags": ("veh2dof", {"closed_loop": False, "missing_flags": True}, True),
}


def rollout(name: str, layout_of=None):
    system_name, options, gaps = CASES[name]
    system = make_system(system_name)
    layout = FrameLayout.for_system(system, N, **options)
    if gaps:
        system = GappySystem(system, 0.4, 0.1, T)
    env = with_window(FilteringEnv(system, B, T, seed=3), layout)
    gen = torch.Generator().manual_seed(0)
    low, high = system.state_low, system.state_high
    actions = iter([low + (high - low) * torch.rand(B, len(low), generator=gen) for _ in range(2 * T)])
    with torch.no_grad():
        td = env.rollout(2 * T, lambda td: td.set("action", next(actions)), break_when_any_done=False)
    return env, layout, td


@pytest.mark.parametrize("name", list(CASES))
def test_layout_describes_the_env_window(name):
    env, layout, td = rollout(name)
    system_name, options, _ = CASES[name]
    system = make_system(system_name)
    assert FrameLayout.of_env(env) == layout
    history = td[HISTORY_KEY]  # [B, 2T, N·F]: two episodes
    assert history.shape[-1] == layout.width == N * layout.frame_dim
    expected = ["prev_estimate"] if options.get("closed_loop", True) else []
    expected.append("measurement")
    if options.get("include_controls", True) and system.control_dim > 0:
        expected += ["control", "prev_control"]
    if options.get("missing_flags"):
        expected.append(MISSING_KEY)
    assert list(layout.keys) == expected
    assert layout.closed_loop == ("prev_estimate" in expected) and layout.missing_flags == (MISSING_KEY in expected)
    assert layout.uses_controls == ("control" in expected)
    # every field of the newest frame is that step's observation; the frame is their concatenation.
    # (Not at an episode's last step: there FilteringEnv's partial reset overwrites the stored u_t in
    # place with the next episode's u_0, after the window was built from the right one.)
    inside = [t for t in range(2 * T) if t not in (T - 1, 2 * T - 1)]
    for key in layout.keys:
        assert layout.widths[key] == td[key].shape[-1]
        torch.testing.assert_close(layout.field(history, key)[:, inside], td[key][:, inside], rtol=0, atol=0)
        torch.testing.assert_close(layout.field(layout.newest(history), key), layout.field(td["frame"], key))
    torch.testing.assert_close(layout.frame(td)[:, inside], td["frame"][:, inside], rtol=0, atol=0)
    frames = td["frame"]  # [B, 2T, F], as CatTensors built them
    torch.testing.assert_close(layout.newest(history), frames, rtol=0, atol=0)
    # each episode's windows are the layout's sliding windows of its frames, padded after its reset
    for episode in (slice(0, T), slice(T, 2 * T)):
        windows = layout.sliding_windows(frames[:, episode])
        torch.testing.assert_close(history[:, episode], windows, rtol=0, atol=0)
        torch.testing.assert_close(history[:, episode][:, 0], layout.first_window(frames[:, episode][:, 0]))
    # streaming: first window, then slide by one frame per step
    window = layout.first_window(frames[:, 0])
    for t in range(1, T):
        window = layout.slide(window, frames[:, t])
        torch.testing.assert_close(history[:, t], window, rtol=0, atol=0)
    assert torch.equal(layout.unstack(history)[:, :, -1], frames)
    # after the reset the window is padded with copies of the first frame
    assert torch.equal(layout.unstack(history[:, T]), frames[:, T : T + 1].expand(-1, N, -1).contiguous())


def test_the_layout_without_the_fed_back_estimate_is_the_open_loop_one():
    system = make_system("veh2dof")
    closed = FrameLayout.for_system(system, N, missing_flags=True)
    assert closed.without("prev_estimate") == FrameLayout.for_system(system, N, closed_loop=False, missing_flags=True)
    assert closed.offset("measurement") == slice(2, 4) and closed.offset(MISSING_KEY) == slice(6, 8)
    assert closed.frame_dim == 8 and closed.width == 32
    assert "control" in closed and "state" not in closed


def test_make_env_builds_the_window_of_a_layout():
    system = make_system("veh2dof")
    layout = FrameLayout.for_system(system, 5, closed_loop=False)
    env = make_env("veh2dof", batch_size=2, seed=0, layout=layout)
    assert FrameLayout.of_env(env) == layout
    assert FrameLayout.of_env(make_env("veh2dof", batch_size=2, window=3)) == FrameLayout.for_system(system, 3)
    # the older form of with_window still builds the closed-loop layout
    old = with_window(FilteringEnv(system, 2, 10, seed=0), 3, True)
    assert FrameLayout.of_env(old) == FrameLayout.for_system(system, 3)


def test_bad_layouts_fail_with_one_line():
    system = make_system("veh2dof")
    with pytest.raises(ValueError, match="in that order"):
        FrameLayout((("measurement", 2), ("prev_estimate", 2)), 3)
    with pytest.raises(ValueError, match="in that order"):
        FrameLayout((("state", 2),), 3)
    with pytest.raises(ValueError, match="window must be an integer"):
        FrameLayout.for_system(system, 0)
    keys = list(FrameLayout.for_system(system, 3).keys)  # a window padded with zeros (retired) is not a filter's
    zeros = Compose(
        CatTensors(keys, out_key=FRAME_KEY, del_keys=False, sort=False),
        CatFrames(N=3, dim=-1, in_keys=[FRAME_KEY], out_keys=[HISTORY_KEY], padding="constant"),
    )
    with pytest.raises(ValueError, match=r"^the env's window is padded with 'constant' \(0\), not with copies"):
        FrameLayout.of_env(TransformedEnv(FilteringEnv(system, 2, 10, seed=0), zeros))
    flagged = FrameLayout.for_system(system, 3, missing_flags=True)  # a system without gaps has no flags
    with pytest.raises(ValueError, match="^the window's field 'missing' needs width 2; the env has no such key$"):
        with_window(FilteringEnv(system, 2, 10, seed=0), flagged)
    with pytest.raises(ValueError, match="builds no 'history' window"):
        FrameLayout.of_env(FilteringEnv(system, 2, 10, seed=0))
    with pytest.raises(ValueError, match="expected a frame"):
        flagged.field(torch.zeros(2, 5), "measurement")
    assert not hasattr(history_module, "history_dim") and not hasattr(history_module, "window_transform")


def test_gym_env_window_is_the_layout():
    system = make_system("veh2dof")
    env = FilteringGymEnv(system, window=3, include_controls=False)
    assert env.layout == FrameLayout.for_system(system, 3, include_controls=False)
    obs, _ = env.reset(seed=2)
    frames = torch.from_numpy(obs).reshape(3, -1)
    assert frames.shape[-1] == env.layout.frame_dim == 4
    assert torch.equal(frames, frames[:1].expand(3, -1))  # "same" padding after the reset
    obs, *_ = env.step(torch.tensor([0.01, -0.02]).numpy())
    newest = env.layout.field(torch.from_numpy(obs), "prev_estimate")
    torch.testing.assert_close(newest, torch.tensor([0.01, -0.02]), rtol=0, atol=0)
