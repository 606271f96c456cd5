"""Classical baselines (daof.filters): KF, EKF, UKF, bootstrap PF.

Pins down: the EKF Jacobians (vs finite differences) and the numpy model (vs the torch system);
systematic resampling identical to filterpy's; the KF at its stationary Riccati RMSE on
``linear``; EKF/UKF/PF equal the KF there; veh2dof RMSEs in the ballpark of the spec's prototype figures;
the counted covariance repair; divergence kept as NaN; input validation.
"""

import numpy as np
import pytest
import torch
from daof.envs import make_system
from daof.envs.linear import stationary_kalman_covariance
from filterpy.monte_carlo import systematic_resample as filterpy_systematic_resample

from daof.filters import (
    EKF,
    UKF,
    CovarianceRepair,
    JointParameterPF,
    KalmanFilter,
    ParticleFilter,
    StationaryKalmanFilter,
    systematic_resample,
)
from daof.filters.kalman import make_model

# the spec's prototype reference RMSE [β rad, r rad/s] (prototype figures, order of magnitude only)
UKF_REFERENCE = torch.tensor([0.0104, 0.0263])
PF_REFERENCE = torch.tensor([0.0093, 0.0232])


@pytest.fixture(scope="module")
def veh_data(veh):
    return veh.simulate(8, 500, seed=101)


@pytest.fixture(scope="module")
def lin_data(lin):
    return lin.simulate(100, 300, seed=202)


def rmse(estimate, data, burn_in=0):
    return (estimate - data["state"])[:, burn_in:].pow(2).mean((0, 1)).sqrt()


# ----------------------------------------------------------------------------- models
def test_numpy_model_and_jacobians_match_torch_and_finite_differences(veh):
    """f, g of the numpy transcription equal the torch system; F, H equal central differences."""
    numpy_model, torch_model = make_model(veh, "numpy"), make_model(veh, "torch")
    rng = np.random.default_rng(0)
    h = 1e-6
    for _ in range(5):
        x = rng.normal(0, [0.05, 0.3])
        u = rng.normal(0, [0.05])
        for fn, jac in (("f", "F"), ("g", "H")):
            value = getattr(numpy_model, fn)(x, u)
            np.testing.assert_allclose(value, getattr(torch_model, fn)(x, u), rtol=1e-12, atol=1e-14)
            fd = np.stack(
                [
                    (getattr(torch_model, fn)(x + h * e, u) - getattr(torch_model, fn)(x - h * e, u)) / (2 * h)
                    for e in np.eye(2)
                ],
                -1,
            )
            scale = np.abs(fd).max()
            np.testing.assert_allclose(getattr(numpy_model, jac)(x, u), fd, atol=1e-6 * scale)
            np.testing.assert_allclose(getattr(torch_model, jac)(x, u), fd, atol=1e-6 * scale)


def test_linear_model_jacobians_are_the_system_matrices(lin):
    model = make_model(lin, "numpy")
    x, u = np.array([0.3, -1.0]), np.array([0.5])
    np.testing.assert_allclose(model.F(x, u), lin.A.double().numpy(), atol=1e-15)
    np.testing.assert_allclose(model.H(x, u), lin.C.double().numpy(), atol=1e-15)


