"""Missing measurements (NaN channels) in the classical filters, and their input validation.

Pins down (docs/missing_data.md): the per-channel noise densities the PF weights with; every
classical filter stays finite under random gaps and is untouched before the first gap; updating
with the present channels only is the filter of the reduced sensor set (EKF, UKF, PF against a
yaw-rate-only vehicle, KF against the position-only oscillator and a hand-written KF that skips
updates); a step with nothing present only predicts; one channel always missing still tracks;
inf measurements, non-finite controls, wrong shapes and dtypes give one clear ValueError each.
"""

import math

import daof.envs as envs
import numpy as np
import pytest
import torch
from daof.envs.noise import GaussianMixtureNoise, GaussianNoise, LaplaceNoise, OutlierLaplaceNoise
from daof.envs.vehicle2dof import Vehicle2DOF
from torch import distributions as D

from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter

NAN = math.nan
GAPS_FROM = 100  # test data: every step before this one has every channel


class YawRateOnly(Vehicle2DOF):
    """veh2dof with only the yaw-rate sensor: what a filter should become when a_y is lost."""

    name = "veh2dof-yaw-rate-only"  # not "veh2dof": no numpy transcription, the torch model
    measurement_names = ("yaw_rate",)
    measurement_units = ("rad/s",)

    def __init__(self):
        super().__init__()
        self.measurement_noise = LaplaceNoise(self.p.measurement_scale[1:])

    def g(self, x, u):
        return super().g(x, u)[..., 1:]


def two_channel_linear(correlated: bool):
    """The oscillator with position and velocity sensors; position noise as in ``linear``."""
    system = envs.make_system("linear")
    system.C = torch.eye(2)
    system.measurement_names, system.measurement_units = ("position", "velocity"), ("m", "m/s")
    cov = [[0.01, 0.012], [0.012, 0.09]] if correlated else [[0.01, 0.0], [0.0, 0.09]]
    system.measurement_noise = GaussianNoise([0.0, 0.0], cov)
    return system


@pytest.fixture(scope="module")
def veh_data(veh):
    return veh.simulate(8, 500, seed=101)


@pytest.fixture(scope="module")
def lin_data(lin):
    return lin.simulate(8, 300, seed=202)


def with_gaps(data, p, seed=0, start=GAPS_FROM):
    """A copy of ``data`` with each measurement entry NaN with probability p from step ``start`` on."""
    y = data["measurement"]
    missing = torch.rand(y.shape, generator=torch.Generator().manual_seed(seed)) < p
    missing[:, :start] = False
    out = data.clone()
    out["measurement"] = y.masked_fill(missing, NAN)
    return out


def without(data, channel):
    out = data.clone()
    out["measurement"][..., channel] = NAN
    return out


def rmse(estimate, data, start=0):
    return (estimate - data["state"])[:, start:].pow(2).mean((0, 1)).sqrt()


FILTERS = {"KF": KalmanFilter, "EKF": EKF, "UKF": UKF, "PF": lambda s: ParticleFilter(s, 500, seed=3)}


# ----------------------------------------------------------------------------- noise densities
@pytest.mark.parametrize(
    "noise",
    [
        LaplaceNoise([1.5, 0.1]),
        OutlierLaplaceNoise([1.5, 0.1], 0.05, 10.0),
        GaussianMixtureNoise((0.7, 0.3), (-9 / 7, 3.0), (1.0, 2.0), [0.002, 0.005]),
        GaussianNoise.diagonal([0.0, 0.1], [0.1, 0.3]),
    ],
    ids=["laplace", "outlier-laplace", "mixture", "diagonal-gaussian"],
)
def test_channel_log_prob_sums_to_log_prob_and_marginal_drops_missing_channels(noise):
    value = noise.sample((50,), torch.Generator().manual_seed(0)) * 3
    channels = noise.channel_log_prob(value)
    assert channels.shape == (50, 2)
    torch.testing.assert_close(channels.sum(-1), noise.log_prob(value))
    everything = torch.ones(2, dtype=torch.bool)
    torch.testing.assert_close(noise.marginal_log_prob(value, everything), noise.log_prob(value))
    # channel 0 missing (and NaN): the density of channel 1 alone; nothing present: log 1 = 0
    gappy = value.clone()
    gappy[:, 0] = NAN
    torch.testing.assert_close(noise.marginal_log_prob(gappy, torch.tensor([False, True])), channels[:, 1])
    assert (noise.marginal_log_prob(gappy.fill_(NAN), torch.tensor([False, False])) == 0).all()


