"""veh14dof sensors and manoeuvre (daof.envs.vehicle14dof.sensors / .manoeuvre) against the spec (§0, §7, §8).

Pins down: the GNSS channels against the simulated true trajectory (position = (X, Y) of P, velocity
= d(X, Y)/dt, i.e. the rotation R(ψ)(u, v) and not R(−ψ)); how ``measure`` applies each channel's
noise, bias, quantisation and the 10 Hz hold; the noise law of all 16 channels (scale σ, Laplace
shape, zero mean; the fresh-fix flag exact); the per-run bias laws; the simulator adding exactly
that noise and those biases; the manoeuvre's ranges.

Statistical checks use fixed seeds and tolerances of Z = 5 standard errors (a correct implementation
fails a check with probability ~6e-7); each states the deviation it detects with probability > 0.999,
i.e. one that sits more than 5 + 3.1 standard errors from the truth.
"""

from __future__ import annotations

import math

import daof.envs as envs
import numpy as np
import pytest
import torch
from daof.envs.vehicle14dof.manoeuvre import nominal_manoeuvre, sample_manoeuvre
from daof.envs.vehicle14dof.params import DEG, KMH, Vehicle14DOFParams
from daof.envs.vehicle14dof.sensors import (
    MEASUREMENT_NAMES,
    ChannelLaplaceNoise,
    channel_std,
    laplace_scale,
    measure,
    sample_biases,
)
from tensordict import TensorDict

F64 = torch.float64
Z = 5.0
N = 200_000  # draws for the noise, bias and manoeuvre laws (no dynamics: a fraction of a second)

#: §8 noise σ per channel, in the channel order (wheel speeds, SAS, f_B, ω_B, GNSS X, Y, Ẋ, Ẏ);
#: GNSS position is the standalone 1.5 m of §8's choice (RTK would be 0.02 m)
SPEC_STD = [0.1] * 4 + [0.1 * math.pi / 180] + [0.0104] * 3 + [1.73e-3] * 3 + [1.5] * 2 + [0.05] * 2

#: every noise and bias off, no SAS quantisation: the channels are the noise-free sensor equations
NOISE_OFF = {
    "wheel_speed_std": 0.0,
    "steer_std_deg": 0.0,
    "steer_quant_deg": 0.0,
    "accel_std": 0.0,
    "gyro_std": 0.0,
    "gnss_pos_std": 0.0,
    "gnss_vel_std": 0.0,
    "wheel_scale_err": 0.0,
    "steer_offset_deg": 0.0,
    "accel_bias_std": 0.0,
    "gyro_bias_std": 0.0,
}


def ks_distance(x: torch.Tensor, cdf) -> float:
    """Kolmogorov–Smirnov distance sup |F_n − F| of the sample ``x`` [n] from the CDF ``cdf``."""
    x, _ = x.double().sort()
    n = x.numel()
    F = cdf(x)
    i = torch.arange(1, n + 1, dtype=F64)
    return max((i / n - F).max().item(), (F - (i - 1) / n).max().item())


def ks_bound(n: int) -> float:
    """KS critical distance at level 1e-6: P(D > d) ≤ 2 exp(−2 n d²).

    At n = 200 000 it is 0.0060: a law whose CDF is off by 0.01 anywhere gives D ≥ 0.01 − 3.1·0.0011
    (the empirical CDF's SE at a point is ≤ 0.5/√n) > 0.006, so it fails with probability > 0.999.
    """
    return math.sqrt(math.log(2 / 1e-6) / (2 * n))


def uniform_cdf(lo, hi):
    return lambda x: ((x - lo) / (hi - lo)).clamp(0.0, 1.0)


def normal_cdf(std):
    return lambda x: 0.5 * torch.erfc(-x / (std * math.sqrt(2)))


def assert_uncorrelated(columns: torch.Tensor) -> None:
    """Pairwise correlations of ``columns`` [n, k] within Z/√n of zero (|ρ| ≥ 0.02 fails at n = 200 000)."""
    corr = torch.corrcoef(columns.double().T)
    off = corr - torch.diag(corr.diagonal())
    assert off.abs().max().item() <= Z / math.sqrt(columns.shape[0]), corr


