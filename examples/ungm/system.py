"""The univariate nonstationary growth model (UNGM), written as a daof user writes a system.

    x_t = a·x_{t−1} + b·x_{t−1} / (1 + x_{t−1}²) + c·cos(ω (t−1)) + v_t,   v_t ~ N(0, q)
    y_t = d·x_t² + w_t,                                                    w_t ~ N(0, r)

with a = 0.5, b = 25, c = 8, ω = 1.2, d = 1/20, q = 10, r = 1 and x_0 ~ N(0, 5): the benchmark of
Gordon, Salmond & Smith (1993), "Novel approach to nonlinear/non-Gaussian Bayesian state estimation",
IEE Proceedings-F 140(2), after Kitagawa (1987), and the example of Arulampalam, Maskell, Gordon & Clapp
(2002), "A tutorial on particle filters for online nonlinear/non-Gaussian Bayesian tracking", IEEE
Trans. Signal Processing 50(2) (which writes the forcing as 8 cos(1.2 t)). The squared measurement
hides the sign of x, so the posterior is often bimodal: the EKF and UKF, which keep one Gaussian,
fall far behind a particle filter.

daof's time convention is x_t = f(x_{t−1}, u_{t−1}) + ξ_{t−1}: the time-varying forcing is the known
control u_t = c·cos(ω t), so ``f(x, u) = a x + b x / (1 + x²) + u``. Use it as
``system=examples.ungm.system:UNGM`` from the repository root (docs/custom_system.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from daof.envs import StochasticSystem
from daof.envs.noise import GaussianNoise

__all__ = ["UNGM", "UNGMParams"]


@dataclass
class UNGMParams:
    """Every constant of the model; each overridable (``make_system(..., q=1.0)``, ``overrides.q=1.0``)."""

    a: float = 0.5
    b: float = 25.0
    c: float = 8.0  # amplitude of the forcing c·cos(ω t)
    omega: float = 1.2  # rad per step
    d: float = 1.0 / 20.0
    q: float = 10.0  # process noise variance
    r: float = 1.0  # measurement noise variance
    prior_var: float = 5.0


class UNGM(StochasticSystem):
    """x ∈ ℝ, y = x²/20 + w: one state, one measurement, one known control (the forcing)."""

    name = "ungm"
    params_class = UNGMParams
    dt = 1.0  # a discrete-time model: one step per time unit
    time_unit = "step"
    state_names = ("x",)
    state_units = ("-",)
    measurement_names = ("y",)
    measurement_units = ("-",)
    control_names = ("forcing",)

    def __init__(self, scenario: str = "nominal", params: UNGMParams | None = None):
        self.scenario = scenario
        self.p = p = params or UNGMParams()
        self.prior = GaussianNoise.diagonal([0.0], [math.sqrt(p.prior_var)])
        self.process_noise = GaussianNoise.diagonal([0.0], [math.sqrt(p.q)])
        self.measurement_noise = GaussianNoise.diagonal([0.0], [math.sqrt(p.r)])

    def f(self, x, u):
        p = self.p
        return p.a * x + p.b * x / (1 + x**2) + u

    def g(self, x, u):
        return self.p.d * x**2

    # the same model in numpy (the EKF/UKF call these; complex x too, for their complex-step Jacobians)
    def f_numpy(self, x, u):
        p = self.p
        return p.a * x + p.b * x / (1 + x**2) + u

    def g_numpy(self, x, u):
        return self.p.d * x**2

    def control(self, t, params):
        """The forcing u_t = c·cos(ω t) that drives x_{t+1}; the same in every run."""
        return (self.p.c * torch.cos(self.p.omega * t.to(torch.get_default_dtype()))).unsqueeze(-1)
