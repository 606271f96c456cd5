"""Reduced MF 5.2 (PAC2002) tyre with combined slip, vectorised over any shape (spec §4).

Zero camber, no turn slip, all shifts and asymmetry terms zero, λ = 1 except the friction scale
λ_μ. cos(atan(z)) is written as 1/√(1 + z²) (identical, one op cheaper).
"""

from __future__ import annotations

import torch

from envs.vehicle14dof.params import TyreCoeffs

__all__ = ["magic_formula", "longitudinal_stiffness", "cornering_stiffness", "pure_forces"]


def longitudinal_stiffness(Fz: torch.Tensor, c: TyreCoeffs) -> torch.Tensor:
    """K_x = F_z (p_Kx1 + p_Kx2 dfz) exp(p_Kx3 dfz) [N per unit slip]."""
    dfz = (Fz - c.Fz_nom) / c.Fz_nom
    return Fz * (c.pKx1 + c.pKx2 * dfz) * torch.exp(c.pKx3 * dfz)


def cornering_stiffness(Fz: torch.Tensor, c: TyreCoeffs) -> torch.Tensor:
    """K_y = p_Ky1 F_z0 sin(2 atan(F_z / (p_Ky2 F_z0))) [N/rad]."""
    return c.pKy1 * c.Fz_nom * torch.sin(2 * torch.atan(Fz / (c.pKy2 * c.Fz_nom)))


def _mf(B, C, D, E, s):
    """D sin(C atan(B s − E (B s − atan(B s))))."""
    Bs = B * s
    return D * torch.sin(C * torch.atan(Bs - E * (Bs - torch.atan(Bs))))


def pure_forces(kappa, s_alpha, Fz, c: TyreCoeffs, mu_scale: float = 1.0):
    """Pure-slip forces (F_x0, F_y0) of §4."""
    dfz = (Fz - c.Fz_nom) / c.Fz_nom
    Dx = mu_scale * (c.pDx1 + c.pDx2 * dfz) * Fz
    Ex = torch.clamp(c.pEx1 + (c.pEx2 + c.pEx3 * dfz) * dfz, max=1.0)
    Kx = Fz * (c.pKx1 + c.pKx2 * dfz) * torch.exp(c.pKx3 * dfz)
    Bx = Kx / (c.pCx1 * Dx + c.eps_F)
    Dy = mu_scale * (c.pDy1 + c.pDy2 * dfz) * Fz
    Ey = torch.clamp(c.pEy1 + c.pEy2 * dfz, max=1.0)
    Ky = c.pKy1 * c.Fz_nom * torch.sin(2 * torch.atan(Fz * (1.0 / (c.pKy2 * c.Fz_nom))))
    By = Ky / (c.pCy1 * Dy + c.eps_F)
    return _mf(Bx, c.pCx1, Dx, Ex, kappa), _mf(By, c.pCy1, Dy, Ey, s_alpha)


def magic_formula(kappa, s_alpha, Fz, c: TyreCoeffs, mu_scale: float = 1.0):
    """Combined-slip wheel-frame forces (F_xw, F_yw) = (G_xα F_x0, G_yκ F_y0) of §4.

    ``kappa`` slip ratio κ, ``s_alpha`` = tan α, ``Fz`` ≥ 0 normal load; any common shape.
    """
    Fx0, Fy0 = pure_forces(kappa, s_alpha, Fz, c, mu_scale)
    # G_xα = cos(r_Cx1 atan(r_Bx1 cos(atan(r_Bx2 κ)) s_α)), G_yκ likewise with κ ↔ s_α
    Bxa = c.rBx1 * torch.rsqrt(1 + (c.rBx2 * kappa) ** 2)
    Byk = c.rBy1 * torch.rsqrt(1 + (c.rBy2 * s_alpha) ** 2)
    Gxa = torch.cos(c.rCx1 * torch.atan(Bxa * s_alpha))
    Gyk = torch.cos(c.rCy1 * torch.atan(Byk * kappa))
    return Gxa * Fx0, Gyk * Fy0
