"""RMSE of trained filters beside a reference, split into the start-up and the rest of each run.

    .venv/bin/python diagnostics/rmse_over_time.py --system linear runs/linear/nominal/daof-v1-N20-s1/best.pt
    .venv/bin/python diagnostics/rmse_over_time.py --system veh2dof runs/veh2dof/nominal/daof-v1-N20-s1/best.pt
    .venv/bin/python diagnostics/rmse_over_time.py --system veh14dof runs/experiment2/paper/nominal/*/best.pt

Data: the training runs' validation set (20 runs × 500 steps, seed 9100; ``--runs``/``--seed``
for other data). References: the Kalman filter on ``linear``; UKF and a 1000-particle PF on
``veh2dof``; none on ``veh14dof`` (no model), whose RMSEs are in SI units. Columns: all steps,
t ≥ --settled, t < --startup. ``--per-step 1,2,3`` adds a table of the RMSE at each of those
steps t (over runs). ``--large-slip 0.15`` (veh2dof) adds a table
split into the runs whose true |β| ever exceeds that many rad and the others, and lists those runs.
``--slip-bins 0.1,0.2,0.3`` (veh2dof) adds the β RMSE by bins of the true |β| over all steps;
``--only-run K`` keeps run K of the data only (e.g. one spin-out).
"""

from __future__ import annotations

import argparse

import torch
from daof.envs import make_system

from daof.filters import UKF, KalmanFilter, ParticleFilter
from daof.filters.learned import load_filter


def _rmse(err: torch.Tensor) -> str:
    return "[" + ", ".join(f"{v:.4g}" for v in err.pow(2).mean((0, 1)).sqrt().tolist()) + "]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--system", default="veh2dof", choices=["veh2dof", "linear", "veh14dof"])
    parser.add_argument("--settled", type=int, default=50)
    parser.add_argument("--startup", type=int, default=20)
    parser.add_argument("--per-step", default="", help="comma-separated steps t >= 1 for a per-step table")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=9100)
    parser.add_argument("--large-slip", type=float, default=None, help="veh2dof: split runs at this max |β| [rad]")
    parser.add_argument("--slip-bins", default="", help="veh2dof: comma-separated |β| bin edges [rad]")
    parser.add_argument("--only-run", type=int, default=None, help="keep this run of the data only")
    args = parser.parse_args()
    edges = [float(e) for e in args.slip_bins.split(",") if e.strip()]
    if edges != sorted(edges) or any(e <= 0 for e in edges):
        parser.error("--slip-bins takes increasing edges > 0")
    if args.only_run is not None and not 0 <= args.only_run < args.runs:
        parser.error(f"--only-run takes a run in 0..{args.runs - 1}")
    per_step = [int(t) for t in args.per_step.split(",") if t.strip()]
    if any(t < 1 or t > 500 for t in per_step):
        parser.error("--per-step takes steps t in 1..500")
    torch.set_num_threads(1)
    system = make_system(args.system)
    data = system.simulate(args.runs, 500, seed=args.seed)
    if args.only_run is not None:
        data = data[args.only_run : args.only_run + 1]
    if args.system == "linear":
        filters = {"Kalman filter": KalmanFilter(system)}
    elif args.system == "veh2dof":
        filters = {"UKF": UKF(system), "PF (1000)": ParticleFilter(system, 1000, seed=0)}
    else:
        filters = {}
    filters.update({path: load_filter(path, system) for path in args.checkpoints})
    print(f"| filter | all steps | t ≥ {args.settled} | t < {args.startup} |\n|---|---|---|---|")
    errors = {name: filt.run(data) - data["state"] for name, filt in filters.items()}
    for name, err in errors.items():
        print(f"| {name} | {_rmse(err)} | {_rmse(err[:, args.settled :])} | {_rmse(err[:, : args.startup])} |")
    if per_step:
        print("\n| filter | " + " | ".join(f"t = {t}" for t in per_step) + " |")
        print("|---|" + "---|" * len(per_step))
        for name, err in errors.items():
            print(f"| {name} | " + " | ".join(_rmse(err[:, t - 1 : t]) for t in per_step) + " |")
    if args.large_slip is not None and args.system == "veh2dof":
        peaks = data["state"][..., 0].abs().amax(1)
        large = peaks > args.large_slip
        first = args.only_run or 0  # run indices of the whole data set
        print(
            f"\n| filter | {int(large.sum())} runs with max |β| > {args.large_slip} | the other {int((~large).sum())} |"
        )
        print("|---|---|---|")
        for name, err in errors.items():
            cells = [_rmse(err[subset]) if subset.any() else "-" for subset in (large, ~large)]
            print(f"| {name} | {cells[0]} | {cells[1]} |")
        print(
            "\nthose runs (index: max |β| rad): "
            + ", ".join(f"{i + first}: {peaks[i]:.3f}" for i in large.nonzero().flatten().tolist())
        )
    if edges and args.system == "veh2dof":
        slip = data["state"][..., 0].abs()
        bounds = [0.0, *edges, float("inf")]
        bins = [(slip >= lo) & (slip < hi) for lo, hi in zip(bounds[:-1], bounds[1:])]
        labels = [f"{lo:g}–{hi:g} ({int(b.sum())} steps)" for lo, hi, b in zip(bounds[:-1], bounds[1:], bins)]
        print("\nβ RMSE by true |β| [rad]:\n| filter | " + " | ".join(labels) + " |\n|---|" + "---|" * len(bins))
        for name, err in errors.items():
            cells = [f"{err[..., 0][b].pow(2).mean().sqrt():.4f}" if b.any() else "-" for b in bins]
            print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
