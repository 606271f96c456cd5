"""The 28-state right-hand side ẋ = f(x, inputs) of the 14-DOF car (spec §2, §5), batched.

State layout (§2): [X, Y, z_s, φ, θ, ψ, z_u(4), ρ(4), u, v, w, φ̇, θ̇, r, ż_u(4), ω(4)]; coordinates
0–13, speeds 14–27, so ẋ[:14] is (Ẋ, Ẏ, speeds...). ``rhs_t`` computes in state-major layout
(states, and per-corner quantities (FL, FR, RL, RR), on the first axis, runs on the last);
``rhs`` is its batch-major face. There is no Python loop over corners.

Inputs held over an RK4 step: δ_sw, the drive and brake torques T_d, T_b per corner and the §0
disturbance (lateral force F_d, yaw moment M_d) at P. The disturbance is added to ΣF_y and M_z only;
it is a force on the body, not a tyre force, so it does not pass through the roll centres (F_geo).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from daof.envs.vehicle14dof.params import Constants
from daof.envs.vehicle14dof.tyre import magic_formula

__all__ = ["Aux", "rhs", "rhs_t", "N_STATE", "IDX"]

N_STATE = 28


class IDX:
    """Indices into the 28-state vector (§2)."""

    X, Y, Z_S, PHI, THETA, PSI = 0, 1, 2, 3, 4, 5
    Z_U = slice(6, 10)
    RHO = slice(10, 14)
    U, V, W, PHI_D, THETA_D, R = 14, 15, 16, 17, 18, 19
    Z_U_D = slice(20, 24)
    OMEGA = slice(24, 28)


class Aux(NamedTuple):
    """Auxiliary outputs of §5.10 used by the sensor model and the tests."""

    a_x: torch.Tensor  # kinematic acceleration of P along x_V (u̇ − r v)
    a_y: torch.Tensor  # v̇ + r u
    theta_dd: torch.Tensor
    phi_dd: torch.Tensor
    w_dot: torch.Tensor
    F_z: torch.Tensor  # [runs, 4]
    F_xw: torch.Tensor  # [runs, 4] wheel-frame tyre forces
    F_yw: torch.Tensor
    kappa: torch.Tensor
    s_alpha: torch.Tensor


def rhs(x: torch.Tensor, delta_sw, T_d, T_b, dist, c: Constants, with_aux: bool = False):
    """ẋ for x [runs, 28] (T_d, T_b [runs, 4], dist [runs, 2]); returns ẋ, or (ẋ, Aux) with ``with_aux``.

    The batch-major face of ``rhs_t``: transposes in and out (the Aux corner fields too).
    """
    out = rhs_t(x.T, delta_sw, T_d.T, T_b.T, dist.T, c, with_aux)
    if not with_aux:
        return out.T
    xdot, aux = out
    return xdot.T, Aux(*(a.T if a.ndim == 2 else a for a in aux))


def rhs_t(xt: torch.Tensor, delta_sw, T_d, T_b, dist, c: Constants, with_aux: bool = False):
    """ẋ in state-major layout: xt [28, runs], T_d, T_b [4, runs], dist [2, runs] -> [28, runs].

    State-major keeps the runs on the fastest axis of every tensor, per-corner ones [4, runs]
    included, so a compiled step vectorises over runs (batch-major [runs, 4] gives its vector
    loops 4 useful lanes of 16). Scalars come from ``c.s`` as 0-dim tensors and per-corner
    constants from ``c.col`` as columns: multiplying a float32 tensor by a Python float costs an
    extra dtype conversion per op, which dominates at small batch.
    """
    s, k = c.s, c.col
    z_u, u, v, w = xt[6:10], xt[14], xt[15], xt[16]
    phi_d, theta_d, r = xt[17], xt[18], xt[19]
    z_u_d, omega = xt[20:24], xt[24:28]
    # one cos and one sin for (φ, θ, ψ, δ) with δ = δ_sw / i_s (§5.1)
    angles = torch.cat([xt[3:6], (delta_sw * s.inv_i_s)[None]], 0)
    cphi, cth, cpsi, cdelta = torch.cos(angles).unbind(0)
    sphi, sth, spsi, sdelta = torch.sin(angles).unbind(0)

    # §5.2 suspension: z_b,i = z_s − x_i sθ + y_i cθ sφ and its rate
    zb = xt[2] - k.x_i * sth + k.y_i * (cth * sphi)
    zb_d = w - k.x_i * (cth * theta_d) + k.y_i * (cth * cphi * phi_d - sth * sphi * theta_d)
    dz = z_u - zb
    # F_s − F_s0: springs, anti-roll bars (against the axle's other corner) and dampers. Written
    # out rather than as a matrix product so that mirror-image corners round alike (a straight run
    # stays exactly straight) and a compiled step fuses without a matmul call.
    F_s_dyn = k.k_s * dz + k.k_arb * (dz - dz.view(2, 2, -1).flip(1).reshape(dz.shape)) + k.c_s * (z_u_d - zb_d)
    F_s = k.F_s0 + F_s_dyn

    # §5.3 normal loads
    F_z = torch.clamp(k.F_z0 - s.k_t * z_u - s.c_t * z_u_d, min=0.0)

    # §5.4 contact-patch velocities (v_x,i = u − r y_i, v_y,i = v + r x_i) and slips; δ_i = (δ, δ, 0, 0)
    vx = u - k.y_i * r
    vy = v + k.x_i * r
    cd = 1.0 + (cdelta - 1.0) * k.front
    sd = sdelta * k.front
    vxw = vx * cd + vy * sd
    vyw = vy * cd - vx * sd
    inv_den = 1.0 / torch.clamp(vxw.abs(), min=c.p.v_eps)
    kappa = (omega * s.R_e - vxw) * inv_den
    s_alpha = -vyw * inv_den

    # §5.5 tyre forces, wheel frame -> V
    F_xw, F_yw = magic_formula(kappa, s_alpha, F_z, c.tyre_s, s.mu_scale)
    F_x = F_xw * cd - F_yw * sd
    F_y = F_xw * sd + F_yw * cd

    # §5.6 force and moment sums over the corners
    F_a = -s.aero * u * u.abs()
    SFx = F_x.sum(0) + F_a
    SFy = F_y.sum(0) + dist[0]
    M_z = (k.x_i * F_y).sum(0) - (k.y_i * F_x).sum(0) + dist[1]
    M_xs = (k.y_i * F_s).sum(0)
    M_ys = -(k.x_i * F_s).sum(0)

    # §5.7 longitudinal/pitch and lateral/roll 2×2 solves, yaw, heave
    m = s.m
    B1 = s.m_s_e * cth  # m_s e cθ
    C1 = s.I_yy + B1 * B1 * s.inv_m_s  # I_yy,s + m_s e² cθ²
    b2 = s.m_s_g_e * sth + s.e * cth * F_a + M_ys
    det1 = m * C1 - B1 * B1
    a_x = (C1 * SFx - B1 * b2) / det1
    theta_dd = (m * b2 - B1 * SFx) / det1
    B2 = -s.m_s_d * cphi  # −m_s d cφ
    C2 = s.I_xx + B2 * B2 * s.inv_m_s  # I_xx,s + m_s d² cφ²
    b2 = s.m_s_g_d * sphi + M_xs
    det2 = m * C2 - B2 * B2
    a_y = (C2 * SFy - B2 * b2) / det2
    phi_dd = (m * b2 - B2 * SFy) / det2
    r_d = M_z * s.inv_I_zz
    w_d = F_s_dyn.sum(0) * s.inv_m_s

    # §5.8 direct load transfer F_geo and unsprung vertical dynamics
    F_y_axle = F_y.view(2, 2, -1).sum(1)  # [(f, r), runs]
    m_u_ay = k.m_u_axle * a_y  # m_u,j a_y
    G = (k.h_rc * (F_y_axle - 2.0 * m_u_ay) + c.two_h_u * m_u_ay) / k.track
    F_geo = torch.stack([-G[0], G[0], -G[1], G[1]]) + k.geo_X * (s.X_g_coef * a_x)
    z_u_dd = ((F_z - k.F_z0) - F_s_dyn - F_geo) * k.inv_m_u

    # §5.9 wheel spin
    sgn = torch.tanh(omega * s.inv_omega_eps)
    omega_d = (T_d - (T_b + s.f_r_R_e * F_z) * sgn - s.R_e * F_xw) * s.inv_J_w

    # §5.10 kinematics
    xdot = torch.cat(
        [
            torch.stack([u * cpsi - v * spsi, u * spsi + v * cpsi, w, phi_d, theta_d, r]),
            z_u_d,
            omega,
            torch.stack([a_x + r * v, a_y - r * u, w_d, phi_dd, theta_dd, r_d]),
            z_u_dd,
            omega_d,
        ],
        0,
    )
    if not with_aux:
        return xdot
    return xdot, Aux(a_x, a_y, theta_dd, phi_dd, w_d, F_z, F_xw, F_yw, kappa, s_alpha)
