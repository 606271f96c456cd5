"""``StationaryKalmanFilter``: the Kalman filter with its steady-state gain at every step.

The paper names this filter as the optimum of its filtering problem on a linear-Gaussian system:
a time-invariant map from the innovation to the update, K = P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹ with P⁻ the fixed
point of the Riccati recursion. It equals the (time-varying) ``KalmanFilter`` once the start-up is
over, and is worse during it, where the exact filter's gain is still large because the prior is
wide. The linear study reports both, so a learned filter's start-up deficit can be read against
the best stationary filter as well as against the optimum (docs/linear_check.md).

Batched in torch over runs (float64 inside). A missing (NaN) channel contributes no innovation: the
fixed gain's columns of the present channels still apply, and a step with no channel only predicts.
"""

from __future__ import annotations

import torch

from daof.envs.linear import stationary_kalman_covariance
from daof.envs.system import StochasticSystem
from daof.filters.base import Filter

__all__ = ["StationaryKalmanFilter"]


class StationaryKalmanFilter(Filter):
    """x̂_t = x̂⁻_t + K (y_t − C x̂⁻_t), x̂⁻_t = A x̂_{t−1} + B u_{t−1}, with K the steady-state gain."""

    name = "KF-stationary"

    def __init__(self, system: StochasticSystem):
        if not all(hasattr(system, m) for m in ("A", "B", "C")):
            raise ValueError(f"StationaryKalmanFilter needs a linear system with A, B, C; {system.name!r} has none")
        super().__init__(system)
        A, B, C = (m.detach().cpu().double() for m in (system.A, system.B, system.C))
        Q = system.process_noise.covariance.detach().cpu().double()
        R = system.measurement_noise.covariance.detach().cpu().double()
        P_pred, _ = stationary_kalman_covariance(A, C, Q, R)
        self.A, self.B, self.C = A, B, C
        self.gain = P_pred @ C.T @ torch.linalg.inv(C @ P_pred @ C.T + R)
        self.x0 = system.prior.mean.detach().cpu().double()

    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        dev, dtype = y.device, y.dtype
        A, B, C, K = (m.to(dev) for m in (self.A, self.B, self.C, self.gain))
        y, u_prev = y.double(), u_prev.double()
        x = self.x0.to(dev).expand(y.shape[0], -1)
        estimates = []
        for t in self._steps(*y.shape[:2]):
            x = x @ A.T + u_prev[:, t] @ B.T
            innovation = torch.nan_to_num(y[:, t] - x @ C.T, nan=0.0)  # a missing channel adds nothing
            x = x + innovation @ K.T
            estimates.append(x)
        return torch.stack(estimates, 1).to(dtype)
