"""The "large curvature turning" manoeuvre and the PI speed holder (spec §0, §7).

Per run: V0 ~ U[60, 80] km/h, turn direction s = ±1, t1 ~ U[0.5, 1.5] s, t2 ~ U[6.5, 8.5] s and
amplitude A ~ U[30°, A_max(V0) − 20°] with A_max the "stable up to" column of the §7 spin-out
table, linearly interpolated in speed. δ_sw(t) = s·A·S(t − t1)·(1 − S(t − t2)).
"""

from __future__ import annotations

import math

import torch
from daof.envs.vehicle14dof.params import DEG, KMH, Constants, Vehicle14DOFParams
from tensordict import TensorDict

__all__ = ["sample_manoeuvre", "nominal_manoeuvre", "ramp", "steering", "speed_holder", "max_amplitude"]


def _uniform(lo_hi, runs, generator, device, dtype):
    lo, hi = lo_hi
    # drawn in float32 whatever the internal dtype, so float32 and float64 runs share episodes
    return (lo + (hi - lo) * torch.rand(runs, generator=generator, device=device)).to(dtype)


def max_amplitude(v0_kmh: torch.Tensor, p: Vehicle14DOFParams) -> torch.Tensor:
    """A_max(V0) [deg]: §7 spin-out table ("stable up to"), linear in speed, clamped at the ends."""
    speeds = torch.tensor(p.spin_speeds_kmh, dtype=v0_kmh.dtype, device=v0_kmh.device)
    amps = torch.tensor(p.spin_amp_deg, dtype=v0_kmh.dtype, device=v0_kmh.device)
    v = v0_kmh.clamp(speeds[0], speeds[-1])
    k = torch.searchsorted(speeds, v.contiguous(), right=True).clamp(1, len(speeds) - 1)
    w = (v - speeds[k - 1]) / (speeds[k] - speeds[k - 1])
    return amps[k - 1] + w * (amps[k] - amps[k - 1])


def sample_manoeuvre(runs, generator, p: Vehicle14DOFParams, device, dtype) -> TensorDict:
    """Draw ``runs`` manoeuvres: ``v_ref`` [m/s], signed ``amplitude`` [rad], ``t1``, ``t2`` [s]."""
    v0_kmh = _uniform(p.v0_kmh, runs, generator, device, dtype)
    direction = torch.where(torch.rand(runs, generator=generator, device=device) < 0.5, -1.0, 1.0)
    t1 = _uniform(p.t1_s, runs, generator, device, dtype)
    t2 = _uniform(p.t2_s, runs, generator, device, dtype)
    a_hi = max_amplitude(v0_kmh, p) - p.amp_margin_deg
    u = torch.rand(runs, generator=generator, device=device).to(dtype)
    amp_deg = p.amp_min_deg + u * (a_hi - p.amp_min_deg)
    return TensorDict(
        {
            "v_ref": v0_kmh * KMH,
            "amplitude": direction.to(dtype) * amp_deg * DEG,
            "t1": t1,
            "t2": t2,
        },
        batch_size=[runs],
        device=device,
    )


def nominal_manoeuvre(runs=1, v0_kmh=70.0, amplitude_deg=50.0, t1=1.0, t2=9.0, dtype=torch.float64):
    """The §7 nominal profile (70 km/h, 50°, ramps at 1 s and 9 s), for tests and App. A."""

    def full(value):
        return torch.full((runs,), float(value), dtype=dtype)

    return TensorDict(
        {
            "v_ref": full(v0_kmh * KMH),
            "amplitude": full(amplitude_deg * DEG),
            "t1": full(t1),
            "t2": full(t2),
        },
        batch_size=[runs],
    )


def ramp(s: torch.Tensor) -> torch.Tensor:
    """Cycloid ramp S(s) = clip(s, 0, 1) − sin(2π clip(s, 0, 1)) / (2π) (§7)."""
    s = s.clamp(0.0, 1.0)
    return s - torch.sin((2 * math.pi) * s) * (1.0 / (2 * math.pi))


def steering(time: torch.Tensor, man: TensorDict) -> torch.Tensor:
    """δ_sw(t) = s·A·S(t − t1)·(1 − S(t − t2)) [rad] for per-run times ``time`` [runs]."""
    return man["amplitude"] * ramp(time - man["t1"]) * (1.0 - ramp(time - man["t2"]))


def speed_holder(u, integ, v_ref, c: Constants, h: float):
    """§7 PI speed holder with anti-windup; returns (T_d [runs, 4], T_b [runs, 4], new integral).

    T_tot = R_e (m a_cmd + f_r m g + ½ρC_dA_f u|u|); T_tot ≥ 0 drives the rear wheels 50/50,
    T_tot < 0 brakes with the 0.66/0.34 split.
    """
    p = c.p
    err = v_ref - u
    raw = p.K_p * err + p.K_i * integ
    a_cmd = raw.clamp(p.a_cmd_min, p.a_cmd_max)
    integ = torch.where(a_cmd == raw, integ + err * h, integ)
    T_tot = p.R_e * (c.m * a_cmd + p.f_r * c.m * p.g + c.aero * u * u.abs())
    drive = T_tot.clamp(min=0.0)[:, None] * c.drive_split
    brake = (-T_tot).clamp(min=0.0)[:, None] * c.brake_split_vec
    return drive, brake, integ
