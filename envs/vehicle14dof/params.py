"""Every parameter of the 14-DOF car (veh14dof spec §3, §4, §6–§8) as one overridable dataclass.

``Vehicle14DOFParams`` holds the numbers exactly as the spec lists them; ``Constants`` derives
what the right-hand side needs (static loads F_s0,i / F_z0,i, d, e, k_arb, per-corner vectors) once
per dtype and device so the ODE never builds tensors in its inner loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from types import SimpleNamespace

import torch
from daof.envs.checks import check_params
from daof.envs.vehicle14dof.tyre import TyreCoeffs, longitudinal_stiffness, prepare

__all__ = ["TyreCoeffs", "Vehicle14DOFParams", "Constants"]


@dataclass
class Vehicle14DOFParams:
    """All numbers of the spec; each overridable through ``make_system("veh14dof", name=value)``."""

    # §3.1 masses and geometry
    m_s: float = 965.7
    m_uf: float = 35.19
    m_ur: float = 28.61
    l_f: float = 1.156
    l_r: float = 1.422
    t_f: float = 1.386
    t_r: float = 1.364
    h_s: float = 0.6137
    h_rcf: float = 0.10
    h_rcr: float = 0.15
    h_pc: float = 0.0
    h_u: float = 0.30
    # §3.2 inertias
    I_xx: float = 207.2
    I_yy: float = 1565.8
    I_zz: float = 1791.6
    J_w: float = 1.0
    # §3.3 suspension (wheel-centre rates per wheel; anti-roll bars per axle)
    k_sf: float = 24445.0
    k_sr: float = 19629.0
    c_sf: float = 1786.0
    c_sr: float = 1649.0
    K_arbf: float = 6915.0
    K_arbr: float = 2644.0
    # §3.4 tyre, wheel, resistances, steering
    R_e: float = 0.306
    k_t: float = 200000.0
    c_t: float = 50.0
    f_r: float = 0.010
    rho_air: float = 1.225
    C_d: float = 0.38
    A_f: float = 1.73
    i_s: float = 16.0
    brake_front: float = 0.66  # brake split, front share (rear 0.34)
    v_eps: float = 5.0
    omega_eps: float = 0.5
    g: float = 9.81
    mu_scale: float = 1.0  # λ_μ
    tyre: TyreCoeffs = field(default_factory=TyreCoeffs)
    # §6 integration: RK4 step inside the filter step Δt
    h: float = 0.001
    dt: float = 0.02
    # float32 (default) matches every App. A row within ±1 % at h = 1 ms and differs from float64 by
    # ~4e-5 m/s in V_x, ~1e-4 m/s² in a_x (docs/benchmarks/veh14dof.md); float64 for T1/T3 exactness
    dtype: str = "float32"
    # torch.compile the RK4 step (opt-in: about a minute of compile time, see integrate.make_substep)
    compile: bool = False
    # §7 PI speed holder
    K_p: float = 3.0
    K_i: float = 1.0
    a_cmd_min: float = -3.0
    a_cmd_max: float = 1.0
    # §0 randomised "large curvature turning" manoeuvre
    v0_kmh: tuple[float, float] = (60.0, 80.0)
    t1_s: tuple[float, float] = (0.5, 1.5)
    t2_s: tuple[float, float] = (6.5, 8.5)
    amp_min_deg: float = 30.0
    amp_margin_deg: float = 20.0
    # §7 spin-out table "stable up to": speed [km/h] -> steering-wheel amplitude [deg]
    spin_speeds_kmh: tuple[float, ...] = (60.0, 70.0, 80.0)
    spin_amp_deg: tuple[float, ...] = (100.0, 80.0, 70.0)
    # §0 Gaussian-mixture disturbance at the CG: (lateral force N, yaw moment N m)
    dist_weights: tuple[float, float] = (0.9, 0.1)
    dist_scale: tuple[float, float] = (100.0, 50.0)  # std of the first component
    dist_std_ratio: tuple[float, float] = (1.0, 10.0)  # component stds in units of dist_scale
    # one component per draw for both channels (§0: 100 N with 50 N m, or 1000 N with 500 N m);
    # False draws it per channel (the simulator's data before this was fixed)
    dist_joint: bool = True
    # §8 sensors: Laplace noise with these standard deviations (b = σ/√2)
    wheel_speed_std: float = 0.1  # rad/s
    steer_std_deg: float = 0.1
    steer_quant_deg: float = 0.1  # SAS resolution; 0 disables quantisation
    accel_std: float = 0.0104  # m/s^2
    gyro_std: float = 1.73e-3  # rad/s
    # chosen: standalone GNSS (1.5 m); 0.02 m would be RTK-fixed
    gnss_pos_std: float = 1.5
    gnss_vel_std: float = 0.05
    gnss_period_steps: int = 5  # 10 Hz fixes at Δt = 20 ms
    # §8 per-run constant biases
    wheel_scale_err: float = 0.003  # ε_R ~ U(±0.3 %)
    steer_offset_deg: float = 1.0  # U(±1°)
    accel_bias_std: float = 0.05
    gyro_bias_std: float = 1.75e-3

    def __post_init__(self):
        check_params(
            self,
            positive=("m_s", "m_uf", "m_ur", "l_f", "l_r", "t_f", "t_r", "h_s", "I_xx", "I_yy", "I_zz", "J_w",
                      "k_sf", "k_sr", "R_e", "k_t", "i_s", "v_eps", "omega_eps", "g", "mu_scale", "h", "dt",
                      "v0_kmh", "spin_speeds_kmh", "spin_amp_deg", "dist_std_ratio", "gnss_period_steps"),
            nonnegative=("h_rcf", "h_rcr", "h_pc", "h_u", "c_sf", "c_sr", "K_arbf", "K_arbr", "c_t", "f_r",
                         "rho_air", "C_d", "A_f", "K_p", "K_i", "t1_s", "t2_s", "amp_min_deg", "amp_margin_deg",
                         "dist_scale", "wheel_speed_std", "steer_std_deg", "steer_quant_deg", "accel_std",
                         "gyro_std", "gnss_pos_std", "gnss_vel_std", "wheel_scale_err", "steer_offset_deg",
                         "accel_bias_std", "gyro_bias_std"),
            intervals=("v0_kmh", "t1_s", "t2_s"),
            probabilities=("brake_front",),
            weights=("dist_weights",),
        )  # fmt: skip
        if self.a_cmd_min > self.a_cmd_max:
            raise ValueError(f"a_cmd_min must be <= a_cmd_max, got {self.a_cmd_min!r} > {self.a_cmd_max!r}")
        if not isinstance(self.gnss_period_steps, int) or isinstance(self.gnss_period_steps, bool):
            raise ValueError(f"gnss_period_steps must be a whole number of steps >= 1, got {self.gnss_period_steps!r}")
        speeds, amps = tuple(self.spin_speeds_kmh), tuple(self.spin_amp_deg)
        if len(speeds) < 2 or len(speeds) != len(amps) or any(a >= b for a, b in zip(speeds, speeds[1:])):
            raise ValueError(
                "spin_speeds_kmh must be >= 2 increasing speeds with one spin_amp_deg each, "
                f"got {self.spin_speeds_kmh!r} and {self.spin_amp_deg!r}"
            )
        if len(self.dist_weights) != 2 or len(self.dist_scale) != 2 or len(self.dist_std_ratio) != 2:
            raise ValueError("dist_weights, dist_scale and dist_std_ratio must be pairs (two components, two axes)")
        if not isinstance(self.tyre, TyreCoeffs):
            raise ValueError(f"tyre must be a TyreCoeffs, got {type(self.tyre).__name__}")
        check_params(self.tyre, positive=("Fz_nom", "eps_F"))

    @property
    def torch_dtype(self) -> torch.dtype:
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        return getattr(torch, self.dtype)


class Constants:
    """Derived quantities of §3 and per-corner vectors (FL, FR, RL, RR) in one dtype/device."""

    def __init__(self, p: Vehicle14DOFParams, dtype=torch.float64, device="cpu"):
        self.p = p
        self.tyre = p.tyre
        self.dtype, self.device = dtype, torch.device(device)
        L = p.l_f + p.l_r
        self.L = L
        self.m = p.m_s + 2 * p.m_uf + 2 * p.m_ur
        self.d = p.h_s - (p.h_rcf * p.l_r + p.h_rcr * p.l_f) / L  # sprung CG above roll axis
        self.e = p.h_s - p.h_pc  # sprung CG above pitch axis
        self.aero = 0.5 * p.rho_air * p.C_d * p.A_f  # F_a = −aero·u|u|
        self.k_arbf = p.K_arbf / p.t_f**2
        self.k_arbr = p.K_arbr / p.t_r**2

        def vec(values):
            return torch.tensor(values, dtype=dtype, device=self.device)

        self.x_i = vec([p.l_f, p.l_f, -p.l_r, -p.l_r])
        self.y_i = vec([p.t_f / 2, -p.t_f / 2, p.t_r / 2, -p.t_r / 2])
        self.m_u = vec([p.m_uf, p.m_uf, p.m_ur, p.m_ur])
        Fs0 = [p.m_s * p.g * a / (2 * L) for a in (p.l_r, p.l_r, p.l_f, p.l_f)]
        self.F_s0 = vec(Fs0)
        self.F_z0 = vec([f + mu * p.g for f, mu in zip(Fs0, (p.m_uf, p.m_uf, p.m_ur, p.m_ur))])
        self.c_s = vec([p.c_sf, p.c_sf, p.c_sr, p.c_sr])
        self.front = vec([1.0, 1.0, 0.0, 0.0])
        self.drive_split = vec([0.0, 0.0, 0.5, 0.5])  # RWD, open differential
        bf = p.brake_front
        self.brake_split_vec = vec([bf / 2, bf / 2, (1 - bf) / 2, (1 - bf) / 2])
        self.h_rc = vec([p.h_rcf, p.h_rcr])
        self.m_u_axle = vec([p.m_uf, p.m_ur])
        self.track = vec([p.t_f, p.t_r])
        self.geo_X = vec([-1.0, -1.0, 1.0, 1.0])  # F_geo = (−G_f, G_f, −G_r, G_r) + X_g geo_X (§5.8)
        self.X_g_coef = (2 * p.m_uf + 2 * p.m_ur) * p.h_u / (2 * L)
        self.Sigma_muhu = (2 * p.m_uf + 2 * p.m_ur) * p.h_u
        self.inv_m_u = 1.0 / self.m_u
        self.two_h_u = vec(2 * p.h_u)
        #: per-corner (and per-axle) constants as columns [4, 1] ([2, 1]), for ``rhs_t``
        self.col = SimpleNamespace(
            F_s0=self.F_s0[:, None],
            F_z0=self.F_z0[:, None],
            c_s=self.c_s[:, None],
            front=self.front[:, None],
            inv_m_u=self.inv_m_u[:, None],
            geo_X=self.geo_X[:, None],
            h_rc=self.h_rc[:, None],
            m_u_axle=self.m_u_axle[:, None],
            track=self.track[:, None],
            x_i=self.x_i[:, None],
            y_i=self.y_i[:, None],
            k_s=vec([p.k_sf, p.k_sf, p.k_sr, p.k_sr])[:, None],
            # F_s = F_s0 + k_s Δ + k_arb (Δ − Δ of the axle's other corner) + c_s Δ̇ (§5.2)
            k_arb=vec([self.k_arbf, self.k_arbf, self.k_arbr, self.k_arbr])[:, None],
        )
        scalars = {f.name: getattr(p, f.name) for f in fields(p) if isinstance(getattr(p, f.name), float)}
        scalars.update(
            m=self.m,
            e=self.e,
            aero=self.aero,
            X_g_coef=self.X_g_coef,
            inv_i_s=1.0 / p.i_s,
            inv_m_s=1.0 / p.m_s,
            inv_I_zz=1.0 / p.I_zz,
            inv_J_w=1.0 / p.J_w,
            inv_omega_eps=1.0 / p.omega_eps,
            f_r_R_e=p.f_r * p.R_e,
            m_s_e=p.m_s * self.e,
            m_s_d=p.m_s * self.d,
            m_s_g_e=p.m_s * p.g * self.e,
            m_s_g_d=p.m_s * p.g * self.d,
        )
        #: 0-dim tensors of every scalar the right-hand side uses (see dynamics.rhs)
        self.s = SimpleNamespace(**{k: vec(v) for k, v in scalars.items()})
        self.tyre_s = prepare(p.tyre, dtype, self.device)

    def free_rolling_omega(self, V0: torch.Tensor) -> torch.Tensor:
        """§5.11: ω_i = V0 (1 − f_r F_z0,i / K_x(F_z0,i)) / R_e, shape [runs, 4]."""
        Kx = longitudinal_stiffness(self.F_z0, self.tyre)
        return V0[:, None] * (1 - self.p.f_r * self.F_z0 / Kx) / self.p.R_e


DEG = math.pi / 180.0
KMH = 1.0 / 3.6
