"""The classical baselines (daof.filters) against references written here from the textbook equations.

The EKF and the UKF below are written from the textbook recursions (EKF: linearise f at x̂_{t−1}
and g at x̂⁻_t; UKF: the additive-noise UKF with Julier's scaled sigma points and van der Merwe's
weights, sigma points redrawn from the prediction for the update), batched over runs in float64 torch,
with Jacobians by torch autograd. They use only what a model-based filter is given: the system's
f and g, the process- and measurement-noise covariances Q and R, and the prior (x̂_0, P_0); none of
the project's filter code. On fixed seeds of veh2dof (nominal) and linear, the project's
``EKF(system).run(data)`` and ``UKF(system).run(data)`` must match them: RMSE within 1 % and every
estimate within 1e-3 of the RMSE. A UKF or EKF run with 3×Q (a deliberate bug that the ±30 % bands
of test_classical_filters.py let through) is shown to fall outside that tolerance.

The particle filter's chunking over runs (``max_elements``) is checked against an unchunked run of
the same runs and seed.
"""

from __future__ import annotations

import copy
import inspect
import math
from contextlib import contextmanager

import pytest
import torch
from daof.envs.noise import GaussianMixtureNoise

from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter

F64 = torch.float64
RMSE_RTOL = 0.01  # the project's RMSE within 1 % of the reference's
ESTIMATE_TOL = 1e-3  # every estimate within 1e-3 × the reference RMSE of that state


# ----------------------------------------------------------------------------- reference filters
class Model:
    """f, g, Q, R, x̂_0, P_0 of a system in float64; Jacobians of f and g by autograd."""

    def __init__(self, system, q_scale: float = 1.0):
        self.system = copy.deepcopy(system).to(F64)  # the system's own f and g, evaluated in float64
        self.Q = q_scale * system.process_noise.covariance.to(F64)
        self.R = system.measurement_noise.covariance.to(F64)
        self.x0 = system.prior.mean.to(F64)
        self.P0 = system.prior.covariance.to(F64)
        self.n = system.state_dim

    def f(self, x, u):
        return self.system.f(x, u)

    def g(self, x, u):
        return self.system.g(x, u)

    @staticmethod
    def jacobian(fn, x, u):
        """∂fn/∂x at every row of x [runs, n] -> [runs, m, n]: rows are independent, so the gradient of
        Σ_runs fn_i is row by row the gradient of fn_i."""
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            y = fn(x, u)
            rows = [torch.autograd.grad(y[:, i].sum(), x, retain_graph=True)[0] for i in range(y.shape[-1])]
        return torch.stack(rows, 1)


def inputs(data):
    return (data[k].to(F64) for k in ("measurement", "prev_control", "control"))


def reference_ekf(model: Model, data) -> torch.Tensor:
    """EKF, for t = 1..T:
    x̂⁻ = f(x̂, u_{t−1}),  P⁻ = F P Fᵀ + Q with F = ∂f/∂x(x̂, u_{t−1});
    H = ∂g/∂x(x̂⁻, u_t),  S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,  x̂ = x̂⁻ + K (y_t − g(x̂⁻, u_t)),
    P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ (Joseph form)."""
    y, u_prev, u = inputs(data)
    runs, steps = y.shape[:2]
    x = model.x0.expand(runs, -1).clone()
    P = model.P0.expand(runs, -1, -1).clone()
    eye = torch.eye(model.n, dtype=F64)
    out = torch.empty(runs, steps, model.n, dtype=F64)
    for t in range(steps):
        F = model.jacobian(model.f, x, u_prev[:, t])
        x = model.f(x, u_prev[:, t])
        P = F @ P @ F.mT + model.Q
        H = model.jacobian(model.g, x, u[:, t])
        S = H @ P @ H.mT + model.R
        K = torch.linalg.solve(S, H @ P).mT  # P⁻ Hᵀ S⁻¹ (S and P⁻ symmetric)
        x = x + (K @ (y[:, t] - model.g(x, u[:, t]))[..., None])[..., 0]
        IKH = eye - K @ H
        P = IKH @ P @ IKH.mT + K @ model.R @ K.mT
        out[:, t] = x
    return out


