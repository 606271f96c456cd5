"""Learned filters: one class per kind, closed-loop ``run`` equals an env rollout (and a
TensorDictSequential and a Collector), the fast path equals the network, checkpoints, bounds, bad input."""

import dataclasses
import os
import pickle
import re
from pathlib import Path

import pytest
import torch
from daof.envs import make_env, make_system
from daof.envs.filtering_env import FEEDBACK_KEY
from daof.envs.history import FrameLayout
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type

from daof.filters.learned import (
    SCHEDULE_STEPS,
    SLF,
    DAOFv1,
    DAOFv2,
    FilterConfig,
    LearnedFilter,
    UpdateFilter,
    hold_last_value,
    load_filter,
    make_filter,
    sliding_windows,
    startup_feature,
)
from daof.train.checkpoint import atomic_save, capture_rng
from daof.train.policies import exploration_policy
from daof.train.schedules import ukf_schedule

#: every filter class: kind and the config fields that pick it
FORMS = {
    "DAOF-v1": ("DAOF-v1", {}),
    "DAOF-v2": ("DAOF-v2", {}),
    "SLF": ("SLF", {}),
}


def small(kind, window=4, system="veh2dof", **config):
    f = make_filter(kind, system=system, window=window, num_cells=16, **config)
    f.fit_normalizer(runs=4, steps=50)
    return f.eval()


def small_form(form, **config):
    kind, fields = FORMS[form]
    return small(kind, **fields, **config)


@pytest.mark.parametrize("kind", ["DAOF-v1", "DAOF-v2"])
def test_offline_run_equals_env_rollout(kind):
    """``run`` on simulate(seed) gives exactly the estimates of an env rollout with the same seed.

    The rollout runs 2 episodes of 15 steps, so the window is padded (with copies of the first
    frame) after a reset too."""
    f = small(kind)
    env = make_env("veh2dof", batch_size=3, window=4, seed=11, max_steps=15)
    with torch.no_grad():
        rollout = env.rollout(30, f.filter_module(), break_when_any_done=False)
    first = rollout["history"][:, 0].reshape(3, 4, -1)
    assert (first == first[:, -1:]).all()
    data = f.system.simulate(3, 15, seed=11)
    torch.testing.assert_close(f.run(data), rollout["action"][:, :15], rtol=0, atol=0)
    second = rollout["history"][:, 15].reshape(3, 4, -1)
    assert (second == second[:, -1:]).all()


def test_exploration_policy_deterministic_mode_is_the_filter():
    """The collector's policy in deterministic mode is the deterministic filter (squashed loc)."""
    f = small("DAOF-v1")
    env = make_env("veh2dof", batch_size=2, window=4, seed=5, max_steps=10)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a = env.rollout(10, exploration_policy(f), break_when_any_done=False)["action"]
    env = make_env("veh2dof", batch_size=2, window=4, seed=5, max_steps=10)
    with torch.no_grad():
        b = env.rollout(10, f.filter_module(), break_when_any_done=False)["action"]
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("kind", ["DAOF-v1", "DAOF-v2"])
def test_mean_feedback_feeds_back_the_deterministic_estimate_while_the_action_explores(kind):
    """``exploration_policy("mean")``: the env's next x̂_{t−1} is the filter's own estimate, the action is sampled.

    Its fed-back estimates are exactly the deterministic filter's closed loop on the same data,
    while the sampled actions (what the reward scores) differ from them.
    """
    f = small(kind)
    env = make_env("veh2dof", batch_size=3, window=4, seed=7, max_steps=12)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # as a collector runs it
        out = env.rollout(12, exploration_policy(f, "mean"), break_when_any_done=False)
    torch.testing.assert_close(out["next", "prev_estimate"], out[FEEDBACK_KEY], rtol=0, atol=0)
    data = f.system.simulate(3, 12, seed=7)
    torch.testing.assert_close(out[FEEDBACK_KEY], f.run(data), rtol=1e-5, atol=1e-6)
    assert not torch.allclose(out["action"], out[FEEDBACK_KEY])
    # the default feeds back the sampled action itself
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        out = env.rollout(12, exploration_policy(f), break_when_any_done=False)
    assert FEEDBACK_KEY not in out.keys()
    torch.testing.assert_close(out["next", "prev_estimate"], out["action"], rtol=0, atol=0)
    with pytest.raises(ValueError, match="feedback must be one of"):
        exploration_policy(f, "noisy")