def test_laplace_channel_density_is_the_laplace_density():
    value = torch.tensor([[0.3, -0.05]])
    expected = torch.stack([D.Laplace(0.0, 1.5).log_prob(value[:, 0]), D.Laplace(0.0, 0.1).log_prob(value[:, 1])], -1)
    torch.testing.assert_close(LaplaceNoise([1.5, 0.1]).channel_log_prob(value), expected)


def test_correlated_gaussian_marginal_uses_the_sub_covariance_per_row():
    cov = torch.tensor([[1.0, 0.6, 0.2], [0.6, 2.0, 0.3], [0.2, 0.3, 0.5]])
    noise = GaussianNoise(torch.zeros(3), cov)
    with pytest.raises(NotImplementedError, match="not independent"):
        noise.channel_log_prob(torch.zeros(3))
    value = noise.sample((4,), torch.Generator().manual_seed(1))
    present = torch.tensor([[True, True, True], [True, False, True], [False, True, False], [False, False, False]])
    got = noise.marginal_log_prob(value.masked_fill(~present, NAN), present)
    assert got[0] == pytest.approx(float(noise.log_prob(value[0])), rel=1e-6)
    sub = D.MultivariateNormal(torch.zeros(2), cov[[0, 2]][:, [0, 2]]).log_prob(value[1, [0, 2]])
    assert got[1] == pytest.approx(float(sub), rel=1e-6)
    assert got[2] == pytest.approx(float(D.Normal(0.0, math.sqrt(2.0)).log_prob(value[2, 1])), rel=1e-6)
    assert got[3] == 0


# ----------------------------------------------------------------------------- random gaps
@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("system_name", ["veh2dof", "linear"])
def test_random_gaps_give_finite_estimates_identical_before_the_first_gap(name, system_name, request):
    if name == "KF" and system_name == "veh2dof":
        pytest.skip("the Kalman filter needs a linear system")
    system = request.getfixturevalue("veh" if system_name == "veh2dof" else "lin")
    data = request.getfixturevalue("veh_data" if system_name == "veh2dof" else "lin_data")
    gappy = with_gaps(data, p=0.3)
    assert torch.isnan(gappy["measurement"]).float().mean() == pytest.approx(
        0.3 * (1 - GAPS_FROM / data.shape[1]), abs=0.02
    )
    clean_filter, gappy_filter = FILTERS[name](system), FILTERS[name](system)
    clean, estimate = clean_filter.run(data), gappy_filter.run(gappy)
    assert torch.isfinite(estimate).all() and gappy_filter.stats.get("diverged") == 0
    assert torch.equal(estimate[:, :GAPS_FROM], clean[:, :GAPS_FROM])  # the complete-data path, bit for bit
    # with 30 % of the measurements gone it still filters: near its complete-data RMSE, inside the prior's spread
    prior_std = system.prior.covariance.diagonal().sqrt()
    error, reference = rmse(estimate, data, GAPS_FROM), rmse(clean, data, GAPS_FROM)
    assert (error < 1.3 * reference).all() and (error < prior_std).all(), (error, reference)


@pytest.mark.parametrize("name", ["EKF", "UKF", "PF"])
@pytest.mark.parametrize("lost", [0, 1], ids=["no-lateral-acceleration", "no-yaw-rate"])
def test_one_channel_always_missing_still_tracks(name, lost, veh, veh_data):
    """Better than predicting with no measurement at all, and inside the prior's spread."""
    estimate = FILTERS[name](veh).run(without(veh_data, lost))
    open_loop = FILTERS[name](veh).run(without(veh_data, [0, 1]))
    assert torch.isfinite(estimate).all() and torch.isfinite(open_loop).all()
    error, blind = rmse(estimate, veh_data), rmse(open_loop, veh_data)
    prior_std = veh.prior.covariance.diagonal().sqrt()
    assert (error < prior_std).all(), error
    assert (error <= 1.02 * blind).all() and (error < 0.9 * blind).any(), (error, blind)


