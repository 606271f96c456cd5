"""Systems (envs.vehicle2dof, envs.linear, envs.registry): the models against hand-computed values,
simulation shapes and seeding, scenarios, and the spec's order-of-magnitude reference figures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from daof.envs import make_system
from daof.envs.system import StochasticSystem

# Spec parameters, written out again here so the hand computation does not read the implementation.
M, IZ, LF, LR, VX, G = 1412.0, 1536.7, 1.06, 1.85, 20.0, 9.81
MU, BF, CF, EF, DT = 0.9, 10.0, 1.3, 0.97, 0.02


def hand_veh2dof(x, u, mu=MU, B=BF, vx=VX):
    """Spec formulas in plain math: returns (f(x, u), g(x, u)) as lists of floats."""
    beta, r = x
    delta = u
    fzf = M * G * LR / (LF + LR)
    fzr = M * G * LF / (LF + LR)

    def tyre(alpha, fz):
        ba = B * alpha
        return -mu * fz * math.sin(CF * math.atan(ba - EF * (ba - math.atan(ba))))

    fyf = tyre(beta + LF * r / vx - delta, fzf)
    fyr = tyre(beta - LR * r / vx, fzr)
    beta_dot = (fyf * math.cos(delta) + fyr) / (M * vx) - r
    r_dot = (LF * fyf * math.cos(delta) - LR * fyr) / IZ
    a_y = (fyf * math.cos(delta) + fyr) / M
    return [beta + DT * beta_dot, r + DT * r_dot], [a_y, r]


CASES = [  # (β, r), δ_f: straight, moderate cornering, near the tyre peak, counter-steer
    ((0.0, 0.0), 0.0),
    ((0.01, 0.1), 0.03),
    ((-0.02, 0.3), -0.05),
    ((0.05, -0.4), 0.06),
]


# ----------------------------------------------------------------------------- veh2dof model
def test_veh2dof_f_and_g_match_the_spec_formulas():
    system = make_system("veh2dof")
    x = torch.tensor([c[0] for c in CASES])
    u = torch.tensor([[c[1]] for c in CASES])
    f, g = system.f(x, u), system.g(x, u)
    assert f.shape == (len(CASES), 2) and g.shape == (len(CASES), 2)
    for i, (xi, ui) in enumerate(CASES):
        f_hand, g_hand = hand_veh2dof(xi, ui)
        np.testing.assert_allclose(f[i].numpy(), f_hand, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(g[i].numpy(), g_hand, rtol=1e-5, atol=1e-5)
    # At rest with straight wheels nothing moves; steering left (δ_f > 0) accelerates to the left.
    assert f[0].abs().max() == 0 and g[0].abs().max() == 0
    assert float(g[1, 0]) > 0


def test_veh2dof_f_g_broadcast_over_leading_dims():
    system = make_system("veh2dof")
    x = torch.tensor([[0.01, 0.1]]).expand(3, 4, 2)
    u = torch.tensor([[0.03]]).expand(3, 4, 1)
    f = system.f(x, u)
    assert f.shape == (3, 4, 2)
    np.testing.assert_allclose(f[2, 3].numpy(), hand_veh2dof((0.01, 0.1), 0.03)[0], rtol=1e-5)


def test_veh2dof_overrides_change_the_model():
    system = make_system("veh2dof", mu=0.5, vx=15.0)
    x, u = torch.tensor([0.01, 0.1]), torch.tensor([0.03])
    # v_x enters through the slip angles and β̇, μ through the peak force.
    f_hand, g_hand = hand_veh2dof((0.01, 0.1), 0.03, mu=0.5, vx=15.0)
    np.testing.assert_allclose(system.f(x, u).numpy(), f_hand, rtol=1e-5)
    np.testing.assert_allclose(system.g(x, u).numpy(), g_hand, rtol=1e-5)


# ----------------------------------------------------------------------------- linear model
def test_linear_zoh_matrices_match_scipy_expm():
    system = make_system("linear")
    p = system.p
    Ac = np.array([[0.0, 1.0], [-(p.omega**2), -2 * p.zeta * p.omega]])
    Bc = np.array([[0.0], [1.0]])
    A = scipy.linalg.expm(Ac * p.dt)
    B = np.linalg.solve(Ac, (A - np.eye(2)) @ Bc)  # ∫₀^Δτ e^{Ac s} ds Bc, Ac invertible
    np.testing.assert_allclose(system.A.numpy(), A, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(system.B.numpy(), B, rtol=1e-5, atol=1e-8)
    x = torch.tensor([[1.0, -2.0], [0.3, 0.5]])
    u = torch.tensor([[0.5], [-1.0]])
    expected_f = x.double().numpy() @ A.T + u.double().numpy() @ B.T
    np.testing.assert_allclose(system.f(x, u).numpy(), expected_f, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(system.g(x, u).numpy(), x[:, :1].numpy())


# ----------------------------------------------------------------------------- simulate
@pytest.mark.parametrize("name", ["veh2dof", "linear"])
def test_simulate_shapes_dtype_and_seeding(name):
    system = make_system(name)
    data = system.simulate(runs=3, steps=7, seed=11)
    assert data.batch_size == (3, 7)
    n, m, c = system.state_dim, system.measurement_dim, system.control_dim
    for key, dim in [("state", n), ("measurement", m), ("control", c), ("prev_control", c)]:
        assert data[key].shape == (3, 7, dim), key
        assert data[key].dtype == torch.float32, key
    # Controls are a known schedule: prev_control at step t is control at step t−1.
    torch.testing.assert_close(data["prev_control"][:, 1:], data["control"][:, :-1])
    again = system.simulate(runs=3, steps=7, seed=11)
    other = system.simulate(runs=3, steps=7, seed=12)
    for key in ("state", "measurement", "control"):
        assert torch.equal(data[key], again[key]), key
        assert not torch.equal(data[key], other[key]), key
    # Different runs of one call are different episodes.
    assert not torch.equal(data["state"][0], data["state"][1])
    with pytest.raises(ValueError, match="runs >= 1"):
        system.simulate(runs=0, steps=5, seed=0)


def test_veh2dof_steering_schedule_is_in_the_spec_range():
    system = make_system("veh2dof")
    sim = system.reset_episode(2000, torch.Generator().manual_seed(0))
    amp = torch.rad2deg(sim["params", "amplitude"])
    period = sim["params", "period"]
    assert 2.0 <= amp.min() and amp.max() <= 3.5 and amp.min() < 2.05 and amp.max() > 3.45
    assert 3.0 <= period.min() and period.max() <= 6.0
    t = torch.arange(0, 500)
    params = sim["params"][:1].expand(500)
    delta = system.control(t, params)[:, 0]
    a, P, phi = (float(sim["params", k][0]) for k in ("amplitude", "period", "phase"))
    expected = [a * math.sin(2 * math.pi * k * DT / P + phi) for k in range(500)]
    np.testing.assert_allclose(delta.numpy(), expected, atol=1e-6)


def test_veh2dof_state_and_measurement_magnitudes_match_the_spec_reference():
    data = make_system("veh2dof").simulate(runs=40, steps=500, seed=3)
    state = data["state"].double()
    # Spec reference: state std over an episode about [0.04 rad, 0.26 rad/s] (order of magnitude).
    std = state.std(dim=1).mean(0)
    for got, ref in zip(std.tolist(), (0.04, 0.26)):
        assert 0.6 * ref < got < 1.5 * ref, (got, ref)
    # Raw yaw-rate measurement error: Laplace b = 0.1 → RMSE √2·0.1 ≈ 0.141 (spec: about 0.14).
    err2 = (data["measurement"][..., 1].double() - state[..., 1]) ** 2
    se = float(err2.std()) / math.sqrt(err2.numel())
    assert abs(float(err2.mean()) - 2 * 0.1**2) < 5 * se
    assert float(err2.mean().sqrt()) == pytest.approx(0.14, rel=0.05)


# ----------------------------------------------------------------------------- scenarios
def _true_step(system, x, u, params, seed):
    """x_{t+1} − ξ_t: replay the noise draw from the same generator state to isolate f_true."""
    x_next = system.transition(x, u, params, torch.Generator().manual_seed(seed))
    xi = system.process_noise.sample(x.shape[:-1], torch.Generator().manual_seed(seed))
    return x_next - xi


def test_mismatch_draws_mu_and_B_per_run_while_the_model_stays_nominal():
    runs = 4000
    system = make_system("veh2dof", "mismatch")
    nominal = make_system("veh2dof")
    sim = system.reset_episode(runs, torch.Generator().manual_seed(1))
    mu, B = sim["params", "mu"], sim["params", "B"]
    assert 0.7 <= mu.min() and mu.max() <= 1.0 and 8.0 <= B.min() and B.max() <= 12.0
    # Uniform: mean and std of U[a, b] are (a+b)/2 and (b−a)/√12; 5 standard errors.
    for v, lo, hi in ((mu, 0.7, 1.0), (B, 8.0, 12.0)):
        assert abs(float(v.mean()) - (lo + hi) / 2) < 5 * (hi - lo) / math.sqrt(12 * runs)
        assert float(v.std()) == pytest.approx((hi - lo) / math.sqrt(12), rel=0.05)
    assert abs(float(torch.corrcoef(torch.stack([mu, B]))[0, 1])) < 5 / math.sqrt(runs)
    # Filters see the nominal model (μ = 0.9, B = 10) ...
    x = torch.tensor([[0.02, 0.3]]).expand(runs, 2)
    u = torch.tensor([[0.05]]).expand(runs, 1)
    torch.testing.assert_close(system.f(x, u), nominal.f(x, u))
    torch.testing.assert_close(system.g(x, u), nominal.g(x, u))
    # ... while the true dynamics of each run use its own μ and B.
    f_true = _true_step(system, x[:3], u[:3], sim["params"][:3], seed=5)
    for i in range(3):
        f_hand, _ = hand_veh2dof((0.02, 0.3), 0.05, mu=float(mu[i]), B=float(B[i]))
        np.testing.assert_allclose(f_true[i].numpy(), f_hand, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(f_true, nominal.f(x[:3], u[:3]), rtol=1e-4, atol=0)


def test_nominal_true_dynamics_equal_the_model():
    system = make_system("veh2dof")
    sim = system.reset_episode(3, torch.Generator().manual_seed(1))
    x, u = torch.tensor([[0.02, 0.3]]).expand(3, 2), torch.tensor([[0.05]]).expand(3, 1)
    torch.testing.assert_close(_true_step(system, x, u, sim["params"], seed=5), system.f(x, u))
    torch.testing.assert_close(sim["params", "mu"], torch.full((3,), 0.9))


def test_outliers_scenario_has_gross_errors_at_five_percent():
    system = make_system("veh2dof", "outliers")
    data = system.simulate(runs=50, steps=200, seed=4)
    residual = data["measurement"] - system.g(data["state"], data["control"])
    b = torch.tensor([1.5, 0.1])
    # |ζ| > 5b: P = p(1 − (e⁻⁵ − e⁻¹⁵)/2) + (1 − p)e⁻⁵ ≈ 0.0562 with p = 0.05 (e⁻⁵ from the Laplace tail).
    p = 0.05
    rate = p * (1 - 0.5 * (math.exp(-5) - math.exp(-15))) + (1 - p) * math.exp(-5)
    n = residual.shape[0] * residual.shape[1]
    frac = (residual.abs() > 5 * b).double().reshape(-1, 2).mean(0)
    assert ((frac - rate).abs() < 5 * math.sqrt(rate * (1 - rate) / n)).all(), frac
    # The nominal scenario has only the Laplace tail: e⁻⁵ ≈ 0.0067.
    clean = make_system("veh2dof").simulate(runs=50, steps=200, seed=4)
    residual = clean["measurement"] - system.g(clean["state"], clean["control"])
    frac = (residual.abs() > 5 * b).double().reshape(-1, 2).mean(0)
    tail = math.exp(-5)
    assert ((frac - tail).abs() < 5 * math.sqrt(tail * (1 - tail) / n)).all(), frac


# ----------------------------------------------------------------------------- registry
def test_make_system_returns_the_named_system():
    for name in ("veh2dof", "linear"):
        system = make_system(name)
        assert isinstance(system, StochasticSystem) and system.name == name
    system = make_system("veh2dof", "outliers", outlier_prob=0.1)
    assert system.scenario == "outliers" and system.measurement_noise.prob == 0.1


def test_make_system_rejects_unknown_name_scenario_or_override():
    with pytest.raises(ValueError, match=r"unknown system 'veh3dof'.*linear.*veh2dof"):
        make_system("veh3dof")
    with pytest.raises(ValueError, match=r"unknown scenario 'icy'.*nominal.*mismatch.*outliers"):
        make_system("veh2dof", "icy")
    with pytest.raises(ValueError, match=r"unknown scenario 'mismatch'.*\['nominal'\]"):
        make_system("linear", "mismatch")
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['friction'\].*'mu'"):
        make_system("veh2dof", friction=0.5)
