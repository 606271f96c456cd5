"""Fixed-step RK4 at h = 1 ms with zero-order-hold inputs, and the filter-step loop (spec §6).

Inputs (δ_sw, T_d, T_b, disturbance) are held over each RK4 step; the driver and the steering
profile are updated once per step from the true state at the step's start, as in §6/§7 and the
App. A reference. One filter step Δt = 20 ms is n = Δt/h = 20 RK4 steps.
"""

from __future__ import annotations

import torch

from envs.vehicle14dof.dynamics import rhs
from envs.vehicle14dof.manoeuvre import speed_holder, steering
from envs.vehicle14dof.params import Constants

__all__ = ["rk4_step", "drive_inputs", "integrate_substeps"]


def rk4_step(x, h: float, delta_sw, T_d, T_b, dist, c: Constants) -> torch.Tensor:
    """Classical RK4: x + h/6 (k1 + 2k2 + 2k3 + k4) with inputs held over the step."""
    k1 = rhs(x, delta_sw, T_d, T_b, dist, c)
    k2 = rhs(x + (0.5 * h) * k1, delta_sw, T_d, T_b, dist, c)
    k3 = rhs(x + (0.5 * h) * k2, delta_sw, T_d, T_b, dist, c)
    k4 = rhs(x + h * k3, delta_sw, T_d, T_b, dist, c)
    return x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)


def drive_inputs(x, integ, time, man, c: Constants, h: float):
    """Steering δ_sw(t) and the PI driver's torques at one instant; returns (δ_sw, T_d, T_b, I)."""
    T_d, T_b, integ = speed_holder(x[:, 14], integ, man["v_ref"], c, h)
    return steering(time, man), T_d, T_b, integ


def integrate_substeps(x, integ, time0, n: int, man, dist, c: Constants, h: float):
    """Advance ``n`` RK4 steps of size ``h`` from per-run time ``time0`` [runs] under the manoeuvre.

    ``dist`` [runs, 2] (lateral force, yaw moment at P) is held over all ``n`` steps.
    Returns (x, driver integral).
    """
    for j in range(n):
        delta_sw, T_d, T_b, integ = drive_inputs(x, integ, time0 + j * h, man, c, h)
        x = rk4_step(x, h, delta_sw, T_d, T_b, dist, c)
    return x, integ
