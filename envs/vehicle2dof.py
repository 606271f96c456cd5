"""The 2-DOF single-track vehicle of Experiment I (docs/design.md, "veh2dof").

State x = [β, r] (side slip, yaw rate), control u = δ_f (front steer, known), measurement
y = [a_y, r] + ζ. Magic-Formula tyres on both axles, explicit Euler at Δτ = 0.02 s,
Gaussian-mixture process noise, Laplace measurement noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from daof.envs.checks import check_params
from daof.envs.noise import GaussianMixtureNoise, GaussianNoise, LaplaceNoise, OutlierLaplaceNoise
from daof.envs.system import StochasticSystem
from tensordict import TensorDict

__all__ = ["Vehicle2DOFParams", "Vehicle2DOF"]


@dataclass
class Vehicle2DOFParams:
    """Every number of the spec, each overridable through ``make_system(..., name=value)``."""

    m: float = 1412.0  # kg
    Iz: float = 1536.7  # kg m^2
    lf: float = 1.06  # m
    lr: float = 1.85  # m
    vx: float = 20.0  # m/s
    g: float = 9.81  # m/s^2
    mu: float = 0.9  # road friction (nominal)
    B: float = 10.0  # Magic-Formula stiffness factor (nominal)
    C: float = 1.3
    E: float = 0.97
    dt: float = 0.02  # s
    # steering manoeuvre δ_f = A sin(2π t Δτ / P + φ)
    steer_amplitude_deg: tuple[float, float] = (2.0, 3.5)
    steer_period_s: tuple[float, float] = (3.0, 6.0)
    # process noise: per-axis scale σ_ξ and the mixture in units of σ_ξ
    process_scale: tuple[float, float] = (0.002, 0.005)
    mixture_weights: tuple[float, float] = (0.7, 0.3)
    mixture_means: tuple[float, float] = (-9.0 / 7.0, 3.0)
    mixture_stds: tuple[float, float] = (1.0, 2.0)
    # measurement noise: Laplace scale b per channel [a_y, r]
    measurement_scale: tuple[float, float] = (1.5, 0.1)
    outlier_prob: float = 0.05
    outlier_magnitude: float = 10.0
    # prior x_0 ~ N(0, diag(prior_std²))
    prior_std: tuple[float, float] = (0.02, 0.1)
    # mismatch scenario: true μ and B drawn per episode
    mismatch_mu: tuple[float, float] = (0.7, 1.0)
    mismatch_B: tuple[float, float] = (8.0, 12.0)

    def __post_init__(self):
        check_params(
            self,
            positive=("m", "Iz", "lf", "lr", "vx", "g", "mu", "B", "C", "dt", "steer_period_s", "process_scale",
                      "mixture_stds", "measurement_scale", "prior_std", "mismatch_mu", "mismatch_B"),
            nonnegative=("steer_amplitude_deg", "outlier_magnitude"),
            intervals=("steer_amplitude_deg", "steer_period_s", "mismatch_mu", "mismatch_B"),
            probabilities=("outlier_prob",),
            weights=("mixture_weights",),
        )  # fmt: skip


def _uniform(lo_hi, runs, generator, device) -> torch.Tensor:
    lo, hi = lo_hi
    return lo + (hi - lo) * torch.rand(runs, generator=generator, device=device)


class Vehicle2DOF(StochasticSystem):
    """2-DOF lateral vehicle with scenarios ``nominal``, ``mismatch`` and ``outliers``."""

    name = "veh2dof"
    scenarios = ("nominal", "mismatch", "outliers")
    state_names = ("beta", "yaw_rate")
    state_units = ("rad", "rad/s")
    measurement_names = ("lateral_acceleration", "yaw_rate")
    measurement_units = ("m/s^2", "rad/s")
    control_names = ("front_steer",)

    def __init__(self, scenario: str = "nominal", params: Vehicle2DOFParams | None = None):
        self.scenario = scenario
        self.p = p = params or Vehicle2DOFParams()
        self.dt = p.dt
        self.prior = GaussianNoise.diagonal([0.0, 0.0], p.prior_std)
        self.process_noise = GaussianMixtureNoise(p.mixture_weights, p.mixture_means, p.mixture_stds, p.process_scale)
        if scenario == "outliers":
            self.measurement_noise = OutlierLaplaceNoise(p.measurement_scale, p.outlier_prob, p.outlier_magnitude)
        else:
            self.measurement_noise = LaplaceNoise(p.measurement_scale)
        l = p.lf + p.lr
        self.Fzf = p.m * p.g * p.lr / l
        self.Fzr = p.m * p.g * p.lf / l
        self._Fz = torch.tensor([self.Fzf, self.Fzr], dtype=torch.float64)
        self._slip_map = torch.tensor([[1.0, 1.0], [p.lf / p.vx, -p.lr / p.vx]], dtype=torch.float64)
        self._f_cache: dict = {}

    # ----------------------------------------------------------------- physics
    def _tyre(self, alpha, Fz, mu, B):
        """Magic-Formula lateral force F_y(α, F_z) = −μ F_z sin(C atan(Bα − E(Bα − atan(Bα))))."""
        p = self.p
        Ba = B * alpha
        return -mu * Fz * torch.sin(p.C * torch.atan(Ba - p.E * (Ba - torch.atan(Ba))))

    def _forces(self, x, u, mu, B):
        """(front lateral force along the body axis, rear lateral force); both axles at once."""
        delta = u[..., 0]
        # slip angles [α_f, α_r] = x @ [[1, 1], [l_f/v_x, −l_r/v_x]] − [δ, 0]
        slip = x @ self._slip_map.to(x) - torch.stack([delta, torch.zeros_like(delta)], -1)
        mu, B = (v.unsqueeze(-1) if isinstance(v, torch.Tensor) else v for v in (mu, B))
        Fy = self._tyre(slip, self._Fz.to(x), mu, B)
        return Fy[..., 0] * torch.cos(delta), Fy[..., 1]

    def derivative(self, x, u, mu=None, B=None):
        """Continuous dynamics [β̇, ṙ]; μ and B default to the nominal model."""
        p = self.p
        mu = p.mu if mu is None else mu
        B = p.B if B is None else B
        Fyf_c, Fyr = self._forces(x, u, mu, B)
        beta_dot = (Fyf_c + Fyr) / (p.m * p.vx) - x[..., 1]
        r_dot = (p.lf * Fyf_c - p.lr * Fyr) / p.Iz
        return torch.stack([beta_dot, r_dot], -1)

    def lateral_acceleration(self, x, u, mu=None, B=None):
        p = self.p
        mu = p.mu if mu is None else mu
        B = p.B if B is None else B
        Fyf_c, Fyr = self._forces(x, u, mu, B)
        return (Fyf_c + Fyr) / p.m

    def f(self, x, u):
        """Nominal Euler step x + Δτ·ẋ(x, u): ``derivative`` with the nominal μ, B, rearranged.

        It runs inside every DAOF-v1 estimate, so it is written in 15 tensor ops instead of ~35:
        slip = x M − δ e₁, F = −μ F_z sin(C atan(lerp(Bα, atan(Bα), E))) per axle,
        F_c = F ⊙ cos(δ e₁) (only the front force turns with the wheel), x' = x K + F_c D.
        """
        M, e1, neg_e1, muFz, K, D, _, _ = self._f_constants(x)
        delta = u[..., :1]
        Ba = torch.addcmul(x @ M, delta, neg_e1) * self.p.B
        Fy = torch.sin(self.p.C * torch.atan(torch.lerp(Ba, torch.atan(Ba), self.p.E))) * muFz
        return x @ K + (Fy * torch.cos(delta * e1)) @ D

    def _f_constants(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The constant matrices of ``f`` in x's dtype and device (built once per dtype/device)."""
        key = (x.dtype, x.device)
        if key not in self._f_cache:
            p, dt = self.p, self.dt
            c = [
                self._slip_map,
                [1.0, 0.0],
                [-1.0, 0.0],
                [-p.mu * self.Fzf, -p.mu * self.Fzr],
                [[1.0, 0.0], [-dt, 1.0]],
                [[dt / (p.m * p.vx), dt * p.lf / p.Iz], [dt / (p.m * p.vx), -dt * p.lr / p.Iz]],
                [[1.0 / p.m, 0.0], [1.0 / p.m, 0.0]],  # g: a_y = (F_yf cos δ + F_yr)/m
                [[0.0, 0.0], [0.0, 1.0]],  # g: the yaw rate is measured as it is
            ]
            self._f_cache[key] = tuple(torch.as_tensor(v, dtype=torch.float64).to(x) for v in c)
        return self._f_cache[key]

    def g(self, x, u):
        """Nominal measurement [a_y(x, u), r], in the same 15 ops as ``f`` (DAOF-v1 calls it every step)."""
        M, e1, neg_e1, muFz, _, _, G, J = self._f_constants(x)
        delta = u[..., :1]
        Ba = torch.addcmul(x @ M, delta, neg_e1) * self.p.B
        Fy = torch.sin(self.p.C * torch.atan(torch.lerp(Ba, torch.atan(Ba), self.p.E))) * muFz
        return x @ J + (Fy * torch.cos(delta * e1)) @ G

    # ----------------------------------------------------------------- the model in numpy
    # The Kalman filters (filterpy, float64) call the model a few times per step on a few points.
    # Measured per call (issue 31): f or g on 5 sigma points 27 µs here, 56-62 µs through the torch
    # wrapper (StochasticSystem.f_numpy); the Jacobian F 42 µs by complex step on these lines,
    # 890 µs by torch.func.jacrev (TorchModel). benchmarks/bench_classical.py --models times them too.
    def f_numpy(self, x, u):
        """Nominal ``f`` in numpy, the spec's equations as written (also for complex x: complex-step Jacobians)."""
        p = self.p
        Fyf_c, Fyr = self._forces_numpy(x, u)
        beta_dot = (Fyf_c + Fyr) / (p.m * p.vx) - x[..., 1]
        r_dot = (p.lf * Fyf_c - p.lr * Fyr) / p.Iz
        return x + self.dt * np.stack([beta_dot, r_dot], -1)

    def g_numpy(self, x, u):
        """Nominal ``g`` = [a_y, r] in numpy (as ``f_numpy``)."""
        Fyf_c, Fyr = self._forces_numpy(x, u)
        return np.stack([(Fyf_c + Fyr) / self.p.m, x[..., 1]], -1)

    def _forces_numpy(self, x, u):
        """(front lateral force along the body axis, rear lateral force) at the nominal μ, B."""
        p = self.p
        beta, r, delta = x[..., 0], x[..., 1], u[..., 0]
        Fyf = self._tyre_numpy(beta + p.lf * r / p.vx - delta, self.Fzf)
        Fyr = self._tyre_numpy(beta - p.lr * r / p.vx, self.Fzr)
        return Fyf * np.cos(delta), Fyr

    def _tyre_numpy(self, alpha, Fz):
        p = self.p
        Ba = p.B * alpha
        return -p.mu * Fz * np.sin(p.C * np.arctan(Ba - p.E * (Ba - np.arctan(Ba))))

    # ----------------------------------------------------------------- uncertain parameters
    def uncertain_parameters(self) -> dict[str, tuple[float, float]]:
        """``mismatch`` draws the road friction μ and the tyre's B per run; the other scenarios nothing."""
        p = self.p
        return {"mu": p.mismatch_mu, "B": p.mismatch_B} if self.scenario == "mismatch" else {}

    def f_with(self, x, u, params):
        """Euler step of ``derivative`` with μ and B from ``params`` (the true model of a mismatch run)."""
        return x + self.dt * self.derivative(x, u, params["mu"], params["B"])

    def g_with(self, x, u, params):
        return torch.stack([self.lateral_acceleration(x, u, params["mu"], params["B"]), x[..., 1]], -1)

    # ----------------------------------------------------------------- episodes
    def sample_params(self, runs, generator, device):
        p = self.p
        amplitude = torch.deg2rad(_uniform(p.steer_amplitude_deg, runs, generator, device))
        period = _uniform(p.steer_period_s, runs, generator, device)
        phase = _uniform((0.0, 2 * math.pi), runs, generator, device)
        if self.scenario == "mismatch":
            mu = _uniform(p.mismatch_mu, runs, generator, device)
            B = _uniform(p.mismatch_B, runs, generator, device)
        else:
            mu = torch.full((runs,), p.mu, device=device)
            B = torch.full((runs,), p.B, device=device)
        return TensorDict(
            {"amplitude": amplitude, "period": period, "phase": phase, "mu": mu, "B": B},
            batch_size=[runs],
            device=device,
        )

    def control(self, t, params):
        angle = 2 * math.pi * t * self.dt / params["period"] + params["phase"]
        return (params["amplitude"] * torch.sin(angle)).unsqueeze(-1)

    def transition(self, x, u, params, generator):
        return self.f_with(x, u, params) + self.process_noise.sample(x.shape[:-1], generator)

    def measure(self, x, u, params, generator):
        return self.g_with(x, u, params) + self.measurement_noise.sample(x.shape[:-1], generator)