# ----------------------------------------------------------------------------- resampling
@pytest.mark.parametrize("n", [1, 7, 100, 5000])
def test_systematic_resample_equals_filterpy_on_the_same_uniform(n):
    rng = np.random.default_rng(n)
    rows = [rng.random(n), rng.random(n) ** 20, np.eye(n)[n // 2] + 1e-12]  # plain, peaked, degenerate
    weights = np.stack([w / w.sum() for w in rows])
    expected, uniforms = [], []
    for i, w in enumerate(weights):
        np.random.seed(i)  # filterpy draws its one uniform from numpy's global generator
        expected.append(filterpy_systematic_resample(w))
        np.random.seed(i)
        uniforms.append(np.random.random())
    got = systematic_resample(torch.from_numpy(weights).float(), torch.tensor(uniforms))
    np.testing.assert_array_equal(got.numpy(), np.stack(expected))


# ----------------------------------------------------------------------------- linear system
def test_kalman_filter_reaches_the_stationary_riccati_rmse(lin, lin_data):
    """After the transient, the KF's pooled RMSE is sqrt(diag P⁺) of the stationary Riccati solution."""
    _, P_post = stationary_kalman_covariance(
        lin.A, lin.C, lin.process_noise.covariance, lin.measurement_noise.covariance
    )
    kf = KalmanFilter(lin)
    estimate = kf.run(lin_data)
    assert estimate.dtype == torch.float32 and estimate.shape == lin_data["state"].shape
    theory = P_post.diagonal().sqrt().float()
    torch.testing.assert_close(rmse(estimate, lin_data, burn_in=100), theory, rtol=0.04, atol=0)
    assert kf.stats == {"repairs": 0, "diverged": 0}


def test_ekf_ukf_equal_the_kalman_filter_on_a_linear_system(lin, lin_data):
    data = lin_data[:5, :100]
    reference = KalmanFilter(lin, dtype=torch.float64).run(data)
    assert reference.dtype == torch.float64
    for filt in (EKF(lin, dtype=torch.float64), UKF(lin, dtype=torch.float64), EKF(lin, model="torch")):
        torch.testing.assert_close(filt.run(data).double(), reference, rtol=1e-5, atol=1e-6)


def test_stationary_kalman_filter_is_the_kalman_filter_after_its_start_up(lin, lin_data):
    """Its gain is the exact filter's limit; it pays only in the start-up, where the prior is wide."""
    data = lin_data[:20]
    exact = KalmanFilter(lin, dtype=torch.float64).run(data)
    stationary = StationaryKalmanFilter(lin).run(data)
    assert stationary.dtype == torch.float32 and stationary.shape == exact.shape
    torch.testing.assert_close(stationary[:, 150:].double(), exact[:, 150:], rtol=0, atol=1e-5)
    start_exact, start_stationary = rmse(exact[:, :20], data[:, :20]), rmse(stationary[:, :20].double(), data[:, :20])
    assert (start_stationary > 1.2 * start_exact).all()


def test_stationary_kalman_filter_only_predicts_without_a_measurement(lin, lin_data, veh):
    data = lin_data[:3, :40].clone()
    data["measurement"][:, 10:] = float("nan")
    estimate = StationaryKalmanFilter(lin).run(data).double()
    A, B = lin.A.double(), lin.B.double()
    predicted = estimate[:, 9]
    for t in range(10, 40):
        predicted = predicted @ A.T + data["prev_control"][:, t].double() @ B.T
        torch.testing.assert_close(estimate[:, t], predicted, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="needs a linear system"):
        StationaryKalmanFilter(veh)


def test_particle_filter_matches_the_kalman_filter_on_linear(lin, lin_data):
    data = lin_data[:50]
    kf = rmse(KalmanFilter(lin).run(data), data, burn_in=100)
    pf = ParticleFilter(lin, num_particles=2000, seed=1)
    torch.testing.assert_close(rmse(pf.run(data), data, burn_in=100), kf, rtol=0.03, atol=0)
    assert pf.stats["diverged"] == 0 and pf.stats["resamples"] > 0


# ----------------------------------------------------------------------------- veh2dof
def test_kalman_filters_on_veh2dof_are_in_the_spec_ballpark(veh, veh_data):
    raw_yaw_rate = (veh_data["measurement"][..., 1] - veh_data["state"][..., 1]).pow(2).mean().sqrt()
    for filt in (EKF(veh), UKF(veh)):
        error = rmse(filt.run(veh_data), veh_data)
        assert error[1] < 0.5 * raw_yaw_rate, filt.name
        torch.testing.assert_close(error, UKF_REFERENCE, rtol=0.3, atol=0, msg=filt.name)
        assert filt.stats == {"repairs": 0, "diverged": 0}


def test_particle_filter_on_veh2dof_is_in_the_spec_ballpark(veh, veh_data):
    pf = ParticleFilter(veh, num_particles=1000, seed=5)
    estimate = pf.run(veh_data)
    torch.testing.assert_close(rmse(estimate, veh_data), PF_REFERENCE, rtol=0.3, atol=0)
    # same seed, same data -> the same estimates
    torch.testing.assert_close(ParticleFilter(veh, num_particles=1000, seed=5).run(veh_data), estimate)


def test_particle_filter_chunks_runs(veh, veh_data):
    data = veh_data[:3, :50]
    pf = ParticleFilter(veh, num_particles=200, seed=0, max_elements=200)  # one run per chunk
    estimate = pf.run(data)
    assert estimate.shape == (3, 50, 2) and torch.isfinite(estimate).all()
    assert rmse(estimate, data)[1] < 0.1


def test_joint_parameter_pf_infers_mu_and_b_and_beats_the_nominal_model_under_mismatch():
    """On ``mismatch`` the PF that infers μ, B (from the scenario's prior) beats the nominal-model PF on β,
    and its final μ estimate is much closer to each run's true μ than the prior's mean is."""
    system = make_system("veh2dof", scenario="mismatch")
    data = system.simulate(8, 300, seed=11)
    true = system.reset_episode(8, torch.Generator().manual_seed(11))["params"]  # simulate's first draw
    joint = JointParameterPF(system, num_particles=2000, seed=0)
    estimate = joint.run(data)
    assert estimate.shape == (8, 300, 2) and joint.parameter_estimates.shape == (8, 300, 2)
    nominal = ParticleFilter(system, num_particles=2000, seed=0).run(data)
    assert rmse(estimate, data)[0] < 0.9 * rmse(nominal, data)[0]
    mu_error = (joint.parameter_estimates[:, -1, 0] - true["mu"]).abs().mean()
    prior_error = (true["mu"] - 0.85).abs().mean()  # the prior mean's error on the same runs
    assert mu_error < 0.6 * prior_error, (mu_error, prior_error)
    # the chunked path (one run per chunk) works too: the parameters ride in the particles
    chunked = JointParameterPF(system, num_particles=2000, seed=0, max_elements=2000).run(data[:2])
    assert torch.isfinite(chunked).all()


def test_joint_parameter_pf_refuses_a_scenario_without_uncertain_parameters(veh):
    with pytest.raises(ValueError, match="no uncertain model parameters"):
        JointParameterPF(veh)


# ----------------------------------------------------------------------------- numerics
def test_covariance_repair_makes_pd_and_counts():
    repair = CovarianceRepair()
    good = np.array([[2.0, 0.5], [0.5, 1.0]])
    assert repair(good) is good and repair.count == 0
    bad = np.array([[1.0, 0.0], [0.0, -1e-8]]) + np.array([[0.0, 1e-12], [0.0, 0.0]])
    fixed = repair(bad)
    assert repair.count == 1
    np.linalg.cholesky(fixed)
    np.testing.assert_allclose(fixed, fixed.T)
    np.testing.assert_allclose(fixed, bad, atol=1e-7)


@pytest.mark.parametrize("cls", [EKF, UKF, KalmanFilter])
def test_a_non_pd_covariance_is_repaired_and_counted(cls, veh, lin, veh_data, lin_data):
    system, data = (lin, lin_data) if cls is KalmanFilter else (veh, veh_data)
    data = data[:2, :50]
    filt = cls(system)
    eigenvalues, vectors = np.linalg.eigh(filt.P0)
    eigenvalues[0] = -1e-6 * eigenvalues[-1]  # inject a tiny negative eigenvalue into P_0
    filt.P0 = vectors @ np.diag(eigenvalues) @ vectors.T
    estimate = filt.run(data)
    assert filt.stats["repairs"] >= 2  # once per run
    assert filt.stats["diverged"] == 0 and torch.isfinite(estimate).all()


@pytest.mark.parametrize(
    "make", [UKF, EKF, lambda s: ParticleFilter(s, 100), lambda s: ParticleFilter(s, 100, resample="always")]
)
def test_a_run_that_goes_non_finite_is_kept_as_nan(make, veh, veh_data):
    data = veh_data[:3, :40].clone()
    clean = make(veh).run(data)
    filt = make(veh)
    if isinstance(filt, ParticleFilter):
        # so far off (finite, but |ζ|/b overflows float32) that every particle has zero likelihood
        data["measurement"][1, 10, 1] = 3e38
    else:
        # an inf measurement is rejected up front (test_missing_measurements.py), so break the
        # estimate itself: run 1, step 10 of the filter's own loop leaves a NaN state behind
        step, calls = filt._step, iter(range(10**9))

        def broken_step(kf, *args):
            step(kf, *args)
            if next(calls) == 40 + 10:
                kf.x[:] = np.nan

        filt._step = broken_step
    estimate = filt.run(data)
    assert filt.stats["diverged"] == 1
    assert torch.isnan(estimate[1, 10:]).all() and torch.isfinite(estimate[1, :10]).all()
    if not isinstance(filt, ParticleFilter):  # runs are independent in the Kalman filters
        torch.testing.assert_close(estimate[[0, 2]], clean[[0, 2]])


def bad_inputs(data):
    cases = {"missing": data.exclude("control"), "ints": data.clone(), "nan control": data.clone()}
    cases["ints"]["measurement"] = data["measurement"].long()
    cases["nan control"]["prev_control"][0, 3, 0] = float("nan")
    wide = data.clone()
    wide["measurement"] = torch.cat([data["measurement"], data["measurement"][..., :1]], -1)
    cases["wide"] = wide
    short = data.clone(False)
    short.batch_size = []
    short["control"] = data["control"][:, :-1]
    cases["short"] = short
    return cases


@pytest.mark.parametrize("make", [UKF, EKF, lambda s: ParticleFilter(s, 10)])
@pytest.mark.parametrize("case", ["missing", "ints", "nan control", "wide", "short"])
def test_bad_input_raises_value_error(make, case, veh, veh_data):
    data = bad_inputs(veh_data[:2, :5])[case]
    with pytest.raises(ValueError):
        make(veh).run(data)


def test_kalman_filter_refuses_a_nonlinear_system(veh):
    with pytest.raises(ValueError):
        KalmanFilter(veh)


# ----------------------------------------------------------------------------- long checks
@pytest.mark.slow
def test_oracle_ordering_on_veh2dof(veh):
    """PF with 10^4 particles ≤ PF-1000 ≈ oracle < UKF; adaptive resampling does not hurt."""
    data = veh.simulate(20, 500, seed=303)
    ukf = rmse(UKF(veh).run(data), data)
    pf = rmse(ParticleFilter(veh, 1000, seed=1).run(data), data)
    pf_always = rmse(ParticleFilter(veh, 1000, seed=1, resample="always").run(data), data)
    oracle = rmse(ParticleFilter(veh, 10_000, seed=1).run(data), data)
    assert (oracle < ukf).all()
    torch.testing.assert_close(pf, oracle, rtol=0.02, atol=0)
    torch.testing.assert_close(pf, pf_always, rtol=0.02, atol=0)


@pytest.mark.parametrize("make", [KalmanFilter, UKF])
def test_covariance_schedule_on_linear_is_the_riccati_recursion_from_the_prior(make, lin):
    """On a linear-Gaussian system P⁻_t, P⁺_t, S_t, K_t do not depend on the data: the schedule is the recursion."""
    A, C = lin.A.double(), lin.C.double()
    Q, R = lin.process_noise.covariance.double(), lin.measurement_noise.covariance.double()
    P, rows = lin.prior.covariance.double(), {"update": [], "prediction": [], "estimate": [], "innovation": []}
    gains = []
    for _ in range(12):
        prior = A @ P @ A.T + Q
        S = C @ prior @ C.T + R
        gains.append(prior @ C.T @ torch.linalg.inv(S))
        P = prior - gains[-1] @ C @ prior
        for key, cov in (("update", prior - P), ("prediction", prior), ("estimate", P), ("innovation", S)):
            rows[key].append(cov.diagonal().sqrt())
    schedule = make(lin).covariance_schedule(lin.simulate(3, 12, seed=4))
    rows["gain"] = gains
    for key, expected in rows.items():
        torch.testing.assert_close(schedule[key], torch.stack(expected), rtol=1e-6, atol=1e-9, msg=key)
    assert (schedule["estimate"][0] < lin.prior.covariance.diagonal().sqrt()).all()  # the first update shrinks P
