"""Learned filters under sensor dropout: what a missing measurement should read as (docs/missing_data.md).

    .venv/bin/python diagnostics/missing_data.py runs/veh2dof/nominal/daof-v1-N20-s1/best.pt [more/best.pt ...]

Trained filters (DAOF-v1, DAOF-v2 or SLF checkpoints on veh2dof) filter fresh runs (seed 9300,
disjoint from training, validation and evaluation seeds) under several gap patterns. A DAOF-v1
runs once per treatment of a missing channel (``LearnedFilter.missing_fill``): "hold" its last
value, or read the "prediction" g(f(x̂_{t−1}, u_{t−1}), u_t); the model-free filters hold (an SLF
trained with ``network.missing_mask`` also reads where the gaps are). The UKF, which skips the
update of a missing channel, is the reference. Prints pooled RMSE per state as a markdown table,
one column per filter and treatment, labelled by the checkpoint's directory.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from daof.envs import make_system

from daof.evaluate import Dropout
from daof.evaluate.dropout import apply_dropout
from daof.evaluate.metrics import pooled_rmse
from daof.filters import UKF
from daof.filters.learned import MISSING_FILLS, load_filter


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


def columns(paths: list[str], system) -> list[tuple[str, object, str]]:
    """(label, filter, missing_fill) per column: every treatment a checkpoint's filter supports."""
    out = []
    for path in paths:
        filt = load_filter(path, system)
        fills = MISSING_FILLS if filt.config.kind == "DAOF-v1" else ("hold",)
        out += [(f"{filt.config.kind} `{Path(path).parent.name}`, {fill}", filt, fill) for fill in fills]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=9300)
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = make_system("veh2dof")
    cols = columns(args.checkpoints, system)
    ukf = UKF(system)
    data = system.simulate(args.runs, args.steps, seed=args.seed)
    states = ", ".join(system.state_names)
    print(f"{args.runs} runs x {args.steps} steps, seed {args.seed}; pooled RMSE [{states}]\n")
    print("| gaps | UKF | " + " | ".join(label for label, _, _ in cols) + " |")
    print("|---" * (2 + len(cols)) + "|")
    for name, gappy in patterns(system, data).items():
        row = [pooled_rmse(ukf.run(gappy), gappy["state"])]
        for label, filt, fill in cols:
            filt.missing_fill = fill
            estimates = filt.run(gappy)
            assert torch.isfinite(estimates).all(), f"non-finite estimate ({label}, {name})"
            row.append(pooled_rmse(estimates, gappy["state"]))
        cells = " | ".join("[" + ", ".join(f"{v:.5f}" for v in r.tolist()) + "]" for r in row)
        print(f"| {name} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