# ----------------------------------------------------------------------------- = the reduced sensor set
@pytest.mark.parametrize("name", ["EKF", "UKF", "PF"])
def test_lateral_acceleration_missing_equals_the_yaw_rate_only_filter(name, veh, veh_data):
    """Updating with the present channel only is exactly the filter built for that one sensor."""
    data = veh_data[:3, :150]
    reduced_data = data.clone()
    reduced_data["measurement"] = data["measurement"][..., 1:]
    if name == "PF":
        full, reduced = ParticleFilter(veh, 300, seed=4), ParticleFilter(YawRateOnly(), 300, seed=4)
    else:  # both on the torch model, so that only the update differs
        cls = EKF if name == "EKF" else UKF
        full, reduced = (
            cls(veh, model="torch", dtype=torch.float64),
            cls(YawRateOnly(), model="torch", dtype=torch.float64),
        )
    estimate = full.run(without(data, 0))
    torch.testing.assert_close(estimate, reduced.run(reduced_data), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("make", [KalmanFilter, lambda s: ParticleFilter(s, 2000, seed=6)], ids=["KF", "PF"])
def test_velocity_missing_equals_the_position_only_filter(make, lin):
    """Two sensors with correlated noise, the second always missing: the marginal R[S, S]."""
    system = two_channel_linear(correlated=True)
    data = without(system.simulate(4, 200, seed=5), 1)
    reduced = data.clone()
    reduced["measurement"] = data["measurement"][..., :1]
    torch.testing.assert_close(make(system).run(data), make(lin).run(reduced), rtol=1e-5, atol=1e-6)


def kalman_skipping_updates(system, data) -> np.ndarray:
    """A Kalman filter written out by hand: predict, then update with the present rows of y only."""
    A, B, C = (m.double().numpy() for m in (system.A, system.B, system.C))
    Q = system.process_noise.covariance.double().numpy()
    R = system.measurement_noise.covariance.double().numpy()
    y, u_prev = (data[k].double().numpy() for k in ("measurement", "prev_control"))
    out = np.empty(data["state"].shape)
    for r in range(y.shape[0]):
        x = system.prior.mean.double().numpy()
        P = system.prior.covariance.double().numpy()
        for t in range(y.shape[1]):
            x, P = A @ x + B @ u_prev[r, t], A @ P @ A.T + Q
            present = ~np.isnan(y[r, t])
            if present.any():
                H, Rs = C[present], R[np.ix_(present, present)]
                K = P @ H.T @ np.linalg.inv(H @ P @ H.T + Rs)
                x = x + K @ (y[r, t, present] - H @ x)
                I_KH = np.eye(len(x)) - K @ H
                P = I_KH @ P @ I_KH.T + K @ Rs @ K.T
            out[r, t] = x
    return out


@pytest.mark.parametrize("system_kind", ["linear", "two-channel", "two-channel-correlated"])
def test_kalman_filter_with_gaps_equals_a_hand_written_kf_that_skips_updates(system_kind, lin):
    system = lin if system_kind == "linear" else two_channel_linear(system_kind.endswith("correlated"))
    data = with_gaps(system.simulate(3, 150, seed=8), p=0.4, seed=1, start=0)
    y = data["measurement"]
    nothing, partial = torch.isnan(y).all(-1), torch.isnan(y).any(-1) & ~torch.isnan(y).all(-1)
    assert nothing.any()  # steps that only predict
    assert bool(partial.any()) == (system_kind != "linear")  # steps that update with one of two channels
    estimate = KalmanFilter(system, dtype=torch.float64).run(data)
    np.testing.assert_allclose(estimate.numpy(), kalman_skipping_updates(system, data), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", ["KF", "EKF", "UKF"])
def test_kalman_filters_with_no_measurement_only_predict(name, veh, lin, veh_data, lin_data):
    """Every channel missing: the estimate is the model's prediction from the prior mean."""
    system, data = (lin, lin_data) if name == "KF" else (veh, veh_data)
    data = without(data[:2, :100], slice(None))
    estimate = FILTERS[name](system).run(data).double()
    x = system.prior.mean.double().expand(2, -1)
    model = envs.make_system(system.name).to(torch.float64)
    for t in range(data.shape[1]):
        x = model.f(x, data["prev_control"][:, t].double())
        if name != "UKF":  # the UKF's predicted mean is the sigma-point average, not f(mean)
            torch.testing.assert_close(estimate[:, t], x, rtol=1e-5, atol=1e-7)
    assert torch.isfinite(estimate).all()


def test_particle_filter_with_no_measurement_is_the_open_loop_particle_cloud(veh, veh_data):
    """Nothing present: the weights stay uniform (no resampling), the estimate is the cloud's mean."""
    runs, steps, n = 2, 60, 400
    data = without(veh_data[:runs, :steps], slice(None))
    pf = ParticleFilter(veh, n, seed=9)
    estimate = pf.run(data)
    assert pf.stats["resamples"] == 0 and torch.isfinite(estimate).all()
    generator = torch.Generator().manual_seed(9)  # the PF's draws, in its order
    x = veh.prior.sample((runs, n), generator)
    for t in range(steps):
        x = veh.f(x, data["prev_control"][:, t, None].expand(runs, n, -1)) + veh.process_noise.sample(
            (runs, n), generator
        )
        torch.testing.assert_close(estimate[:, t], x.mean(1), rtol=1e-4, atol=1e-6)
        torch.rand(runs, generator=generator)  # the resampling uniform it draws every step


# ----------------------------------------------------------------------------- bad input
def bad_inputs(data):
    """name -> (data, the key the error must name)."""
    cases = {}

    def case(name, key, **entries):
        bad = data.clone(False)
        bad.batch_size = []
        for k, v in entries.items():
            bad[k] = v
        cases[name] = (bad, key)

    y, u, up = data["measurement"], data["control"], data["prev_control"]
    for what, value in (("inf", math.inf), ("-inf", -math.inf)):
        case(
            f"{what} measurement",
            "measurement",
            measurement=y.index_put((torch.tensor([1]), torch.tensor([3])), torch.tensor(value)),
        )
    for what, value in (("nan", NAN), ("inf", math.inf)):
        case(
            f"{what} control",
            "control",
            control=u.index_put((torch.tensor([0]), torch.tensor([2])), torch.tensor(value)),
        )
        case(
            f"{what} prev_control",
            "prev_control",
            prev_control=up.index_put((torch.tensor([1]), torch.tensor([4])), torch.tensor(value)),
        )
    case("int measurement", "measurement", measurement=y.long())
    case("bool control", "control", control=u > 0)
    case("complex control", "control", control=u.to(torch.complex64))
    case("wide measurement", "measurement", measurement=torch.cat([y, y[..., :1]], -1))
    case("narrow measurement", "measurement", measurement=y[..., :0])
    case("no run axis", "measurement", measurement=y[0])
    case("short control", "control", control=u[:, :-1])
    case("fewer runs", "prev_control", prev_control=up[:1])
    cases["no control"] = (data.exclude("control"), "control")
    cases["a tensor"] = (y, "TensorDict")
    return cases


CASES = list(bad_inputs(envs.make_system("linear").simulate(2, 6, seed=0)))


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("case", CASES)
def test_bad_input_gives_one_clear_value_error(name, case, veh, lin):
    system = lin if name == "KF" else veh
    data, key = bad_inputs(system.simulate(2, 6, seed=0))[case]
    filt = FILTERS[name](system)
    with pytest.raises(ValueError) as error:
        filt.run(data)
    message = str(error.value)
    assert message.startswith(f"{filt.name}: ") and key in message and "\n" not in message, message
    if "inf measurement" in case:
        assert "[run, step, channel] = [1, 3, 0]" in message and "NaN marks a missing channel" in message


def test_nan_measurements_pass_validation(veh, veh_data):
    data = without(veh_data[:2, :5], 0)
    y, _, _ = EKF(veh).validate(data)
    assert torch.isnan(y[..., 0]).all()