# ----------------------------------------------------------------------------- GNSS vs the true trajectory
@pytest.fixture(scope="module")
def noise_free_run():
    """16 steps (0.32 s) of 8 runs with noise and biases off, the internal 28-state recorded every step.

    Before the first step each run's heading ψ is set to one of 8 values across (−172°, +172°) and its
    lateral velocity v to −1..+1 m/s (on the flat road the dynamics do not depend on ψ, and v is a
    side-slip transient), so R(ψ)(u, v) is exercised in every quadrant with v ≠ 0 from the start.
    Returns (x [runs, 17, 28] at t = 0..16, y [runs, 16, 16] at t = 1..16), float64.
    """
    system = envs.make_system("veh14dof", **NOISE_OFF)
    gen = torch.Generator().manual_seed(1)
    sim = system.reset_episode(8, gen)
    sim["x"][:, 5] = torch.linspace(-3.0, 3.0, 8)
    sim["x"][:, 15] = torch.linspace(-1.0, 1.0, 8)
    xs, ys = [sim["x"].double()], []
    for _ in range(16):
        sim, obs = system.advance(sim, gen)
        xs.append(sim["x"].double())
        ys.append(obs["measurement"].double())
    return torch.stack(xs, 1), torch.stack(ys, 1)


def test_gnss_position_is_the_true_position_and_is_held_between_fixes(noise_free_run):
    x, y = noise_free_run
    fresh = y[..., 15] == 1
    assert (fresh.sum(1) >= 3).all()  # fixes every 5 steps (10 Hz at Δt = 20 ms)
    # a fresh fix is (X, Y) of P at that step (to the float32 of the measurement)
    torch.testing.assert_close(y[..., 11:13][fresh], x[:, 1:, 0:2].float().double()[fresh], rtol=0, atol=0)
    # between fixes all four GNSS channels hold the last fix
    for r in range(y.shape[0]):
        last = None
        for k in range(y.shape[1]):
            if fresh[r, k]:
                last = y[r, k, 11:15]
            elif last is not None:
                assert torch.equal(y[r, k, 11:15], last), (r, k)


def test_gnss_velocity_is_the_derivative_of_the_true_position(noise_free_run):
    """A fresh (Ẋ, Ẏ) equals the central difference (X, Y)(t ± Δt) of the true trajectory.

    The difference's own error is Δt²/6·|d³(X, Y)/dt³| < 0.01 m/s here (the side-slip transient);
    the tolerance is 0.03 m/s. Rotating (u, v) by −ψ instead of +ψ is off by 2|sin ψ|·√(u² + v²),
    2.6 to 16 m/s at these headings.
    """
    x, y = noise_free_run
    dt = 0.02
    fresh = (y[..., 15] == 1)[:, :-1]  # t = 1..15, which have a neighbour on both sides
    central = (x[:, 2:, 0:2] - x[:, :-2, 0:2]) / (2 * dt)  # at t = 1..15
    gnss_velocity = y[:, :-1, 13:15]
    assert fresh.sum() >= 20
    error = (gnss_velocity - central)[fresh]
    assert error.abs().max().item() < 0.03, error.abs().max()
    # the headings really span the circle: the −ψ rotation would be far off at every run
    psi = x[:, 1:-1, 5][fresh]
    assert (2 * psi.sin().abs() * gnss_velocity[fresh].norm(dim=-1)).min().item() > 2.0


def test_gnss_fixes_are_consistent_with_each_other(noise_free_run):
    """From the GNSS channels alone: the position change between consecutive fixes (0.1 s apart) is the
    trapezoid integral of the fixes' velocities, to 0.02 m (trapezoid error Δ³/12·|d³X/dt³| ≈ 4e-3 m;
    the −ψ rotation is off by metres)."""
    _, y = noise_free_run
    fresh = y[..., 15] == 1
    checked = 0
    for r in range(y.shape[0]):
        ks = fresh[r].nonzero().squeeze(-1).tolist()
        for a, b in zip(ks, ks[1:]):
            span = (b - a) * 0.02
            moved = y[r, b, 11:13] - y[r, a, 11:13]
            integral = span * 0.5 * (y[r, a, 13:15] + y[r, b, 13:15])
            assert (moved - integral).abs().max().item() < 0.02, (r, a, b, moved, integral)
            checked += 1
    assert checked >= 10


