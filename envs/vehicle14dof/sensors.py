"""The measurement model: 15 sensor channels plus the GNSS fresh-fix flag (spec §0, §8).

Channels: wheel speeds ω_1..4 [rad/s], steering-wheel angle δ_sw [rad], IMU specific force f_B
[m/s²] (3), body rates ω_B [rad/s] (3), GNSS X, Y [m] and Ẋ, Ẏ [m/s], and the 0/1 flag.
Noise is Laplace per channel with the §8 standard deviation σ (scale b = σ/√2) plus constant
per-run biases; GNSS fixes arrive at 10 Hz and are held between fixes.
"""

from __future__ import annotations

import math

import torch
from daof.envs.noise import Noise
from daof.envs.vehicle14dof.dynamics import Aux
from daof.envs.vehicle14dof.params import DEG, Constants, Vehicle14DOFParams
from tensordict import TensorDict

__all__ = [
    "MEASUREMENT_NAMES",
    "MEASUREMENT_UNITS",
    "ChannelLaplaceNoise",
    "imu",
    "gnss",
    "clean_channels",
    "channel_std",
    "sample_biases",
    "measure",
]

MEASUREMENT_NAMES = (
    "wheel_speed_fl",
    "wheel_speed_fr",
    "wheel_speed_rl",
    "wheel_speed_rr",
    "steering_wheel_angle",
    "accel_x",
    "accel_y",
    "accel_z",
    "gyro_x",
    "gyro_y",
    "gyro_z",
    "gnss_x",
    "gnss_y",
    "gnss_vx",
    "gnss_vy",
    "gnss_fresh",
)
MEASUREMENT_UNITS = ("rad/s",) * 4 + ("rad",) + ("m/s^2",) * 3 + ("rad/s",) * 3 + ("m", "m", "m/s", "m/s", "1")


class ChannelLaplaceNoise(Noise):
    """Independent zero-mean Laplace noise per channel with scale b ≥ 0 (b = 0: exact channel).

    Used for the 16 channels, where the fresh-fix flag is noise-free; informational only (no
    model-based filter runs on veh14dof), its covariance is diag(2b²).
    """

    def __init__(self, scale):
        self.b = torch.as_tensor(scale, dtype=torch.float32).clone()
        self.dim = self.b.shape[-1]
        if (self.b < 0).any():
            raise ValueError("Laplace scales must be non-negative")

    def sample(self, shape=(), generator=None):
        # Inverse CDF; rand() can return exactly 0 (log1p(−1) = −inf), hence the clamp at 50 b.
        v = torch.rand(self._shape(shape), generator=generator, device=self.b.device) - 0.5
        return -self.b * v.sign() * torch.log1p(-2 * v.abs()).clamp_min(-50.0)

    def log_prob(self, value):
        noisy = self.b > 0
        b = self.b[noisy]
        return (-value[..., noisy].abs() / b - torch.log(2 * b)).sum(-1)

    @property
    def mean(self):
        return torch.zeros_like(self.b)

    @property
    def covariance(self):
        return torch.diag(2 * self.b**2)


def channel_std(p: Vehicle14DOFParams) -> list[float]:
    """σ of the 15 noisy channels (§8), in the channel order of ``MEASUREMENT_NAMES``."""
    return (
        [p.wheel_speed_std] * 4
        + [p.steer_std_deg * DEG]
        + [p.accel_std] * 3
        + [p.gyro_std] * 3
        + [p.gnss_pos_std] * 2
        + [p.gnss_vel_std] * 2
    )


def imu(x: torch.Tensor, aux: Aux, c: Constants):
    """Noise-free IMU at the sprung CG, axes of B (§8): specific force f_B and body rates ω_B."""
    phi, theta = x[:, 3], x[:, 4]
    phi_d, theta_d, r = x[:, 17], x[:, 18], x[:, 19]
    cphi, sphi, cth, sth = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    b_x = aux.a_x + c.e * aux.theta_dd * cth
    b_y = aux.a_y - c.d * aux.phi_dd * cphi
    b_z = aux.w_dot + c.p.g
    c1 = cth * b_x - sth * b_z
    c3 = sth * b_x + cth * b_z
    f_B = torch.stack([c1, cphi * b_y + sphi * c3, cphi * c3 - sphi * b_y], -1)
    omega_B = torch.stack([phi_d - r * sth, theta_d * cphi + r * sphi * cth, r * cphi * cth - theta_d * sphi], -1)
    return f_B, omega_B