#: the project's UKF defaults (its constructor signature): α = 1, β = 2, κ = 3 − n
UKF_ALPHA, UKF_BETA = 1.0, 2.0


def reference_ukf(model: Model, data, alpha=UKF_ALPHA, beta=UKF_BETA, kappa=None) -> torch.Tensor:
    """UKF for additive noise (Särkkä, Bayesian Filtering and Smoothing, 2013, §5.5) with the scaled
    sigma points of Julier (2002) and van der Merwe's weights:
    λ = α²(n + κ) − n; χ(m, P) = [m, m ± columns of √((n + λ) P)] (lower Cholesky factor);
    W_m = [λ/(n + λ), 1/(2(n + λ)) …], W_c = W_m + (1 − α² + β) on the centre point.
    Predict: χ_f = f(χ(x̂, P), u_{t−1}), x̂⁻ = Σ W_m χ_f, P⁻ = Σ W_c (χ_f − x̂⁻)(·)ᵀ + Q.
    Update, through new points χ⁻ = χ(x̂⁻, P⁻): Z = g(χ⁻, u_t), ẑ = Σ W_m Z, S = Σ W_c (Z − ẑ)(·)ᵀ + R,
    C = Σ W_c (χ⁻ − x̂⁻)(Z − ẑ)ᵀ, K = C S⁻¹, x̂ = x̂⁻ + K (y_t − ẑ), P = P⁻ − K S Kᵀ.
    (Passing the propagated χ_f through g instead would drop Q from S and C: not even exact on a
    linear system.)"""
    y, u_prev, u = inputs(data)
    runs, steps = y.shape[:2]
    n = model.n
    kappa = 3.0 - n if kappa is None else kappa
    lam = alpha**2 * (n + kappa) - n
    Wm = torch.full((2 * n + 1,), 1.0 / (2 * (n + lam)), dtype=F64)
    Wm[0] = lam / (n + lam)
    Wc = Wm.clone()
    Wc[0] += 1.0 - alpha**2 + beta
    x = model.x0.expand(runs, -1).clone()
    P = model.P0.expand(runs, -1, -1).clone()
    out = torch.empty(runs, steps, n, dtype=F64)

    def sigma_points(mean, cov):
        cols = torch.linalg.cholesky((n + lam) * cov).mT  # row i = column i of the lower factor
        return torch.cat([mean[:, None], mean[:, None] + cols, mean[:, None] - cols], 1)  # [runs, 2n+1, n]

    for t in range(steps):
        chi_f = model.f(sigma_points(x, P), u_prev[:, t, None].expand(-1, 2 * n + 1, -1))
        x_prior = torch.einsum("k,rkn->rn", Wm, chi_f)
        dx = chi_f - x_prior[:, None]
        P_prior = torch.einsum("k,rki,rkj->rij", Wc, dx, dx) + model.Q
        chi_u = sigma_points(x_prior, P_prior)  # fresh points: they carry Q's spread into the update
        Z = model.g(chi_u, u[:, t, None].expand(-1, 2 * n + 1, -1))
        z = torch.einsum("k,rkm->rm", Wm, Z)
        dz = Z - z[:, None]
        S = torch.einsum("k,rki,rkj->rij", Wc, dz, dz) + model.R
        C = torch.einsum("k,rki,rkj->rij", Wc, chi_u - x_prior[:, None], dz)
        K = torch.linalg.solve(S, C.mT).mT  # C S⁻¹
        x = x_prior + (K @ (y[:, t] - z)[..., None])[..., 0]
        P = P_prior - K @ S @ K.mT
        out[:, t] = x
    return out


def rmse(estimate, data):
    return (estimate.to(F64) - data["state"].to(F64)).pow(2).mean((0, 1)).sqrt()


