"""How many more samples does learning an estimate from the reward need than learning it from the label?

    .venv/bin/python benchmarks/reward_vs_label.py

At γ = 0 DAOF's critic of the reward's own curvature (``network.critic_form=reward_quadratic``)
fits μ(h, a) = V(h) − c(a − m(h))² to rewards r = −c(a − x)², a drawn around m by exploration, and
its m(h) is the estimate the actor follows. The SLF fits the same m(h) to the label x. Both are
unbiased, but one reward says less about x than the label does: it holds x only through
(a − x)². This script draws x ~ N(E[x], s²) (s: the error no filter can remove), a ~ N(m, σ²) at a
current fit m = E[x] + bias, and compares the per-sample gradients in m of the two least-squares
losses (the critic's with V at its optimum): the ratio of their squared signal-to-noise ratios is
how many more samples the reward needs for the same precision of m. It is a lower bound for DAOF:
the critic's V and σ are fitted too, and the actor adds its own noise when it follows m.
"""

from __future__ import annotations

import argparse

import torch


def samples_ratio(spread: float, bias: float = 0.1, draws: int = 4_000_000, seed: int = 0) -> float:
    """(SNR of the label's gradient / SNR of the reward's gradient)², exploration std ``spread`` in units of s."""
    gen = torch.Generator().manual_seed(seed)
    s, c = 1.0, 1.0
    x = torch.randn(draws, generator=gen, dtype=torch.float64) * s
    m = bias * s
    a = m + spread * s * torch.randn(draws, generator=gen, dtype=torch.float64)
    reward = -c * (a - x) ** 2
    value = -c * (s**2 + m**2)  # the critic's V at its optimum: E[r] at a = m
    residual = (value - c * (a - m) ** 2) - reward
    grad_reward = residual * 2 * c * (a - m)  # ∂/∂m of ½ residual²
    grad_label = m - x  # ∂/∂m of ½ (m − x)²

    def snr(g: torch.Tensor) -> float:
        return float(g.mean() / g.std())

    return (snr(grad_label) / snr(grad_reward)) ** 2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spreads", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0, 4.0, 16.0])
    args = parser.parse_args()
    print("| exploration std / irreducible error | samples needed (reward / label) |")
    print("|---|---|")
    for spread in args.spreads:
        print(f"| {spread:g} | {samples_ratio(spread):.2f} |")


if __name__ == "__main__":
    main()
