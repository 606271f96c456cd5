"""How many more samples does learning an estimate from the reward need than learning it from the label?

    .venv/bin/python diagnostics/reward_vs_label.py

At γ = 0 DAOF's critic of the reward's own curvature (``network.critic_form=reward_quadratic``)
fits μ(h, a) = V(h) − c(a − m(h))² to rewards r = −c(a − x)², a drawn around m by exploration, and
its m(h) is the estimate the actor follows. The SLF fits the same m(h) to the label x. This script
draws x ~ N(E[x], s²) (s: the error no filter can remove), a ~ N(m, σ_a²) at a current fit
m = E[x] + bias, and compares per-sample gradients in m of the critic's mean term (V at its
optimum) with the label's: the ratio of their squared signal-to-noise ratios is how many more
samples the critic needs for the same precision of m. Two weightings of the critic's mean term:

* ``unweighted``: least squares, what DSAC-T's 1/(σ² + ε) amounts to when ε ≫ σ² (veh14dof's
  rewards with ε = 0.1) or when σ depends on h alone;
* ``reward spread``: weighted by 1/Var(r | h, a) = 1/(c²(4(a − m)²s² + 2s⁴)), what DSAC-T's
  1/(σ² + ε) is with ``network.critic_scale=reward`` and ε ≪ σ² (``FilterCritic``).

One reward with a known a holds x up to a reflection about a, so it need not say less than the
label: weighted by the reward's spread, the critic needs about as many samples as the label once
the exploration is wide. Both are lower bounds for DAOF: the critic's V and σ are fitted too, and
the actor adds its own noise when it follows m.
"""

from __future__ import annotations

import argparse

import torch


def samples_ratios(spread: float, bias: float = 0.1, draws: int = 4_000_000, seed: int = 0) -> tuple[float, float]:
    """Samples needed relative to the label (unweighted, reward-spread weighted); ``spread``: exploration std / s."""
    gen = torch.Generator().manual_seed(seed)
    s, c = 1.0, 1.0
    x = torch.randn(draws, generator=gen, dtype=torch.float64) * s
    m = bias * s
    a = m + spread * s * torch.randn(draws, generator=gen, dtype=torch.float64)
    reward = -c * (a - x) ** 2
    value = -c * (s**2 + m**2)  # the critic's V at its optimum: E[r] at a = m
    residual = (value - c * (a - m) ** 2) - reward
    grad_unweighted = residual * 2 * c * (a - m)  # ∂/∂m of ½ residual²
    grad_weighted = grad_unweighted / (c**2 * (4 * (a - m) ** 2 * s**2 + 2 * s**4))
    grad_label = m - x  # ∂/∂m of ½ (m − x)²

    def snr(g: torch.Tensor) -> float:
        return float(g.mean() / g.std())

    return (snr(grad_label) / snr(grad_unweighted)) ** 2, (snr(grad_label) / snr(grad_weighted)) ** 2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spreads", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0, 4.0, 16.0])
    args = parser.parse_args()
    print("| exploration std / irreducible error | samples needed / label's: unweighted | reward-spread weighted |")
    print("|---|---|---|")
    for spread in args.spreads:
        unweighted, weighted = samples_ratios(spread)
        print(f"| {spread:g} | {unweighted:.2f} | {weighted:.2f} |")


if __name__ == "__main__":
    main()
