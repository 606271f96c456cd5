"""Fit a trained closed-loop filter's actor by regression on the true state (a diagnostic, not a filter).

    .venv/bin/python benchmarks/closed_loop_regression.py runs/experiment1/paper/nominal/daof-v1-N20/best.pt

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


@torch.no_grad()
def closed_loop_inputs(filt, runs: int, steps: int, seed: int) -> list[torch.Tensor]:
    """(window, x̂_{t−1}, u_{t−1}, t, x_t) of every step of fresh runs filtered by ``filt``."""
    system = filt.system
    data = system.simulate(runs, steps, seed)
    y, u_prev, u = data["measurement"], data["prev_control"], data["control"]
    layers = filt._inference_layers()
    measured = filt.open_loop_frames(y, u, u_prev)
    prev = system.prior.mean.expand(runs, -1).clone()
    window, rows = None, []
    for t in range(steps):
        frame = torch.cat([prev, measured[:, t]], -1)
        window = filt._first_window(frame) if window is None else torch.cat([window[:, filt.frame_dim :], frame], -1)
        rows.append((window, prev, u_prev[:, t], torch.full((runs, 1), t + 1), data["state"][:, t]))
        prev = filt._fast_estimate(layers, window, prev, u_prev[:, t], t + 1)
    return [torch.cat(parts, 0) for parts in zip(*rows)]


def segment_rmse(err2: torch.Tensor, steps: slice) -> list[float]:
    return [round(v, 5) for v in err2[:, steps].flatten(0, -2).mean(0).sqrt().tolist()]


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

    def validate() -> torch.Tensor:
        filt.eval()
        err2 = (filt.run(validation) - validation["state"]).pow(2)
        filt.train()
        return err2

    print("start", segment_rmse(validate(), slice(None)), flush=True)
    weights = 1.0 / system.error_scale**2
    optim = torch.optim.Adam(filt.policy.parameters(), lr=args.lr)
    for it in range(args.iterations):
        window, prev, u_prev, step, state = closed_loop_inputs(filt, args.runs, args.steps, 1000 + it)
        for _ in range(args.updates):
            i = torch.randint(window.shape[0], (args.batch,))
            loc, _ = filt.policy(window[i], step[i])
            if filt.acts_by_update:
                estimate = filt._add_prediction(torch.tanh(loc), prev[i], u_prev[i], step[i])
            else:
                estimate = filt.low + (filt.high - filt.low) * (torch.tanh(loc) + 1) / 2
            loss = ((estimate - state[i]).pow(2) * weights).sum(-1).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
        if (it + 1) % 10 == 0:
            print(it + 1, segment_rmse(validate(), slice(None)), flush=True)
    err2 = validate()
    print(
        "all",
        segment_rmse(err2, slice(None)),
        "t=1",
        segment_rmse(err2, slice(0, 1)),
        "t=2",
        segment_rmse(err2, slice(1, 2)),
        "t<20",
        segment_rmse(err2, slice(0, 19)),
        "t>=50",
        segment_rmse(err2, slice(49, None)),
    )


if __name__ == "__main__":
    main()