def assert_matches_reference(estimate, reference, data, what=""):
    """RMSE within RMSE_RTOL of the reference's, and every estimate within ESTIMATE_TOL × that RMSE."""
    ref_rmse = rmse(reference, data)
    got = rmse(estimate, data)
    assert ((got / ref_rmse - 1).abs() <= RMSE_RTOL).all(), f"{what}: RMSE {got.tolist()} vs {ref_rmse.tolist()}"
    gap = (estimate.to(F64) - reference).abs().amax((0, 1))
    assert (gap <= ESTIMATE_TOL * ref_rmse).all(), f"{what}: max |x̂ − x̂_ref| {gap.tolist()} vs RMSE {ref_rmse.tolist()}"


# ----------------------------------------------------------------------------- data
@contextmanager
def one_thread():
    """Module fixtures are set up before conftest's per-test single-thread fixture; on a loaded
    machine a second OpenMP thread makes each tiny batched solve ~100× slower."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


@pytest.fixture(scope="module")
def veh_data(veh):
    with one_thread():
        return veh.simulate(8, 300, seed=4242)


@pytest.fixture(scope="module")
def lin_data(lin):
    with one_thread():
        return lin.simulate(8, 200, seed=4343)


@pytest.fixture(scope="module")
def veh_references(veh, veh_data):
    with one_thread():
        model = Model(veh)
        return {"EKF": reference_ekf(model, veh_data), "UKF": reference_ukf(model, veh_data)}


def test_ukf_defaults_are_the_ones_the_reference_uses():
    params = inspect.signature(UKF).parameters
    assert params["alpha"].default == UKF_ALPHA and params["beta"].default == UKF_BETA
    assert params["kappa"].default is None  # κ = 3 − n (the UKF's docstring)


def test_references_agree_with_the_exact_kalman_filter_on_linear(lin, lin_data):
    """Self-check of the references: on a linear-Gaussian system EKF = UKF = Kalman filter exactly,
    here the closed-form recursion with A, B, C (to rounding)."""
    model = Model(lin)
    A, B, C = (m.to(F64) for m in (lin.A, lin.B, lin.C))
    y, u_prev, _ = inputs(lin_data)
    x, P = model.x0.expand(y.shape[0], -1).clone(), model.P0.clone()
    kf = []
    for t in range(y.shape[1]):
        x = x @ A.T + u_prev[:, t] @ B.T
        P = A @ P @ A.T + model.Q
        K = P @ C.T @ torch.linalg.inv(C @ P @ C.T + model.R)
        x = x + (y[:, t] - x @ C.T) @ K.T
        P = (torch.eye(2, dtype=F64) - K @ C) @ P
        kf.append(x)
    kf = torch.stack(kf, 1)
    torch.testing.assert_close(reference_ekf(model, lin_data), kf, rtol=0, atol=1e-10)
    torch.testing.assert_close(reference_ukf(model, lin_data), kf, rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", ["EKF", "UKF", "KF"])
def test_project_filters_match_the_references_on_linear(lin, lin_data, name):
    reference = reference_ekf(Model(lin), lin_data)  # = the exact KF (test above)
    filt = {"EKF": EKF, "UKF": UKF, "KF": KalmanFilter}[name](lin)
    assert_matches_reference(filt.run(lin_data), reference, lin_data, name)
    assert filt.stats == {"repairs": 0, "diverged": 0}


@pytest.mark.parametrize("name", ["EKF", "UKF"])
def test_project_filters_match_the_references_on_veh2dof(veh, veh_data, veh_references, name):
    filt = {"EKF": EKF, "UKF": UKF}[name](veh)
    estimate = filt.run(veh_data)
    assert estimate.shape == veh_data["state"].shape
    assert_matches_reference(estimate, veh_references[name], veh_data, name)
    assert filt.stats == {"repairs": 0, "diverged": 0}


def with_process_noise_scaled(system, factor: float):
    """A copy of veh2dof whose process noise has ``factor`` × its covariance (each axis scale × √factor)."""
    p = system.p
    mutant = copy.deepcopy(system)
    mutant.process_noise = GaussianMixtureNoise(
        p.mixture_weights, p.mixture_means, p.mixture_stds, [s * math.sqrt(factor) for s in p.process_scale]
    )
    torch.testing.assert_close(mutant.process_noise.covariance, factor * system.process_noise.covariance)
    return mutant


@pytest.mark.parametrize("name", ["EKF", "UKF"])
def test_a_filter_run_with_3x_q_is_outside_the_tolerance(veh, veh_data, veh_references, name):
    """The mutation "the baseline runs with 3×Q" is caught: the project's filter on a copy of the
    system with the process noise's covariance tripled fails ``assert_matches_reference`` against the
    reference with the true Q, and already its RMSE alone is more than 1 % off; the reference run with
    3×Q reproduces the mutant (so the gap is the Q, not the implementation)."""
    mutant = with_process_noise_scaled(veh, 3.0)
    estimate = {"EKF": EKF, "UKF": UKF}[name](mutant).run(veh_data)
    with pytest.raises(AssertionError):
        assert_matches_reference(estimate, veh_references[name], veh_data, name)
    change = rmse(estimate, veh_data) / rmse(veh_references[name], veh_data) - 1
    assert (change.abs() > RMSE_RTOL).any(), change
    model = Model(veh, q_scale=3.0)
    reference_3q = (reference_ekf if name == "EKF" else reference_ukf)(model, veh_data)
    assert_matches_reference(estimate, reference_3q, veh_data, f"{name} 3Q")


# ----------------------------------------------------------------------------- particle filter chunking
def test_pf_first_chunk_and_a_single_chunk_are_the_unchunked_filter(veh, veh_data):
    """``ParticleFilter`` splits the runs into chunks of ``max_elements // num_particles`` runs (at least
    one) and drives them in order with one generator seeded by ``seed``. So, bit for bit:
    a single chunk that holds every run is the unchunked filter, and the first chunk of a chunked run
    is the unchunked filter on those runs alone (the later chunks continue the generator's stream)."""
    data = veh_data[:5, :60]
    n = 400
    unchunked = ParticleFilter(veh, num_particles=n, seed=3).run(data)
    one_chunk = ParticleFilter(veh, num_particles=n, seed=3, max_elements=5 * n).run(data)
    assert torch.equal(one_chunk, unchunked)
    for per_chunk, max_elements in ((2, 2 * n + n // 2), (1, n // 3)):  # 2 runs a chunk; fewer than N: 1
        chunked = ParticleFilter(veh, num_particles=n, seed=3, max_elements=max_elements).run(data)
        assert chunked.shape == data["state"].shape and torch.isfinite(chunked).all()
        first = ParticleFilter(veh, num_particles=n, seed=3).run(data[:per_chunk])
        assert torch.equal(chunked[:per_chunk], first), per_chunk
        assert not torch.equal(chunked, unchunked)  # the later chunks draw other particles


def test_pf_every_chunk_filters_its_own_runs(veh, veh_data):
    """One run per chunk vs unchunked (same runs, same seed), 6 runs × 150 steps, N = 2000: the two
    differ only by Monte Carlo error, which is small against the estimation error: per run and state,
    the RMS difference is below 0.25 × the RMSE against the truth (measured ≈ 0.05). Pairing each
    chunked run with a neighbouring unchunked run (a shuffled or shifted concatenation of the chunks)
    gives a difference of the order of the states themselves, far above that."""
    data = veh_data[:6, :150]
    n = 2000
    pf = ParticleFilter(veh, num_particles=n, seed=8)
    unchunked = pf.run(data)
    chunked_pf = ParticleFilter(veh, num_particles=n, seed=8, max_elements=n)
    chunked = chunked_pf.run(data)
    assert chunked_pf.stats["diverged"] == 0 and chunked_pf.stats["resamples"] > 0
    truth = data["state"]
    error = (unchunked - truth).pow(2).mean(1).sqrt()  # [runs, state]
    gap = (chunked - unchunked).pow(2).mean(1).sqrt()
    assert (gap < 0.25 * error).all(), gap / error
    shifted = (chunked.roll(1, 0) - unchunked).pow(2).mean(1).sqrt()
    assert (shifted > 1.0 * error).all(), shifted / error
