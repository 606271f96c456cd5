"""A system's scales come from its own simulated data (daof.envs.scales), never from the answer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import torch
from daof.envs import make_system, scales
from daof.envs.gaps import GappySystem
from daof.envs.linear import LinearOscillator

from daof.filters.learned import FilterConfig, LearnedFilter


def stationary_kalman_rmse(system) -> np.ndarray:
    A, C = system.A.double().numpy(), system.C.double().numpy()
    Q = system.process_noise.covariance.double().numpy()
    R = system.measurement_noise.covariance.double().numpy()
    P = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)  # predicted covariance
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    return np.sqrt(np.diag((np.eye(2) - K @ C) @ P))


def test_linear_error_scale_is_the_kalman_filters_rmse_on_the_data():
    """On linear the UKF is the Kalman filter: its RMSE is the stationary one plus a short start-up."""
    system = make_system("linear")
    assert system.scales().source == "UKF"
    ratio = system.error_scale.double().numpy() / stationary_kalman_rmse(system)
    assert (ratio >= 1.0).all() and (ratio < 1.1).all()


class ModelFreeLinear(LinearOscillator):
    """The linear oscillator without a model: its error scale must come from the data alone."""

    has_model = False


def test_a_model_free_systems_error_scale_is_a_linear_estimators_rmse():
    """The best linear map from the last measurements cannot beat the Kalman filter, and on a linear
    system with a window of 10 it comes close."""
    system = ModelFreeLinear()
    assert system.scales().source == "linear estimator"
    ratio = system.error_scale.double().numpy() / stationary_kalman_rmse(system)
    assert (ratio > 1.0).all() and (ratio < 1.5).all()


def test_the_output_range_is_the_simulated_states_range_widened_by_its_width():
    system = make_system("veh2dof")
    data = system.simulate(scales.SCALES_RUNS, scales.SCALES_STEPS, scales.SCALES_SEED)
    low, high = data["state"].flatten(0, 1).min(0).values, data["state"].flatten(0, 1).max(0).values
    width = high - low
    torch.testing.assert_close(system.state_low, low - scales.RANGE_MARGIN * width)
    torch.testing.assert_close(system.state_high, high + scales.RANGE_MARGIN * width)


def test_an_override_replaces_the_datas_value_and_none_restores_it():
    system = make_system("veh2dof")
    data_low = system.state_low.clone()
    system.state_low = [-1.0, -2.0]
    assert system.state_low.tolist() == [-1.0, -2.0]
    assert torch.equal(make_system("veh2dof").state_low, data_low)  # another object keeps the data's
    system.state_low = None
    assert torch.equal(system.state_low, data_low)


def test_equal_systems_share_one_computation_and_other_parameters_get_their_own(monkeypatch):
    calls = []
    compute = scales.error_scale
    monkeypatch.setattr(scales, "error_scale", lambda *a: calls.append(1) or compute(*a))
    monkeypatch.setattr(scales, "_CACHE", {})
    first = make_system("linear").error_scale
    assert torch.equal(make_system("linear").error_scale, first) and len(calls) == 1
    noisier = make_system("linear", measurement_std=1.0).error_scale
    assert len(calls) == 2 and (noisier > first).all()


def test_a_wrapped_system_has_its_base_systems_scales():
    base = make_system("veh2dof")
    gappy = GappySystem(base, p_max=0.2, blackout_s=0.0, steps=50)
    for name in ("state_low", "state_high", "error_scale"):
        assert torch.equal(getattr(gappy, name), getattr(base, name))


@pytest.mark.parametrize("kind", ["DAOF-v1", "SLF"])
def test_a_learned_filter_keeps_the_scales_it_trained_with(kind, tmp_path):
    from daof.filters.learned import load_filter

    config = FilterConfig(kind=kind, system="veh2dof", window=2, num_cells=8)
    learned = LearnedFilter(config)
    assert torch.equal(learned.error_scale, learned.system.error_scale)
    learned.error_scale.mul_(2.0)  # as if the data had given other scales when it trained
    learned.save(tmp_path / "f.pt")
    assert torch.equal(load_filter(tmp_path / "f.pt").error_scale, learned.error_scale)


REPOSITORY = str(Path(__file__).resolve().parents[1])  # examples/ungm is imported from here


def test_the_ukfs_excess_error_is_none_where_it_is_consistent_and_large_where_it_is_sure_and_wrong(monkeypatch):
    """linear: the UKF is the Kalman filter, its P⁺ accounts for all its error; UNGM: the squared
    measurement hides the sign of x, the UKF's Gaussian posterior misses half of it."""
    monkeypatch.syspath_prepend(REPOSITORY)
    assert torch.equal(make_system("linear").scales().excess, torch.zeros(2))
    ungm = make_system("examples.ungm.system:UNGM").scales()
    assert ungm.source == "UKF" and (ungm.excess > 0.5 * ungm.error).all()


@pytest.mark.parametrize("name", ["linear", "examples.ungm.system:UNGM"])
def test_daof_v1s_bound_covers_the_excess_error_and_is_unchanged_without_one(name, monkeypatch):
    monkeypatch.syspath_prepend(REPOSITORY)
    from daof.filters.learned.daof_v1 import EXCESS_COVER
    from daof.filters.learned.network import SCHEDULE_STEPS
    from daof.train.schedules import ukf_schedule

    learned = LearnedFilter(FilterConfig(kind="DAOF-v1", system=name, window=2, num_cells=8, correction_sigmas=0.5))
    schedule = ukf_schedule(learned.system, seed=1)
    learned.set_schedules(schedule)
    claimed = schedule["estimate"].float()[:SCHEDULE_STEPS]
    claimed = torch.cat([claimed, claimed[-1:].expand(SCHEDULE_STEPS - len(claimed), -1)])
    narrow = 0.5 * torch.maximum(claimed, learned.error_scale)
    excess = learned.system.scales().excess
    if name == "linear":
        assert torch.equal(learned.correction_scale, narrow)
    else:
        assert torch.allclose(learned.correction_scale, (EXCESS_COVER * excess).expand_as(narrow))
        assert (learned.correction_scale > 2 * narrow).all()