# ----------------------------------------------------------------------------- measure(): channel by channel
def test_measure_applies_each_channels_noise_bias_quantisation_and_hold():
    """Exact algebra of ``measure`` per channel, with distinct numbers on every channel so that a
    swapped slice or a missing term shows: ω_i·(1 + ε_R,i) + n_i; Q(δ_sw + offset + n) with the 0.1°
    quantiser after the noise; f_B + b_a + n; ω_B + b_g + n; GNSS clean + n on a fresh step, the held
    fix otherwise (fresh when (t + phase) is a multiple of 5); the flag 1/0."""
    p = Vehicle14DOFParams()
    runs = 5
    t = torch.tensor([0, 1, 2, 3, 4])
    phase = torch.tensor([0, 4, 0, 1, 1])  # fresh: (t + phase) % 5 == 0 -> runs 0, 1, 4
    ch = torch.arange(15, dtype=F64)
    r = torch.arange(runs, dtype=F64)[:, None]
    clean = 10.0 + ch + 0.1 * r  # [runs, 15]
    noise = 1e-3 * (ch + 1) * (1 + r)
    held = -(torch.arange(4, dtype=F64) + 1) * (1 + r)
    biases = TensorDict(
        {
            "wheel_scale": 1.0 + 1e-3 * (torch.arange(4, dtype=F64) + 1) * (1 + r),
            "steer_offset": 0.01 * (1 + r[:, 0]),
            "accel_bias": 0.02 * (torch.arange(3, dtype=F64) + 1) + 0 * r,
            "gyro_bias": -0.03 * (torch.arange(3, dtype=F64) + 1) + 0 * r,
            "gnss_phase": phase,
        },
        batch_size=[runs],
    )
    y, new_held = measure(clean, t, held, biases, noise, p)
    assert y.shape == (runs, 16) and new_held.shape == (runs, 4)
    q = 0.1 * DEG
    fresh = torch.tensor([True, True, False, False, True])
    expected = torch.cat(
        [
            clean[:, 0:4] * biases["wheel_scale"] + noise[:, 0:4],
            (torch.round((clean[:, 4] + biases["steer_offset"] + noise[:, 4]) / q) * q)[:, None],
            clean[:, 5:8] + biases["accel_bias"] + noise[:, 5:8],
            clean[:, 8:11] + biases["gyro_bias"] + noise[:, 8:11],
            torch.where(fresh[:, None], clean[:, 11:15] + noise[:, 11:15], held),
            fresh.double()[:, None],
        ],
        -1,
    )
    torch.testing.assert_close(y, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(new_held, expected[:, 11:15], rtol=0, atol=0)
    # the SAS reading is on the 0.1° grid; without quantisation it is the raw sum
    assert ((y[:, 4] / q - torch.round(y[:, 4] / q)).abs() < 1e-9).all()
    raw, _ = measure(clean, t, held, biases, noise, Vehicle14DOFParams(steer_quant_deg=0.0))
    torch.testing.assert_close(raw[:, 4], clean[:, 4] + biases["steer_offset"] + noise[:, 4], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- noise law, all 16 channels
def test_channel_std_and_laplace_scale_are_the_spec_values():
    p = Vehicle14DOFParams()
    assert len(MEASUREMENT_NAMES) == 16 and len(SPEC_STD) == 15
    np.testing.assert_allclose(channel_std(p), SPEC_STD, rtol=1e-12)
    np.testing.assert_allclose(laplace_scale(p), np.array(SPEC_STD) / math.sqrt(2), rtol=1e-12)
    system = envs.make_system("veh14dof")
    # the filters' view: diag(σ², 0) with the flag exact
    torch.testing.assert_close(
        system.measurement_noise.covariance.diagonal().double(),
        torch.tensor([*(s * s for s in SPEC_STD), 0.0], dtype=F64),
        rtol=1e-6,
        atol=0,
    )


def test_every_channel_noise_has_the_spec_scale_and_laplace_shape():
    """n = 200 000 draws of the 16-channel noise (the simulator's law: Laplace, b = σ/√2 from
    ``laplace_scale``, the flag noise-free), per channel:

    * scale: the sample std within Z·SE of σ, SE = σ·√((κ − 1)/(4n)) = 0.0025σ for a Laplace (kurtosis
      κ = 6): σ off by 2.1 % fails with probability > 0.999;
    * shape: mean|e|/std = 1/√2 = 0.7071 (a Gaussian's is √(2/π) = 0.7979), SE = 0.354/√n = 7.9e-4:
      a ratio off by 0.0064 (one tenth of the Laplace–Gaussian gap) fails with probability > 0.999;
      and the kurtosis 6 ± 0.5 (SE ≈ 0.077; a Gaussian's is 3);
    * mean: zero within Z·SE.
    """
    p = Vehicle14DOFParams()
    noise = ChannelLaplaceNoise([*laplace_scale(p), 0.0])
    e = noise.sample((N,), torch.Generator().manual_seed(11)).double()
    assert e.shape == (N, 16)
    assert (e[:, 15] == 0).all()  # the fresh-fix flag is exact
    e = e[:, :15]
    sigma = torch.tensor(SPEC_STD, dtype=F64)
    std = e.std(0)
    assert ((std / sigma - 1).abs() <= Z * math.sqrt(5 / (4 * N))).all(), std / sigma
    ratio = e.abs().mean(0) / std
    assert ((ratio - 1 / math.sqrt(2)).abs() <= Z * 0.3536 / math.sqrt(N)).all(), ratio
    kurtosis = (e**4).mean(0) / (e**2).mean(0) ** 2
    assert ((kurtosis - 6.0).abs() <= 0.5).all(), kurtosis
    assert (e.mean(0).abs() <= Z * std / math.sqrt(N)).all()
    assert_uncorrelated(e)  # independent across channels


# ----------------------------------------------------------------------------- bias laws
def test_bias_laws_per_channel():
    """``sample_biases`` per run, n = 200 000 runs, each bias against its §8 law by a KS test (level 1e-6;
    a CDF off by 0.01 anywhere fails with probability > 0.999: e.g. a uniform half-width or a Gaussian σ
    about 3 % off), its range where bounded, and independence across wheels and axes:

    wheel-radius scale 1 + ε_R, ε_R ~ U(±0.3 %) per wheel; SAS offset ~ U(±1°); accelerometer bias
    ~ N(0, 0.05²) m/s² per axis; gyro bias ~ N(0, (1.75e-3)²) rad/s per axis; the 10 Hz GNSS phase
    uniform over the 5 filter steps of a fix period.
    """
    p = Vehicle14DOFParams()
    b = sample_biases(N, torch.Generator().manual_seed(12), p, "cpu", F64)
    bound = ks_bound(N)
    eps = b["wheel_scale"] - 1.0
    assert eps.shape == (N, 4)
    assert (eps.abs() <= 0.003 + 1e-12).all() and (eps.abs().max(0).values > 0.003 * 0.999).all()
    offset = b["steer_offset"] / DEG
    assert (offset.abs() <= 1.0 + 1e-9).all() and offset.abs().max() > 0.999
    laws = [(eps[:, i], uniform_cdf(-0.003, 0.003)) for i in range(4)]
    laws += [(offset, uniform_cdf(-1.0, 1.0))]
    laws += [(b["accel_bias"][:, i], normal_cdf(0.05)) for i in range(3)]
    laws += [(b["gyro_bias"][:, i], normal_cdf(1.75e-3)) for i in range(3)]
    for k, (sample, cdf) in enumerate(laws):
        assert ks_distance(sample, cdf) <= bound, k
    assert_uncorrelated(torch.cat([eps, offset[:, None], b["accel_bias"], b["gyro_bias"]], -1))
    counts = torch.bincount(b["gnss_phase"], minlength=5).double()
    assert counts.numel() == 5
    assert ((counts / N - 0.2).abs() <= Z * math.sqrt(0.2 * 0.8 / N)).all(), counts


# ----------------------------------------------------------------------------- the simulator end to end
def test_simulator_adds_exactly_the_channel_noise_and_biases():
    """The same seed with and without noise and biases gives the same trajectory (every draw is made
    either way), so the difference of the measurements is, per channel, the run's bias term plus the
    Laplace noise the simulator drew. 256 runs × 10 steps (SAS quantisation off in both):

    * with the biases of ``sim["params"]`` removed, the residual's std is within Z·SE of σ on every
      channel: SE = 2.2 % of σ over the 2 560 samples of a non-GNSS channel (σ 20 % off fails with
      probability > 0.999), 4.9 % over the ~512 fresh GNSS fixes (45 % off fails, e.g. a position σ
      given to the velocity, 30× off);
    * mean|e|/std is Laplace's 0.707, not a Gaussian's 0.798 (SE 0.007 on the non-GNSS channels);
    * the fresh-fix flag carries no noise.
    """
    runs, steps, seed = 256, 10, 5
    noisy = envs.make_system("veh14dof", steer_quant_deg=0.0)
    clean = envs.make_system("veh14dof", **NOISE_OFF)
    out = {}
    for name, system in (("noisy", noisy), ("clean", clean)):
        gen = torch.Generator().manual_seed(seed)
        sim = system.reset_episode(runs, gen)
        params = sim["params", "sensor"]
        ys, states = [], []
        for _ in range(steps):
            sim, obs = system.advance(sim, gen)
            ys.append(obs["measurement"].double())
            states.append(obs["state"])
        out[name] = (torch.stack(ys, 1), torch.stack(states, 1), params)
    y, state, bias = out["noisy"]
    y0, state0, bias0 = out["clean"]
    assert torch.equal(state, state0)  # the same trajectory
    assert (bias0["wheel_scale"] == 1).all() and (bias0["accel_bias"] == 0).all()
    e = torch.empty_like(y[..., :15])
    e[..., 0:4] = y[..., 0:4] - y0[..., 0:4] * bias["wheel_scale"][:, None].double()
    e[..., 4] = y[..., 4] - y0[..., 4] - bias["steer_offset"][:, None].double()
    e[..., 5:8] = y[..., 5:8] - y0[..., 5:8] - bias["accel_bias"][:, None].double()
    e[..., 8:11] = y[..., 8:11] - y0[..., 8:11] - bias["gyro_bias"][:, None].double()
    e[..., 11:15] = y[..., 11:15] - y0[..., 11:15]
    fresh = y[..., 15] == 1
    assert torch.equal(y[..., 15], y0[..., 15])
    sigma = torch.tensor(SPEC_STD, dtype=F64)
    for c in range(15):
        if c >= 11:
            # before a run's first fix both hold their reset-time fix, which has noise too; after it
            # the GNSS channels only change at fixes
            sample = e[..., c][fresh]
        else:
            sample = e[..., c].reshape(-1)
        n = sample.numel()
        std = sample.std()
        assert abs(std / sigma[c] - 1) <= Z * math.sqrt(5 / (4 * n)), (MEASUREMENT_NAMES[c], n, std / sigma[c])
        ratio = sample.abs().mean() / std
        assert abs(ratio - 1 / math.sqrt(2)) <= Z * 0.3536 / math.sqrt(n), (MEASUREMENT_NAMES[c], ratio)
    assert fresh.sum() >= 450


# ----------------------------------------------------------------------------- manoeuvre
def spec_amplitude_max(v0_kmh: torch.Tensor) -> torch.Tensor:
    """§7 spin-out table, "stable up to": 100° at 60 km/h, 80° at 70, 70° at 80; linear in speed (§0)."""
    return torch.from_numpy(np.interp(v0_kmh.numpy(), [60.0, 70.0, 80.0], [100.0, 80.0, 70.0]))


def test_sample_manoeuvre_follows_the_spec_ranges():
    """§0, n = 200 000 draws: V0 ~ U[60, 80] km/h, s = ±1 equally likely, t1 ~ U[0.5, 1.5] s,
    t2 ~ U[6.5, 8.5] s, |A| ~ U[30°, A_max(V0) − 20°] given V0; all independent. KS tests at level 1e-6
    (a CDF off by 0.01 anywhere fails with probability > 0.999); P(s = +1) = 1/2 within Z·SE
    (SE = 0.0011: 0.51 fails with probability > 0.999)."""
    p = Vehicle14DOFParams()
    m = sample_manoeuvre(N, torch.Generator().manual_seed(13), p, "cpu", F64)
    v0 = m["v_ref"] / KMH
    amp = m["amplitude"] / DEG
    direction = amp.sign()
    amp = amp.abs()
    bound = ks_bound(N)
    for sample, lo, hi in ((v0, 60.0, 80.0), (m["t1"], 0.5, 1.5), (m["t2"], 6.5, 8.5)):
        assert sample.min() >= lo - 1e-9 and sample.max() <= hi + 1e-9
        assert sample.min() < lo + 1e-3 * (hi - lo) and sample.max() > hi - 1e-3 * (hi - lo)
        assert ks_distance(sample, uniform_cdf(lo, hi)) <= bound
    assert set(direction.unique().tolist()) == {-1.0, 1.0}
    assert abs((direction > 0).double().mean().item() - 0.5) <= Z * math.sqrt(0.25 / N)
    hi = spec_amplitude_max(v0) - 20.0
    assert (amp >= 30.0 - 1e-9).all() and (amp <= hi + 1e-9).all()
    # the top of the range is 80° at 60 km/h, 60° at 70 km/h and 50° at 80 km/h
    torch.testing.assert_close(
        spec_amplitude_max(torch.tensor([60.0, 70.0, 80.0], dtype=F64)) - 20.0,
        torch.tensor([80.0, 60.0, 50.0], dtype=F64),
    )
    w = (amp - 30.0) / (hi - 30.0)  # uniform on [0, 1] given V0
    assert ks_distance(w, uniform_cdf(0.0, 1.0)) <= bound
    assert_uncorrelated(torch.stack([v0, direction, m["t1"], m["t2"], w], -1))
    # the nominal profile of §7: 70 km/h, 50°, ramps at 1 s and 9 s
    nom = nominal_manoeuvre()
    assert nom["v_ref"].item() == pytest.approx(70 * KMH) and nom["amplitude"].item() == pytest.approx(50 * DEG)
    assert (nom["t1"].item(), nom["t2"].item()) == (1.0, 9.0)
