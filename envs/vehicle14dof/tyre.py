"""Reduced MF 5.2 (PAC2002) tyre with combined slip, vectorised over any shape (spec §4).

Zero camber, no turn slip, all shifts and asymmetry terms zero, λ = 1 except the friction scale
λ_μ. cos(atan(z)) is written as 1/√(1 + z²) (identical, one op cheaper). The functions take the
coefficients either as ``TyreCoeffs`` (floats) or as the namespace of ``prepare`` (0-dim tensors
plus a few products, which the simulator uses because float32 × Python-float costs a conversion).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from types import SimpleNamespace

import torch

__all__ = ["TyreCoeffs", "prepare", "magic_formula", "longitudinal_stiffness", "cornering_stiffness", "pure_forces"]


@dataclass(frozen=True)
class TyreCoeffs:
    """Reduced MF 5.2 coefficients of Pacejka's 205/60R15 (A3.1), sign-adapted (§4)."""

    Fz_nom: float = 4000.0  # F_z0 of the tyre model (FNOMIN), not the static corner load
    pCx1: float = 1.685
    pDx1: float = 1.210
    pDx2: float = -0.037
    pEx1: float = 0.344
    pEx2: float = 0.095
    pEx3: float = -0.020
    pKx1: float = 21.51
    pKx2: float = -0.163
    pKx3: float = 0.245
    pCy1: float = 1.193
    pDy1: float = 0.990  # published −0.990 (ISO sign convention)
    pDy2: float = -0.145  # published +0.145
    pEy1: float = -1.003
    pEy2: float = -0.537
    pKy1: float = 14.95  # published −14.95
    pKy2: float = 2.130
    rBx1: float = 12.35
    rBx2: float = -10.77
    rCx1: float = 1.092
    rBy1: float = 6.461
    rBy2: float = 4.196
    rCy1: float = 1.081
    eps_F: float = 1e-3  # ε_F [N]


def prepare(c: TyreCoeffs, dtype=None, device=None) -> SimpleNamespace:
    """Coefficients plus derived products; floats, or 0-dim tensors if ``dtype`` is given."""
    values = asdict(c)
    values.update(
        inv_Fz_nom=1.0 / c.Fz_nom,
        Ky_scale=c.pKy1 * c.Fz_nom,  # p_Ky1 F_z0
        inv_Ky_ref=1.0 / (c.pKy2 * c.Fz_nom),  # 1 / (p_Ky2 F_z0)
    )
    if dtype is not None:
        values = {k: torch.tensor(v, dtype=dtype, device=device) for k, v in values.items()}
    return SimpleNamespace(**values)


def _coeffs(c):
    return prepare(c) if isinstance(c, TyreCoeffs) else c


def longitudinal_stiffness(Fz: torch.Tensor, c) -> torch.Tensor:
    """K_x = F_z (p_Kx1 + p_Kx2 dfz) exp(p_Kx3 dfz) [N per unit slip]."""
    c = _coeffs(c)
    dfz = Fz * c.inv_Fz_nom - 1.0
    return Fz * (c.pKx1 + c.pKx2 * dfz) * torch.exp(c.pKx3 * dfz)


def cornering_stiffness(Fz: torch.Tensor, c) -> torch.Tensor:
    """K_y = p_Ky1 F_z0 sin(2 atan(F_z / (p_Ky2 F_z0))) [N/rad]."""
    c = _coeffs(c)
    return c.Ky_scale * torch.sin(2.0 * torch.atan(Fz * c.inv_Ky_ref))


def _mf(B, C, D, E, s):
    """D sin(C atan(B s − E (B s − atan(B s))))."""
    Bs = B * s
    return D * torch.sin(C * torch.atan(Bs - E * (Bs - torch.atan(Bs))))


def pure_forces(kappa, s_alpha, Fz, c, mu_scale=1.0):
    """Pure-slip forces (F_x0, F_y0) of §4; dfz = (F_z − F_z0)/F_z0 with F_z0 the tyre's nominal load."""
    c = _coeffs(c)
    dfz = Fz * c.inv_Fz_nom - 1.0
    Dx = mu_scale * (c.pDx1 + c.pDx2 * dfz) * Fz
    Ex = torch.clamp(c.pEx1 + (c.pEx2 + c.pEx3 * dfz) * dfz, max=1.0)
    Kx = Fz * (c.pKx1 + c.pKx2 * dfz) * torch.exp(c.pKx3 * dfz)
    Bx = Kx / (c.pCx1 * Dx + c.eps_F)
    Dy = mu_scale * (c.pDy1 + c.pDy2 * dfz) * Fz
    Ey = torch.clamp(c.pEy1 + c.pEy2 * dfz, max=1.0)
    Ky = c.Ky_scale * torch.sin(2.0 * torch.atan(Fz * c.inv_Ky_ref))
    By = Ky / (c.pCy1 * Dy + c.eps_F)
    return _mf(Bx, c.pCx1, Dx, Ex, kappa), _mf(By, c.pCy1, Dy, Ey, s_alpha)


def magic_formula(kappa, s_alpha, Fz, c, mu_scale=1.0):
    """Combined-slip wheel-frame forces (F_xw, F_yw) = (G_xα F_x0, G_yκ F_y0) of §4.

    ``kappa`` slip ratio κ, ``s_alpha`` = tan α, ``Fz`` ≥ 0 normal load; any common shape.
    """
    c = _coeffs(c)
    Fx0, Fy0 = pure_forces(kappa, s_alpha, Fz, c, mu_scale)
    # G_xα = cos(r_Cx1 atan(r_Bx1 cos(atan(r_Bx2 κ)) s_α)), G_yκ likewise with κ ↔ s_α
    Bxa = c.rBx1 * torch.rsqrt(1.0 + (c.rBx2 * kappa) ** 2)
    Byk = c.rBy1 * torch.rsqrt(1.0 + (c.rBy2 * s_alpha) ** 2)
    Gxa = torch.cos(c.rCx1 * torch.atan(Bxa * s_alpha))
    Gyk = torch.cos(c.rCy1 * torch.atan(Byk * kappa))
    return Gxa * Fx0, Gyk * Fy0