@pytest.mark.parametrize("system", ["linear", "veh2dof"])
def test_v1_schedules_set_the_posterior_bound_the_gain_and_the_innovation_scale(system):
    """b_t = k · max(√diag P⁺_t of the UKF, its RMSE on the data: error_scale), K̄_t its mean gain, √diag S_t the
    innovation input's scale;
    before the schedules are set b is k√Q (a placeholder); a shorter schedule is held at its last row."""
    f = small("DAOF-v1", system=system)
    k, floor = f.config.correction_sigmas, f.system.process_noise.covariance.diagonal().sqrt()
    torch.testing.assert_close(f.correction_scale, (k * floor).expand_as(f.correction_scale))  # before fitting
    schedule = ukf_schedule(f.system, seed=3, runs=4)
    f.set_schedules(schedule)
    torch.testing.assert_close(f.correction_scale, k * torch.maximum(schedule["estimate"], f.error_scale))
    assert (f.correction_scale[-1] > k * schedule["estimate"][-1]).any()  # the UKF claims less than it reaches
    torch.testing.assert_close(f.reference_gain, schedule["gain"])
    torch.testing.assert_close(f.policy.innovation_scale, schedule["innovation"])
    short = small("DAOF-v1", system=system)
    short.set_schedules({key: value[:10] for key, value in schedule.items()})
    torch.testing.assert_close(short.correction_scale[10:], f.correction_scale[9:10].expand(SCHEDULE_STEPS - 10, -1))


@pytest.mark.parametrize("system", ["linear", "veh2dof"])
def test_v1_update_is_the_mean_gain_update_plus_the_bounded_residual(system):
    """x̂_t − f(x̂_{t−1}, u_{t−1}) = K̄_t ν_t + b_t ⊙ a_t with the actor's a_t ∈ [−1, 1]ⁿ and b_t = k√P⁺_t of step t;
    the deterministic filter, the collector's policy in deterministic mode and ``run`` agree."""
    f = small("DAOF-v1", system=system)
    schedule = ukf_schedule(f.system, seed=3, runs=4)
    f.set_schedules(schedule)
    env = make_env(system, batch_size=3, window=4, seed=4, max_steps=60)
    with torch.no_grad():
        td = env.rollout(60, exploration_policy(f), break_when_any_done=False)
    assert (td["correction"].abs() <= 1).all() and (td["step"][..., 0] == torch.arange(1, 61)).all()
    s, rows = f.system, td["step"][..., 0].clamp(max=SCHEDULE_STEPS) - 1
    prediction = s.f(td["prev_estimate"], td["prev_control"])
    nu = td["measurement"] - s.g(prediction, td["control"])
    kalman = (schedule["gain"][rows] @ nu.unsqueeze(-1)).squeeze(-1)
    expected = (prediction + kalman + f.correction_scale[rows] * td["correction"]).clamp(f.state_low, f.state_high)
    torch.testing.assert_close(td["action"], expected, atol=1e-6, rtol=0)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        explored = make_env(system, batch_size=3, window=4, seed=4, max_steps=60).rollout(
            60, exploration_policy(f), break_when_any_done=False
        )["action"]
    with torch.no_grad():
        filtered = make_env(system, batch_size=3, window=4, seed=4, max_steps=60).rollout(
            60, f.filter_module(), break_when_any_done=False
        )["action"]
    torch.testing.assert_close(explored, filtered)
    data = s.simulate(3, 20, seed=11)
    env = make_env(system, batch_size=3, window=4, seed=11, max_steps=20)
    with torch.no_grad():
        rolled = env.rollout(20, f.filter_module(), break_when_any_done=False)["action"]
    torch.testing.assert_close(f.run(data), rolled, rtol=0, atol=0)


@pytest.mark.parametrize("system", ["linear", "veh2dof"])
def test_v1_paper_form_learns_the_whole_update_within_the_prior_bound(system, tmp_path):
    """reference_gain=False: x̂_t = f(x̂_{t−1}, u_{t−1}) + b_t ⊙ a_t, b_t = k · max(√diag P⁻_t, error_scale), no K̄_t
    table; it saves and loads as itself, and another kind or a contradicting checkpoint is refused."""
    f = small("DAOF-v1", system=system, reference_gain=False, correction_sigmas=3.0)
    assert not hasattr(f, "reference_gain")
    schedule = ukf_schedule(f.system, seed=3, runs=4)
    f.set_schedules(schedule)
    torch.testing.assert_close(f.correction_scale, 3.0 * torch.maximum(schedule["prediction"], f.error_scale))
    env = make_env(system, batch_size=3, window=4, seed=4, max_steps=30)
    with torch.no_grad():
        td = env.rollout(30, exploration_policy(f), break_when_any_done=False)
    s, rows = f.system, td["step"][..., 0].clamp(max=SCHEDULE_STEPS) - 1
    prediction = s.f(td["prev_estimate"], td["prev_control"])
    expected = (prediction + f.correction_scale[rows] * td["correction"]).clamp(f.state_low, f.state_high)
    torch.testing.assert_close(td["action"], expected, atol=1e-6, rtol=0)
    f.save(tmp_path / "paper.pt")
    again = load_filter(tmp_path / "paper.pt")
    assert again.config.reference_gain is False
    data = s.simulate(2, 20, seed=5)
    torch.testing.assert_close(again.run(data), f.run(data), rtol=0, atol=0)
    with pytest.raises(ValueError, match="DAOF-v1's paper form"):
        small("DAOF-v2", system=system, reference_gain=False)
    training = {"kind": "DAOF-v1", "system": system, "window": 4, "network": {"num_cells": 16}}
    with pytest.raises(ValueError, match="lack the reference gain table"):
        FilterConfig.from_training(training, f.state_dict())


