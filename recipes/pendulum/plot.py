"""Learning curves (deterministic eval return vs env steps) from the recipe's CSV logs.

python recipes/pendulum/plot.py --log-dir runs/pendulum --out docs/figures/pendulum_returns.png
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

LABELS = {"dsac_t": "DSAC-T (losses.DSACTLoss)", "sac": "SAC (torchrl SACLoss)"}


def read_scalar(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A CSVLogger scalar file: rows of (step, value)."""
    with open(path) as f:
        rows = [(int(float(step)), float(value)) for step, value in csv.reader(f)]
    steps, values = zip(*rows)
    return np.array(steps), np.array(values)


def load_runs(log_dir: Path) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """{loss name: {run name: (steps, eval returns)}} for every ``<loss>_seed<k>`` run."""
    runs: dict[str, dict] = defaultdict(dict)
    for path in sorted(log_dir.glob("*_seed*/scalars/eval/return.csv")):
        run = path.parents[2].name
        runs[run.rsplit("_seed", 1)[0]][run] = read_scalar(path)
    return runs


def print_table(log_dir: Path, runs: dict) -> None:
    """Markdown rows: per-seed final return and wall time, then mean ± std per loss."""
    print("| loss | run | final return (15k steps) | wall time [min] |\n|---|---|---|---|")
    for loss, by_run in sorted(runs.items()):
        finals = []
        for run, (steps, values) in sorted(by_run.items()):
            wall_path = log_dir / run / "scalars" / "final" / "wall_time.csv"
            wall = f"{read_scalar(wall_path)[1][-1] / 60:.1f}" if wall_path.exists() else "running"
            finals.append(values[-1])
            print(f"| {loss} | {run} | {values[-1]:.1f} (at {steps[-1]}) | {wall} |")
        std = np.std(finals, ddof=1) if len(finals) > 1 else float("nan")
        print(f"| {loss} | mean ± std over {len(finals)} | {np.mean(finals):.1f} ± {std:.1f} | |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--log-dir", type=Path, default=Path("runs/pendulum"))
    parser.add_argument("--out", type=Path, default=Path("docs/figures/pendulum_returns.png"))
    parser.add_argument("--bar", type=float, default=-200.0, help="the spec's pass line")
    args = parser.parse_args()
    print_table(args.log_dir, load_runs(args.log_dir))

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for color, (loss, runs) in zip(("C0", "C1", "C2"), sorted(load_runs(args.log_dir).items())):
        for steps, values in runs.values():
            ax.plot(steps, values, color=color, alpha=0.3, lw=1)
        n = min(len(s) for s, _ in runs.values())
        steps = next(iter(runs.values()))[0][:n]
        mean = np.mean([v[:n] for _, v in runs.values()], axis=0)
        ax.plot(steps, mean, color=color, lw=2.2, label=f"{LABELS.get(loss, loss)}, mean of {len(runs)} seeds")
    ax.axhline(args.bar, color="k", ls="--", lw=1, label=f"bar ({args.bar:g})")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("deterministic return (mean of 10 episodes)")
    ax.set_title("Pendulum-v1, one update per step, same 3x256 GELU networks")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.out, dpi=130)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
