"""A linear-Gaussian system whose optimal filter is the (stationary) Kalman filter.

A forced, damped oscillator x = [p, v] (position, velocity), p̈ = −ω² p − 2ζω ṗ + u, discretised
exactly (zero-order hold) at Δτ, with Gaussian process noise and a scalar noisy position
measurement. It is the project's end-to-end correctness check: a learned filter here should
match the Kalman filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from daof.envs.noise import GaussianNoise
from daof.envs.system import StochasticSystem
from tensordict import TensorDict

__all__ = ["LinearParams", "LinearOscillator", "stationary_kalman_covariance"]


@dataclass
class LinearParams:
    """Every number of the linear system, each overridable through ``make_system``."""

    omega: float = math.pi  # rad/s, natural frequency (period 2 s)
    zeta: float = 0.1  # damping ratio
    dt: float = 0.05  # s
    process_std: tuple[float, float] = (0.01, 0.05)  # per step, on [p, v]
    measurement_std: float = 0.1
    prior_std: tuple[float, float] = (0.5, 0.5)
    force_amplitude: tuple[float, float] = (0.5, 1.5)
    force_period_s: tuple[float, float] = (2.0, 6.0)


def stationary_kalman_covariance(A, C, Q, R, iterations: int = 2000) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed point of the Riccati recursion: (predicted P⁻, updated P⁺) in float64."""
    A, C, Q, R = (m.double() for m in (A, C, Q, R))
    P = Q.clone()
    for _ in range(iterations):
        S = C @ P @ C.T + R
        K = P @ C.T @ torch.linalg.inv(S)
        P_post = (torch.eye(A.shape[0], dtype=A.dtype) - K @ C) @ P
        P = A @ P_post @ A.T + Q
    return P, P_post


class LinearOscillator(StochasticSystem):
    """x_{t+1} = A x_t + B u_t + w_t, y_t = C x_t + v_t, all Gaussian."""

    name = "linear"
    state_names = ("position", "velocity")
    state_units = ("m", "m/s")
    measurement_names = ("position",)
    measurement_units = ("m",)
    control_names = ("force",)

    def __init__(self, scenario: str = "nominal", params: LinearParams | None = None):
        self.scenario = scenario
        self.p = p = params or LinearParams()
        self.dt = p.dt
        Ac = torch.tensor([[0.0, 1.0], [-(p.omega**2), -2 * p.zeta * p.omega]], dtype=torch.float64)
        Bc = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
        # Zero-order-hold discretisation through the augmented matrix exponential.
        aug = torch.zeros(3, 3, dtype=torch.float64)
        aug[:2, :2], aug[:2, 2:] = Ac * p.dt, Bc * p.dt
        expm = torch.linalg.matrix_exp(aug)
        self.A = expm[:2, :2].float()
        self.B = expm[:2, 2:].float()
        self.C = torch.tensor([[1.0, 0.0]])
        self.prior = GaussianNoise.diagonal([0.0, 0.0], p.prior_std)
        self.process_noise = GaussianNoise.diagonal([0.0, 0.0], p.process_std)
        self.measurement_noise = GaussianNoise.diagonal([0.0], [p.measurement_std])
        self.state_low = torch.tensor([-5.0, -15.0])
        self.state_high = torch.tensor([5.0, 15.0])
        _, P_post = stationary_kalman_covariance(
            self.A, self.C, self.process_noise.covariance, self.measurement_noise.covariance
        )
        # The stationary Kalman filter's RMSE per state: a perfect filter earns about −1 per step.
        self.error_scale = P_post.diagonal().sqrt().float()

    def f(self, x, u):
        return x @ self.A.T + u @ self.B.T

    def g(self, x, u):
        return x @ self.C.T

    def sample_params(self, runs, generator, device):
        p = self.p
        lo, hi = p.force_amplitude
        amplitude = lo + (hi - lo) * torch.rand(runs, generator=generator, device=device)
        lo, hi = p.force_period_s
        period = lo + (hi - lo) * torch.rand(runs, generator=generator, device=device)
        phase = 2 * math.pi * torch.rand(runs, generator=generator, device=device)
        return TensorDict({"amplitude": amplitude, "period": period, "phase": phase}, batch_size=[runs], device=device)

    def control(self, t, params):
        angle = 2 * math.pi * t * self.dt / params["period"] + params["phase"]
        return (params["amplitude"] * torch.sin(angle)).unsqueeze(-1)