def test_v1_with_a_zero_residual_is_the_kalman_filter_on_linear():
    """On a linear-Gaussian system the UKF's gains are the data-independent K_t of the Kalman filter:
    with its residual at zero (tanh(0) = 0) DAOF-v1 is that filter, start-up included."""
    from daof.filters import KalmanFilter

    f = small("DAOF-v1", system="linear")
    f.set_schedules(ukf_schedule(f.system, seed=3, runs=4))
    last = [m for m in f.policy.mlp if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_(), last.bias.zero_()
    data = f.system.simulate(4, SCHEDULE_STEPS + 30, seed=12)
    ours, kf = f.run(data), KalmanFilter(f.system).run(data).float()
    torch.testing.assert_close(ours[:, :SCHEDULE_STEPS], kf[:, :SCHEDULE_STEPS], atol=2e-5, rtol=1e-4)
    # after S steps the gain is held at K_S, which is within 0.3 % of the RMSE of the still-settling K_t
    assert ((ours - kf).abs().amax((0, 1)) < 3e-3 * f.system.error_scale).all()


def test_v1_innovation_input_is_the_scaled_innovation_of_the_newest_frame():
    """ν_t = y_t − g(f(x̂_{t−1}, u_{t−1}), u_t) from the env's keys, divided by √S_t of its step, enters the MLP."""
    f = small("DAOF-v1")
    f.set_schedules(ukf_schedule(f.system, seed=3, runs=4))
    env = make_env("veh2dof", batch_size=3, window=4, seed=4, max_steps=8)
    with torch.no_grad():
        td = env.rollout(8, exploration_policy(f), break_when_any_done=False)
        s = f.system
        nu = td["measurement"] - s.g(s.f(td["prev_estimate"], td["prev_control"]), td["control"])
        torch.testing.assert_close(f.innovation(td["history"]), nu)
        features = f.policy.features(td["history"], td["step"])
        width = f.policy.input_loc.numel()
        scale = f.policy.innovation_scale[td["step"][..., 0] - 1]
        torch.testing.assert_close(features[..., width : width + 2], nu / scale)
    assert not small("DAOF-v2").innovation_input and f.policy.feature_dim == width + 2 + 1


def test_startup_feature_is_one_at_the_first_step_and_zero_once_settled():
    steps = torch.tensor([[1], [2], [SCHEDULE_STEPS + 1], [SCHEDULE_STEPS + 40]])
    torch.testing.assert_close(startup_feature(steps), torch.tensor([[1.0], [1 - 1 / SCHEDULE_STEPS], [0.0], [0.0]]))
    assert startup_feature(1) == 1.0 and startup_feature(SCHEDULE_STEPS + 1) == 0.0
    for kind, reads in [("DAOF-v1", True), ("DAOF-v2", True), ("SLF", False)]:
        assert ("step" in small(kind).policy_in_keys) == reads


def test_v1_estimate_stays_in_the_plausible_state_range():
    """A prediction at the edge of the state range plus a positive update is clamped to the range."""
    f = small("DAOF-v1")
    with torch.no_grad():
        f.policy.mlp[-1].bias.fill_(5.0)  # loc ≫ 0: the update saturates at +half-range
    window = torch.zeros(3, f.policy.input_loc.numel())
    edge = f.system.state_high.expand(3, -1)
    est = f.estimate(window, edge, torch.zeros(3, 1))
    assert (est <= f.system.state_high).all() and (est >= f.system.state_low).all()
    assert torch.isclose(est, f.system.state_high.expand(3, -1)).any()


def test_sliding_windows_pad_like_catframes():
    """Open-loop windows: oldest first, the first frame repeated N−1 times in front."""
    frames = torch.arange(1.0, 5.0).reshape(1, 4, 1)
    same = FrameLayout((("measurement", 1),), 3)
    assert same.sliding_windows(frames)[0].tolist() == [[1, 1, 1], [1, 1, 2], [1, 2, 3], [2, 3, 4]]
    assert torch.equal(sliding_windows(frames, 3), same.sliding_windows(frames))  # the name before FrameLayout


def test_slf_is_open_loop_and_vectorised():
    """SLF reads no fed-back estimate: its windows hold measurements and controls only."""
    f = small("SLF", window=5)
    assert f.frame_dim == f.system.measurement_dim + 2 * f.system.control_dim
    data = f.system.simulate(2, 40, seed=1)
    est = f.run(data)
    assert est.shape == (2, 40, 2) and torch.isfinite(est).all()
    # the estimate at t depends only on the last N measurement frames
    changed = data.clone()
    changed["measurement"][:, :10] += 1.0
    torch.testing.assert_close(f.run(changed)[:, 15:], est[:, 15:])
    # streamed one step at a time (how its cost is timed) it gives the same estimates
    torch.testing.assert_close(f.run_streaming(data), est, atol=1e-6, rtol=1e-5)


def test_checkpoint_round_trip(tmp_path):
    f = small("DAOF-v2")
    f.save(tmp_path / "f.pt", extra={"note": 1})
    g = load_filter(tmp_path / "f.pt", expect={"system": "veh2dof", "window": 4})
    data = f.system.simulate(2, 20, seed=2)
    torch.testing.assert_close(f.run(data), g.run(data))
    assert g.extra == {"note": 1}


def test_checkpoint_errors(tmp_path):
    f = small("DAOF-v2")
    f.save(tmp_path / "f.pt")
    with pytest.raises(ValueError, match="window=4, expected 20"):
        load_filter(tmp_path / "f.pt", expect={"window": 20})
    with pytest.raises(ValueError, match="system='veh2dof', expected 'linear'"):
        load_filter(tmp_path / "f.pt", expect={"system": "linear"})
    with pytest.raises(FileNotFoundError, match="no filter checkpoint"):
        load_filter(tmp_path / "missing.pt")
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a learned-filter checkpoint"):
        load_filter(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="a filter for 'veh2dof', not for 'linear'"):
        load_filter(tmp_path / "f.pt", make_system("linear"))
    blob = torch.load(tmp_path / "f.pt", weights_only=False)
    blob["state_dict"]["policy.mlp.0.weight"] = blob["state_dict"]["policy.mlp.0.weight"][:, :-1]  # an older layout
    torch.save(blob, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="does not fit this filter's layout"):
        load_filter(tmp_path / "old.pt")


def test_bad_config():
    with pytest.raises(ValueError, match="unknown filter kind"):
        FilterConfig(kind="DAOF-v3", system="veh2dof")
    with pytest.raises(ValueError, match="window must be an integer"):
        FilterConfig(kind="DAOF-v1", system="veh2dof", window=0)


def test_run_rejects_bad_data():
    f = small("DAOF-v2")
    data = f.system.simulate(2, 10, seed=0)
    bad = data.clone()
    bad["control"][0, 3] = float("nan")
    with pytest.raises(ValueError, match="control"):
        f.run(bad)
    with pytest.raises(ValueError, match="measurement"):
        f.run(data.exclude("measurement"))


def test_hold_last_value_fills_gaps_with_the_last_present_value():
    y = torch.tensor([[[float("nan"), 1.0], [2.0, float("nan")], [float("nan"), float("nan")], [5.0, 6.0]]])
    held = hold_last_value(y, torch.tensor([-1.0, -2.0]))
    assert held[0].tolist() == [[-1.0, 1.0], [2.0, 1.0], [2.0, 1.0], [5.0, 6.0]]
    assert hold_last_value(held, torch.zeros(2)) is held  # complete data passes through untouched


@pytest.mark.parametrize(
    "kind,fill", [("DAOF-v1", "prediction"), ("DAOF-v1", "hold"), ("DAOF-v2", "hold"), ("SLF", "hold")]
)
def test_learned_filters_stay_finite_under_dropout(kind, fill):
    """NaN measurements (sensor dropout) never make a learned filter's estimate non-finite."""
    f = small(kind)
    f.missing_fill = fill
    data = f.system.simulate(3, 60, seed=2)
    data["measurement"][:, ::3, 0] = float("nan")
    data["measurement"][1, 10:40, 1] = float("nan")
    data["measurement"][2, :5] = float("nan")
    assert torch.isfinite(f.run(data)).all() and torch.isfinite(f.run_streaming(data)).all()


def test_daof_v1_reads_a_missing_channel_as_its_prediction():
    """The default for DAOF-v1: a missing y_t,j enters the window as g(f(x̂_{t−1}, u_{t−1}), u_t)_j
    (innovation 0 there); present channels and the steps before the first gap are untouched."""
    f = small("DAOF-v1")
    assert f.missing_fill == "prediction" and small("SLF").missing_fill == "hold"
    data = f.system.simulate(3, 30, seed=4)
    gappy = data.clone()
    gappy["measurement"][:, 10:, 1] = float("nan")
    gappy["measurement"][0, 20, 0] = float("nan")
    complete = [step for step in f.stream_steps(data["measurement"], data["prev_control"], data["control"])]
    steps = list(f.stream_steps(gappy["measurement"], gappy["prev_control"], gappy["control"]))
    n, m = f.system.state_dim, f.system.measurement_dim
    for t, (window, prev, estimate) in enumerate(steps):
        y = window[:, -f.frame_dim :][:, n : n + m]
        predicted = f.system.g(f.predict(prev, gappy["prev_control"][:, t]), gappy["control"][:, t])
        missing = torch.isnan(gappy["measurement"][:, t])
        torch.testing.assert_close(y[missing], predicted[missing], rtol=0, atol=0)
        torch.testing.assert_close(y[~missing], gappy["measurement"][:, t][~missing], rtol=0, atol=0)
        if t < 10:
            torch.testing.assert_close(estimate, complete[t][2], rtol=0, atol=0)
    f.missing_fill = "hold"
    held = f.run(gappy)
    assert not torch.equal(held[:, 10:], torch.stack([e for _, _, e in steps], 1)[:, 10:])


def test_prediction_fill_needs_a_model_predictor():
    with pytest.raises(ValueError, match="DAOF-v1/KalmanNet only"):
        small("DAOF-v2").missing_fill = "prediction"
    with pytest.raises(ValueError, match="missing_fill must be one of"):
        small("DAOF-v1").missing_fill = "zeros"


def test_slf_missing_mask_flags_the_gaps_in_every_frame():
    """``missing_mask``: each frame ends with 1{y_t missing} per channel, read unnormalised; the
    values themselves are held as without the mask."""
    f = small("SLF", missing_mask=True)
    s = f.system
    m = s.measurement_dim
    assert f.frame_dim == 2 * m + 2 * s.control_dim
    data = s.simulate(2, 30, seed=5)
    gappy = data.clone()
    gappy["measurement"][0, 5:12, 1] = float("nan")
    gappy["measurement"][1, ::4, 0] = float("nan")
    frames = f.open_loop_frames(gappy["measurement"], gappy["control"], gappy["prev_control"])
    assert torch.equal(frames[..., -m:], torch.isnan(gappy["measurement"]).float())
    plain = small("SLF").open_loop_frames(gappy["measurement"], gappy["control"], gappy["prev_control"])
    torch.testing.assert_close(frames[..., :-m], plain, rtol=0, atol=0)
    flags = slice(f.frame_dim - m, f.frame_dim)
    assert torch.equal(f.policy.input_loc[flags], torch.zeros(m))
    assert torch.equal(f.policy.input_scale[flags], torch.ones(m))
    assert torch.isfinite(f.run(gappy)).all()
    torch.testing.assert_close(f.run(gappy), f.run_streaming(gappy))  # batched and step-by-step agree


# ----------------------------------------------------------------------------- one class per kind
def test_each_kind_is_its_own_class_on_a_shared_base():
    """``make_filter`` and ``LearnedFilter(config)`` (the name before the split) build the class of the kind."""
    expected = {"DAOF-v1": DAOFv1, "DAOF-v2": DAOFv2, "SLF": SLF}
    for form, cls in expected.items():
        kind, fields = FORMS[form]
        config = FilterConfig(kind=kind, system="veh2dof", window=3, num_cells=8, **fields)
        for f in (make_filter(kind, config), LearnedFilter(config), cls(config)):
            assert type(f) is cls and isinstance(f, LearnedFilter) and f.name == kind
        assert issubclass(cls, UpdateFilter) == (form == "DAOF-v1")
    with pytest.raises(ValueError, match="makes a DAOFv2, not a DAOFv1"):
        DAOFv1(FilterConfig(kind="DAOF-v2", system="veh2dof"))
    with pytest.raises(ValueError, match="got a SLF config"):
        make_filter("DAOF-v1", FilterConfig(kind="SLF", system="veh2dof"))
    with pytest.raises(ValueError, match="DAOF-v1 needs a model predictor"):
        make_filter("DAOF-v1", system="veh14dof")


@pytest.mark.parametrize("form", list(FORMS))
def test_fast_path_is_the_policy_network_and_its_squash(form):
    """The hand-folded inference path (``estimate``) is ``PolicyNet.forward`` + the squash (+ the
    prediction for an update filter), in an env rollout (step as a tensor) and streamed (step as an int)."""
    f = small_form(form)
    f.set_schedules(ukf_schedule(f.system, seed=3, runs=4))

    def generic(window, prev, u_prev, step):
        loc, _ = f.policy(window, step) if f.startup_input else f.policy(window)
        action = f.squash(loc)
        return f.update_estimate(action, prev, u_prev, step, window) if f.acts_by_update else action

    env = make_env("veh2dof", batch_size=3, seed=4, max_steps=60, layout=f.layout)
    with torch.no_grad():
        td = env.rollout(60, f.filter_module(env=env), break_when_any_done=False)
        expected = generic(td["history"], td["prev_estimate"], td["prev_control"], td["step"])
    torch.testing.assert_close(td["action"], expected, rtol=1e-6, atol=1e-6)
    data = f.system.simulate(2, 60, seed=5)
    y, u_prev, u = f.validate(data)
    with torch.no_grad():
        for t, (window, prev, estimate) in enumerate(f.stream_steps(y, u_prev, u)):
            step = torch.full((2, 1), t + 1)
            torch.testing.assert_close(estimate, generic(window, prev, u_prev[:, t], step), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("setting", ["rollout", "sequential", "collector"])
@pytest.mark.parametrize("form", list(FORMS))
def test_every_learned_filter_runs_in_a_torchrl_env(form, setting):
    """Each filter in an env with its own window layout: ``env.rollout``, inside a TensorDictSequential
    and inside a Collector, it gives ``run``'s estimates on the same episodes (to the bit for the
    closed-loop filters, streamed; the SLF's vectorised ``run`` to float rounding, its streamed one exactly)."""
    f = small_form(form)
    B, T = 3, 15
    env = make_env("veh2dof", batch_size=B, seed=11, max_steps=T, layout=f.layout)
    module = f.filter_module(env=env)
    with torch.no_grad():
        if setting == "collector":
            collector = Collector(
                env, module, frames_per_batch=B * T, total_frames=B * T, auto_register_policy_transforms=False
            )
            out = next(iter(collector))
            collector.shutdown()
        else:
            policy = module
            if setting == "sequential":  # the filter, then a module reading its estimate
                error = TensorDictModule(lambda x, est: x - est, in_keys=["true_state", "action"], out_keys=["error"])
                policy = TensorDictSequential(module, error)
            out = env.rollout(T, policy, break_when_any_done=False)
    assert out.batch_size == (B, T)
    data = f.system.simulate(B, T, seed=11)
    torch.testing.assert_close(out["action"], f.run_streaming(data), rtol=0, atol=0)
    exact = 0 if f.closed_loop else 1e-6
    torch.testing.assert_close(out["action"], f.run(data), rtol=exact, atol=exact)
    if setting == "sequential":
        torch.testing.assert_close(out["error"], out["true_state"] - out["action"])


def test_filter_modules_say_what_they_read():
    reads = {
        "DAOF-v1": ["history", "prev_estimate", "prev_control", "step"],
        "DAOF-v2": ["history", "step"],
        "SLF": ["history"],
    }
    for form, keys in reads.items():
        module = small_form(form).filter_module()
        assert list(module.in_keys) == keys and list(module.out_keys) == ["action"], form


def test_a_filter_refuses_an_env_with_another_window_in_one_line():
    f = small("DAOF-v1", window=5)
    env = make_env("veh2dof", batch_size=2, window=20, seed=0)
    with pytest.raises(ValueError) as error:
        f.filter_module(env=env)
    message = str(error.value)
    assert "\n" not in message and message.startswith("DAOF-v1 reads windows of N=5 frames"), message
    assert "the env builds N=20 frames" in message and "make_env(..., layout=filter.layout)" in message
    f.check_env(make_env("veh2dof", batch_size=2, window=5, seed=0))  # the same layout passes
    slf = small("SLF", window=5)  # open loop: a closed-loop env of the same N is another window
    with pytest.raises(ValueError, match=r"^SLF reads windows of N=5 frames of \(measurement\[2\]"):
        slf.check_env(make_env("veh2dof", batch_size=2, window=5, seed=0))


# ----------------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("run", ["v1", "slf", "kind", "typed-v1", "filter_config"])
def test_load_filter_reads_a_training_checkpoint(tmp_path, run):
    """checkpoint.pt (``FilterTrainer.save_checkpoint``): the training config, the filter's state dict,
    RNG states (numpy arrays among them), optimiser state. The filter is rebuilt from the filter config
    the checkpoint holds, or in older ones from the training config (a recipe's ``version`` config,
    the SLF's, a typed ``kind`` config whose network section no longer names every option)."""
    # a config written before the options were retired: their surviving values load (reference_gain
    # is DAOF-v1's own option: dropped for the other kinds whatever its value, as it always was)
    network = {"num_cells": 16, "depth": 2, "correction_sigmas": 0.5, "reference_gain": True}
    network |= {"correction_bound": "posterior", "innovation_input": True, "window_padding": "same"}
    if run == "typed-v1":  # today's training config: no retired option
        network = {"num_cells": 16, "depth": 2, "correction_sigmas": 0.5}
    config = {"system": "veh2dof", "scenario": "nominal", "window": 3, "include_controls": True, "network": network}
    config |= {"overrides": {"replay": {"runs": 5, "steps": 10, "seed": 1}}, "seeds": {"normalizer": 7}}
    kinds = {"v1": {"version": "v1"}, "slf": {}, "kind": {"kind": "DAOF-v2"}, "typed-v1": {"kind": "DAOF-v1"}}
    config |= kinds.get(run, {"kind": "DAOF-v1"})
    filter_config = FilterConfig.from_training(config)
    assert filter_config.kind == {"slf": "SLF", "kind": "DAOF-v2"}.get(run, "DAOF-v1")
    f = make_filter(filter_config.kind, filter_config)
    f.fit_normalizer(runs=4, steps=50)
    history = [{"frames": 100, "rmse_beta": 0.1}]
    training = {"frames": 100, "updates": 3, "wall": 1.5, "history": history, "best": {}, "next_ckpt": 200}
    blob = {"training": training, "config": config, "filter": f.state_dict(), "rng": capture_rng()}
    blob |= {"optim": torch.optim.Adam(f.parameters()).state_dict(), "logger": None}
    if run == "filter_config":  # as a trainer wrote it before the options were retired
        blob["filter_config"] = dict(vars(f.config)) | {"correction_bound": "posterior", "reference_gain": True}
        blob["filter_config"] |= {"innovation_input": True, "window_padding": "same"}
    atomic_save(blob, tmp_path / "checkpoint.pt")
    g = load_filter(tmp_path / "checkpoint.pt", expect={"window": 3})
    assert type(g) is type(f) and g.config == f.config and g.extra["history"] == history
    data = f.system.simulate(2, 20, seed=2)
    torch.testing.assert_close(g.run(data), f.eval().run(data), rtol=0, atol=0)


@pytest.mark.parametrize(
    "where, option, value",
    [
        ("filter_config", "correction_bound", "kalman"),
        ("config", "innovation_input", False),
        ("saved", "window_padding", "zeros"),
        ("weights", "innovation_input", False),
    ],
)
def test_load_filter_refuses_a_checkpoint_with_a_retired_option_in_one_line(tmp_path, where, option, value):
    """A DAOF-v1 saved with an option value that was retired (docs/log/2026-12-07-retired-options.md) is
    refused with one line naming the option and that log: in the filter config a trainer stored, in an
    older checkpoint's training config, in a saved filter's config, or only in its weights (no ν input)."""
    f = small("DAOF-v1", window=3)
    path = tmp_path / "checkpoint.pt"
    if where == "saved":
        torch.save({"config": dict(vars(f.config)) | {option: value}, "state_dict": f.state_dict()}, path)
    else:
        config = {"kind": "DAOF-v1", "system": "veh2dof", "window": 3, "network": {"num_cells": 16}}
        state = f.state_dict()
        blob = {"training": {"frames": 1}, "config": config, "filter": state}
        if where == "filter_config":
            blob["filter_config"] = dict(vars(f.config)) | {option: value}
        elif where == "config":
            config["network"][option] = value
        else:
            state["policy.innovation_scale"] = state["policy.innovation_scale"][..., :0]
        atomic_save(blob, path)
    with pytest.raises(ValueError) as error:
        load_filter(path)
    message = str(error.value)
    assert "\n" not in message and str(path) in message and "docs/log/2026-12-07-retired-options.md" in message
    assert f"{option}={value!r} was retired" in message, message
    # the value that survives loads; another kind never read DAOF-v1's options
    assert FilterConfig.from_dict({"kind": "DAOF-v2", "system": "veh2dof", "correction_bound": "kalman"}).kind


def v2_checkpoint(path, where: str, v2_action: str):
    """A DAOF-v2 saved before its increment form was removed, naming ``v2_action``: a saved filter, a
    training checkpoint with the filter config its trainer stored, or an older one with only the
    training config (``run_config.json``'s content)."""
    f = small("DAOF-v2", window=3)
    if where == "saved":
        torch.save({"config": dict(vars(f.config)) | {"v2_action": v2_action}, "state_dict": f.state_dict()}, path)
        return f
    network = {"num_cells": 16, "depth": 3, "v2_action": v2_action}
    config = {"kind": "DAOF-v2", "system": "veh2dof", "window": 3, "network": network}
    blob = {"training": {"frames": 1}, "config": config, "filter": f.state_dict()}
    if where == "filter_config":
        blob["filter_config"] = dict(vars(f.config)) | {"v2_action": v2_action}
    atomic_save(blob, path)
    return f


@pytest.mark.parametrize("where", ["saved", "filter_config", "config"])
def test_a_daof_v2_checkpoint_naming_the_estimate_form_still_loads(tmp_path, where):
    """``v2_action="estimate"`` (every DAOF-v2 saved before 2026-12-07 that is not of the increment form)
    is the only form left: the option is ignored and the filter loads with the same estimates."""
    f = v2_checkpoint(tmp_path / "f.pt", where, "estimate")
    g = load_filter(tmp_path / "f.pt")
    assert type(g) is DAOFv2 and g.config == f.config and not hasattr(g.config, "v2_action")
    data = f.system.simulate(2, 20, seed=2)
    torch.testing.assert_close(g.run(data), f.run(data), rtol=0, atol=0)


@pytest.mark.parametrize("where", ["saved", "filter_config", "config"])
def test_a_daof_v2_checkpoint_of_the_removed_increment_form_is_refused_in_one_line(tmp_path, where):
    """DAOF-v2's increment form was removed on 2026-12-07: a checkpoint of it is refused with one line
    naming the file, the removal's date and its log entry (which exists)."""
    path = tmp_path / "f.pt"
    v2_checkpoint(path, where, "increment")
    with pytest.raises(ValueError) as error:
        load_filter(path)
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"checkpoint {path}: "), message
    log = "docs/log/2026-12-07-daof-v2-increment-form-removed.md"
    assert "v2_action='increment' was removed on 2026-12-07 with DAOF-v2's increment form" in message
    assert log in message and (Path(__file__).resolve().parents[1] / log).is_file()


def test_make_filter_and_stored_configs_read_v2_action_as_a_retired_option():
    """``v2_action`` is no field any more: the estimate form's value is ignored wherever a config comes
    from (a mapping, fields, a stored config, a training config), any other value is refused in one line."""
    assert "v2_action" not in {field.name for field in dataclasses.fields(FilterConfig)}
    base = {"kind": "DAOF-v2", "system": "veh2dof", "window": 3, "num_cells": 8}
    plain = FilterConfig(**base)
    assert FilterConfig.from_dict(base | {"v2_action": "estimate"}) == plain
    training = {"kind": "DAOF-v2", "system": "veh2dof", "window": 3, "network": {"num_cells": 8}}
    assert FilterConfig.from_training(training | {"network": {"num_cells": 8, "v2_action": "estimate"}}) == plain
    assert make_filter("DAOF-v2", system="veh2dof", window=3, num_cells=8, v2_action="estimate").config == plain
    assert make_filter("DAOF-v2", plain, v2_action="estimate").config == plain
    # a kind that never read it drops it whatever its value, as before
    assert FilterConfig.from_dict({"kind": "SLF", "system": "veh2dof", "v2_action": "increment"}).kind == "SLF"
    refusals = [
        lambda: FilterConfig.from_dict(base | {"v2_action": "increment"}),
        lambda: FilterConfig.from_training(training | {"network": {"v2_action": "increment"}}),
        lambda: make_filter("DAOF-v2", system="veh2dof", v2_action="increment"),
        lambda: make_filter("DAOF-v2", plain, v2_action="increment"),
    ]
    for refused in refusals:
        with pytest.raises(ValueError, match=r"^v2_action='increment' was removed on 2026-12-07 ") as error:
            refused()
        assert "\n" not in str(error.value)
    with pytest.raises(TypeError, match="v2_action"):  # the dataclass itself has no such field
        FilterConfig(**base, v2_action="estimate")


def test_load_filter_reads_best_and_final_files_with_plain_data_only(tmp_path):
    f = small("DAOF-v1")
    f.save(tmp_path / "best.pt", extra={"history": [{"frames": 1, "score": 0.5}], "note": "x"})
    blob = torch.load(tmp_path / "best.pt", weights_only=True)  # tensors and plain data only
    assert set(blob) == {"config", "state_dict", "extra"} and blob["config"]["kind"] == "DAOF-v1"
    assert type(load_filter(tmp_path / "best.pt")) is DAOFv1
    np = pytest.importorskip("numpy")
    f.save(tmp_path / "final.pt", extra={"score": np.float32(0.25), "frames": np.int64(3), "ok": np.bool_(True)})
    assert load_filter(tmp_path / "final.pt").extra == {"score": 0.25, "frames": 3, "ok": True}
    with pytest.raises(ValueError, match=r"plain data only; extra\['when'\] is a object"):
        f.save(tmp_path / "bad.pt", extra={"when": object()})


class _Payload:
    """Creates a marker file when unpickled: what a malicious checkpoint would run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_load_filter_refuses_a_pickled_payload_without_running_it(tmp_path):
    marker = tmp_path / "payload-ran"
    f = small("SLF")
    torch.save(
        {"config": {"kind": "SLF", "system": "veh2dof"}, "state_dict": f.state_dict(), "x": _Payload(marker)},
        tmp_path / "evil.pt",
    )
    with open(tmp_path / "evil.pkl", "wb") as file:
        pickle.dump({"config": _Payload(marker)}, file)
    for name in ("evil.pt", "evil.pkl"):
        path = tmp_path / name
        with pytest.raises(ValueError) as error:
            load_filter(path)
        message = str(error.value)
        assert message.startswith(str(path)) and "\n" not in message, message
        assert not marker.exists(), f"loading {name} ran its payload"
    torch.load(tmp_path / "evil.pt", weights_only=False)  # the payload is real: an unsafe load runs it
    assert marker.exists()


def test_load_filter_refuses_unreadable_files_with_one_line(tmp_path):
    f = small("DAOF-v2")
    f.save(tmp_path / "good.pt")
    good = (tmp_path / "good.pt").read_bytes()
    files = {"empty.pt": b"", "truncated.pt": good[: len(good) // 2], "random.pt": os.urandom(2000)}
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
        start = re.escape(str(tmp_path / name))
        with pytest.raises(ValueError, match=f"^{start} is not a readable checkpoint") as error:
            load_filter(tmp_path / name)
        assert "\n" not in str(error.value)
