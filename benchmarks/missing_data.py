"""DAOF-v1 under sensor dropout: what a missing measurement should read as (docs/missing_data.md).

    .venv/bin/python benchmarks/missing_data.py runs/veh2dof/nominal/daof-v1-N20-s1/best.pt

A trained DAOF-v1 (trained on complete data) filters fresh runs (seed 9300, disjoint from training,
validation and evaluation seeds) under several gap patterns, once per treatment of a missing
channel (``LearnedFilter.missing_fill``): "hold" its last value, or read the "prediction"
g(f(x̂_{t−1}, u_{t−1}), u_t). The UKF, which skips the update of a missing channel, is the
reference. Prints pooled RMSE per state as a markdown table.
"""

from __future__ import annotations

import argparse

import torch

from daof.evaluate import Dropout
from daof.evaluate.dropout import apply_dropout
from daof.evaluate.metrics import pooled_rmse
from daof.filters import UKF
from daof.filters.learned import MISSING_FILLS, load_filter
from envs import make_system


def patterns(system, data) -> dict:
    """Gap pattern name -> data with those measurement entries NaN."""
    names = system.measurement_names
    out = {"complete": data}
    out["study dropout (10 % gaps + 1 s yaw-rate blackout)"] = Dropout().apply(data, system)
    out["30 % gaps"] = apply_dropout(data, 0.3, seed=1)
    for channel in names:
        gone = data.clone()
        y = gone["measurement"].clone()
        y[..., names.index(channel)] = float("nan")
        gone.set("measurement", y)
        out[f"{channel} always missing"] = gone
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=9300)
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = make_system("veh2dof")
    filt = load_filter(args.checkpoint, system, expect={"kind": "DAOF-v1"})
    ukf = UKF(system)
    data = system.simulate(args.runs, args.steps, seed=args.seed)
    states = ", ".join(system.state_names)
    print(f"{args.runs} runs x {args.steps} steps, seed {args.seed}; pooled RMSE [{states}]\n")
    print("| gaps | UKF | " + " | ".join(f"DAOF-v1, {fill}" for fill in MISSING_FILLS) + " |")
    print("|---" * (2 + len(MISSING_FILLS)) + "|")
    for name, gappy in patterns(system, data).items():
        row = [pooled_rmse(ukf.run(gappy), gappy["state"])]
        for fill in MISSING_FILLS:
            filt.missing_fill = fill
            estimates = filt.run(gappy)
            assert torch.isfinite(estimates).all(), f"non-finite DAOF-v1 estimate ({fill}, {name})"
            row.append(pooled_rmse(estimates, gappy["state"]))
        cells = " | ".join("[" + ", ".join(f"{v:.5f}" for v in r.tolist()) + "]" for r in row)
        print(f"| {name} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
