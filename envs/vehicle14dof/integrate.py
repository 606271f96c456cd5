"""Fixed-step RK4 at h = 1 ms with zero-order-hold inputs, and the filter-step loop (spec §6).

Inputs (δ_sw, T_d, T_b, disturbance) are held over each RK4 step; the driver and the steering
profile are updated once per step from the true state at the step's start, as in §6/§7 and the
App. A reference. One filter step Δt = 20 ms is n = Δt/h = 20 RK4 steps.
"""

from __future__ import annotations

import torch
from daof.envs.vehicle14dof.dynamics import rhs, rhs_t
from daof.envs.vehicle14dof.manoeuvre import speed_holder, steering
from daof.envs.vehicle14dof.params import Constants

__all__ = ["rk4_step", "drive_inputs", "make_substep", "integrate_substeps"]


def rk4_step(x, h: float, delta_sw, T_d, T_b, dist, c: Constants, f=rhs) -> torch.Tensor:
    """Classical RK4: x + h/6 (k1 + 2k2 + 2k3 + k4) with inputs held over the step.

    ``f`` is ``rhs`` (x [runs, 28], the default) or ``rhs_t`` (state-major x [28, runs], inputs
    likewise transposed). ``torch.add(..., alpha=)`` fuses the scalar multiply into the add.
    """
    k1 = f(x, delta_sw, T_d, T_b, dist, c)
    k2 = f(torch.add(x, k1, alpha=0.5 * h), delta_sw, T_d, T_b, dist, c)
    k3 = f(torch.add(x, k2, alpha=0.5 * h), delta_sw, T_d, T_b, dist, c)
    k4 = f(torch.add(x, k3, alpha=h), delta_sw, T_d, T_b, dist, c)
    incr = (k1 + k4).add_(k2, alpha=2.0).add_(k3, alpha=2.0)
    return torch.add(x, incr, alpha=h / 6.0)


def drive_inputs(x, integ, time, man, c: Constants, h: float):
    """Steering δ_sw(t) and the PI driver's torques at one instant; returns (δ_sw, T_d, T_b, I)."""
    T_d, T_b, integ = speed_holder(x[:, 14], integ, man["v_ref"], c, h)
    return steering(time, man), T_d, T_b, integ


def make_substep(c: Constants, h: float, compile: bool = False):
    """One RK4 step with the driver and steering evaluated at its start, in state-major layout.

    Takes and returns xt [28, runs] (and the disturbance as [2, runs]); plain tensors in and out.
    ``compile=True`` wraps it in ``torch.compile`` (inductor, fused kernels vectorised over runs):
    faster than eager at every batch after a first compile per batch size
    (docs/benchmarks/veh14dof.md).
    """

    def substep(xt, integ, time, v_ref, amplitude, t1, t2, dist_t):
        T_d, T_b, integ = speed_holder(xt[14], integ, v_ref, c, h)
        man = {"amplitude": amplitude, "t1": t1, "t2": t2}
        return rk4_step(xt, h, steering(time, man), T_d.T, T_b.T, dist_t, c, rhs_t), integ

    return torch.compile(substep, dynamic=False) if compile else substep


def integrate_substeps(x, integ, time0, n: int, man, dist, c: Constants, h: float, substep=None):
    """Advance ``n`` RK4 steps of size ``h`` from per-run time ``time0`` [runs] under the manoeuvre.

    ``dist`` [runs, 2] (lateral force, yaw moment at P) is held over all ``n`` steps; ``substep``
    is a ``make_substep`` function (default: eager). x [runs, 28] is integrated in state-major
    layout (one transpose each way per call). Returns (x, driver integral).
    """
    substep = substep or make_substep(c, h)
    v_ref, amplitude, t1, t2 = man["v_ref"], man["amplitude"], man["t1"], man["t2"]
    xt, dist_t = x.T.contiguous(), dist.T.contiguous()
    for j in range(n):
        xt, integ = substep(xt, integ, time0 + j * h, v_ref, amplitude, t1, t2, dist_t)
    return xt.T.contiguous(), integ