def gnss(x: torch.Tensor) -> torch.Tensor:
    """Noise-free GNSS (X, Y, Ẋ, Ẏ) of P with (Ẋ, Ẏ) = R(ψ)(u, v) (§8)."""
    psi, u, v = x[:, 5], x[:, 14], x[:, 15]
    cpsi, spsi = torch.cos(psi), torch.sin(psi)
    return torch.stack([x[:, 0], x[:, 1], u * cpsi - v * spsi, u * spsi + v * cpsi], -1)


def clean_channels(x, delta_sw, aux: Aux, c: Constants) -> torch.Tensor:
    """The 15 noise-free channels [runs, 15] at one instant."""
    f_B, omega_B = imu(x, aux, c)
    return torch.cat([x[:, 24:28], delta_sw[:, None], f_B, omega_B, gnss(x)], -1)


def sample_biases(runs, generator, p: Vehicle14DOFParams, device, dtype) -> TensorDict:
    """Constant per-run sensor errors of §8: wheel-radius scale, SAS offset, IMU biases."""

    # drawn in float32 whatever the internal dtype, so float32 and float64 runs share episodes
    def rand(*shape):
        return torch.rand(runs, *shape, generator=generator, device=device).to(dtype)

    def randn(*shape):
        return torch.randn(runs, *shape, generator=generator, device=device).to(dtype)

    return TensorDict(
        {
            "wheel_scale": 1.0 + p.wheel_scale_err * (2 * rand(4) - 1),
            "steer_offset": p.steer_offset_deg * DEG * (2 * rand() - 1),
            "accel_bias": p.accel_bias_std * randn(3),
            "gyro_bias": p.gyro_bias_std * randn(3),
            # step phase of the 10 Hz GNSS within the filter steps
            "gnss_phase": torch.randint(
                p.gnss_period_steps, (runs,), generator=generator, device=device, dtype=torch.long
            ),
        },
        batch_size=[runs],
        device=device,
    )


def measure(clean, t, held_gnss, biases: TensorDict, noise: torch.Tensor, p: Vehicle14DOFParams):
    """Noisy channels y_t [runs, 16] and the new GNSS hold [runs, 4].

    ``clean`` [runs, 15] noise-free channels, ``t`` [runs] step index, ``noise`` [runs, 15] Laplace
    draws. The wheel-speed scale error multiplies; the SAS reading is quantised after noise (an
    ADC sees the noisy signal); a GNSS fix is fresh when (t + phase) is a multiple of the period.
    """
    wheel = clean[:, 0:4] * biases["wheel_scale"] + noise[:, 0:4]
    steer = clean[:, 4] + biases["steer_offset"] + noise[:, 4]
    if p.steer_quant_deg > 0:
        q = p.steer_quant_deg * DEG
        steer = torch.round(steer / q) * q
    accel = clean[:, 5:8] + biases["accel_bias"] + noise[:, 5:8]
    gyro = clean[:, 8:11] + biases["gyro_bias"] + noise[:, 8:11]
    fresh = (t + biases["gnss_phase"]) % p.gnss_period_steps == 0
    held = torch.where(fresh[:, None], clean[:, 11:15] + noise[:, 11:15], held_gnss)
    flag = fresh.to(clean.dtype)[:, None]
    return torch.cat([wheel, steer[:, None], accel, gyro, held, flag], -1), held


def laplace_scale(p: Vehicle14DOFParams) -> list[float]:
    """Laplace scale b = σ/√2 per noisy channel."""
    return [s / math.sqrt(2.0) for s in channel_std(p)]
