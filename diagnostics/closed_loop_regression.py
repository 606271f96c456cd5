"""Fit a trained closed-loop filter's actor by regression on the true state (a diagnostic, not a filter).

    .venv/bin/python diagnostics/closed_loop_regression.py runs/experiment1/paper/nominal/daof-v1-N20/best.pt

What would DAOF's network reach with exact gradients instead of a critic's? Each iteration
simulates fresh training runs, filters them closed loop with the current actor (so the inputs are
its own fed-back estimates, as in DAgger), then takes Adam steps on Σ_i (x̂_i − x_i)² / s_i²
(s = the system's error scale) through the deterministic estimate. The validation set is the
recipes' (20 runs × 500 steps, seed 9100). Nothing is saved; the training seeds start at 1000.
"""

from __future__ import annotations

import argparse

import torch

from daof.filters.learned import load_filter
from daof.train.validation import rmse_per_state


@torch.no_grad()
def closed_loop_inputs(filt, runs: int, steps: int, seed: int) -> list[torch.Tensor]:
    """(window, x̂_{t−1}, u_{t−1}, t, x_t) of every step of fresh runs filtered by ``filt``."""
    data = filt.system.simulate(runs, steps, seed)
    y, u_prev, u = data["measurement"], data["prev_control"], data["control"]
    rows = [
        (window, prev, u_prev[:, t], torch.full((runs, 1), t + 1), data["state"][:, t])
        for t, (window, prev, _) in enumerate(filt.stream_steps(y, u_prev, u))
    ]
    return [torch.cat(parts, 0) for parts in zip(*rows)]


def segment_rmse(estimates: torch.Tensor, truth: torch.Tensor, steps: slice = slice(None)) -> list[float]:
    """Pooled RMSE per state over the steps ``steps`` of every run."""
    return [round(v, 5) for v in rmse_per_state(estimates[:, steps], truth[:, steps]).tolist()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--updates", type=int, default=20, help="Adam steps per collection")
    parser.add_argument("--lr", type=float, default=1e-5)
    parser.add_argument("--runs", type=int, default=64)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--scratch", action="store_true", help="re-initialise the actor first")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    filt = load_filter(args.checkpoint)
    if not filt.closed_loop:
        raise SystemExit(f"{args.checkpoint} is an open-loop filter (the SLF is trained by regression already)")
    system = filt.system
    if args.scratch:
        for module in filt.policy.mlp.modules():
            if hasattr(module, "reset_parameters"):
                module.reset_parameters()
    validation = system.simulate(20, 500, 9100)

    truth = validation["state"]

    def validate() -> torch.Tensor:
        filt.eval()
        estimates = filt.run(validation)
        filt.train()
        return estimates

    print("start", segment_rmse(validate(), truth), flush=True)
    weights = 1.0 / system.error_scale**2
    optim = torch.optim.Adam(filt.policy.parameters(), lr=args.lr)
    for it in range(args.iterations):
        window, prev, u_prev, step, state = closed_loop_inputs(filt, args.runs, args.steps, 1000 + it)
        for _ in range(args.updates):
            i = torch.randint(window.shape[0], (args.batch,))
            estimate = filt.estimate(window[i], prev[i], u_prev[i], step[i])  # differentiable in the weights
            loss = ((estimate - state[i]).pow(2) * weights).sum(-1).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
        if (it + 1) % 10 == 0:
            print(it + 1, segment_rmse(validate(), truth), flush=True)
    estimates = validate()
    print(
        "all",
        segment_rmse(estimates, truth),
        "t=1",
        segment_rmse(estimates, truth, slice(0, 1)),
        "t=2",
        segment_rmse(estimates, truth, slice(1, 2)),
        "t<20",
        segment_rmse(estimates, truth, slice(0, 19)),
        "t>=50",
        segment_rmse(estimates, truth, slice(49, None)),
    )


if __name__ == "__main__":
    main()
