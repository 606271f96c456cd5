"""``StationaryKalmanFilter``: the Kalman filter with its steady-state gain at every step.

The paper names this filter as the optimum of its filtering problem on a linear-Gaussian system:
a time-invariant map from the innovation to the update, K = P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹ with P⁻ the fixed
point of the Riccati recursion. It equals the (time-varying) ``KalmanFilter`` once the start-up is
over, and is worse during it, where the exact filter's gain is still large because the prior is
wide. The linear study reports both, so a learned filter's start-up deficit can be read against
the best stationary filter as well as against the optimum (docs/linear_check.md).

Batched in torch over runs (float64 inside). A missing (NaN) channel contributes no innovation: the
fixed gain's columns of the present channels still apply, and a step with no channel only predicts.
``run_with_std`` also returns the std of its exact error covariance (the Joseph form for a fixed gain):
wide in the start-up, where this filter is not the optimum, and the KF's once settled.
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
    std_source = "covariance"

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
        self.P0 = system.prior.covariance.detach().cpu().double()
        self.Q, self.R = Q, R

    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self._filter(y, u_prev, covariance=False)[0]

    def _run_with_std(self, y, u_prev, u):
        """The estimates and √diag P_t of the fixed-gain filter's exact error covariance (Joseph form)."""
        return self._filter(y, u_prev, covariance=True)

    def _filter(self, y: torch.Tensor, u_prev: torch.Tensor, covariance: bool):
        """(estimates, std or None) [runs, steps, n]; the std from P_t = (I − K̃C)(A P_{t−1} Aᵀ + Q)(I − K̃C)ᵀ
        + K̃ R K̃ᵀ, P_0 the prior's, K̃ the gain with the columns of missing channels zeroed (exact for any gain)."""
        dev, dtype = y.device, y.dtype
        A, B, C, K = (m.to(dev) for m in (self.A, self.B, self.C, self.gain))
        y, u_prev = y.double(), u_prev.double()
        x = self.x0.to(dev).expand(y.shape[0], -1)
        if covariance:
            Q, R, eye = (m.to(dev) for m in (self.Q, self.R, torch.eye(A.shape[0], dtype=A.dtype)))
            P = self.P0.to(dev).expand(y.shape[0], -1, -1)
            present = (~torch.isnan(y)).to(K.dtype)
        estimates, stds = [], []
        for t in self._steps(*y.shape[:2]):
            x = x @ A.T + u_prev[:, t] @ B.T
            innovation = torch.nan_to_num(y[:, t] - x @ C.T, nan=0.0)  # a missing channel adds nothing
            x = x + innovation @ K.T
            estimates.append(x)
            if covariance:
                gain = K * present[:, t, None, :]  # [runs, n, m]
                rest = eye - gain @ C
                P = rest @ (A @ P @ A.T + Q) @ rest.transpose(-1, -2) + gain @ R @ gain.transpose(-1, -2)
                stds.append(P.diagonal(dim1=-2, dim2=-1).clamp_min(0.0).sqrt())
        std = torch.stack(stds, 1).to(dtype) if covariance else None
        return torch.stack(estimates, 1).to(dtype), std
