"""How well calibrated is each filter's error std? NEES and ±2σ coverage per state on fresh evaluation data.

    python -m daof.train.uncertainty RUNS/daof-v1-N20-s1        # first, a head beside each learned filter
    python diagnostics/calibration.py veh2dof RUNS OUT           # EKF, UKF, PF and every RUNS/*-N20-s1/best.pt
    python diagnostics/calibration.py linear RUNS OUT --runs 100 --steps 500 --seed 20261122

Runs the study (``daof.evaluate.run_study``, no cost timing) of the system's classical filters (veh2dof: EKF,
UKF, PF with 1000 particles; linear: KF, KF-stationary, PF) and every learned filter whose run directory
``RUNS/<kind>-N<window>-s<seed>`` (``--pattern``) holds a ``best.pt`` (with its uncertainty head where fitted;
a row per training seed where several match), caches each filter's result in OUT/study under a digest of its
checkpoint and head, writes the report with its calibration section and figure to OUT, and prints the
calibration table; with ``--split S`` (default 50) also the start-up t ≤ S and the rest apart, and beside
each learned filter a constant σ per state (its head's offset), which shows what the head adds.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import torch
from daof.envs.registry import make_system

from daof.evaluate import run_study
from daof.evaluate.metrics import calibration
from daof.evaluate.report import ReportSpec, write_report
from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter, StationaryKalmanFilter
from daof.filters.learned import LearnedFilter, load_filter
from daof.filters.learned.uncertainty import head_path
from daof.fingerprint import checkpoint_fingerprint, classical_fingerprint

CLASSICAL = {
    "veh2dof": lambda s: {"EKF": EKF(s), "UKF": UKF(s), "PF": ParticleFilter(s, 1000, seed=1)},
    "linear": lambda s: {
        "KF": KalmanFilter(s),
        "KF-stationary": StationaryKalmanFilter(s),
        "PF": ParticleFilter(s, 1000, seed=1),
    },
}
REFERENCE = {"veh2dof": "UKF", "linear": "KF"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("system", choices=sorted(CLASSICAL))
    parser.add_argument("runs_root", type=Path, help="directory of the learned filters' run directories")
    parser.add_argument("out", type=Path)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--pattern", default="*-N20-s1", help="which run directories (glob)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--split", type=int, default=50, help="also the start-up t ≤ SPLIT and after it (0: not)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    system = make_system(args.system)
    filters = CLASSICAL[args.system](system)
    versions = {name: classical_fingerprint(filt, system) for name, filt in filters.items()}
    runs = [run for run in sorted(args.runs_root.glob(args.pattern)) if (run / "best.pt").is_file()]
    seed_of = {run: re.search(r"-s(\d+)$", run.name)[1] for run in runs}
    for run in runs:
        filt = load_filter(run / "best.pt", system)
        # a row per training seed where there are several ("DAOF-v1 (seed 2)", the reports' rows)
        name = filt.name if len(set(seed_of.values())) == 1 else f"{filt.name} (seed {seed_of[run]})"
        filters[name] = filt
        files = [run / "best.pt", head_path(run / "best.pt")]
        versions[name] = checkpoint_fingerprint([f for f in files if f.is_file()])  # a refitted head runs again
    start = time.perf_counter()
    study = run_study(
        system,
        filters,
        args.runs,
        args.steps,
        args.seed,
        measure_cost=False,
        cache_dir=args.out / "study",
        reference=REFERENCE[args.system],
        versions=versions,
    )
    command = f"python diagnostics/calibration.py {args.system} {args.runs_root} {args.out}"
    command += f" --runs {args.runs} --steps {args.steps} --seed {args.seed} --pattern '{args.pattern}'"
    meta = {"command": command, "wall_s": round(time.perf_counter() - start, 1)}
    spec = ReportSpec(meta=meta)
    write_report(study, args.out, title=f"Calibration of the error std: {args.system}", profile="paper", spec=spec)
    names = system.state_names
    print(f"\n| filter | σ from | NEES ({' / '.join(names)}) | ±2σ coverage [%] ({' / '.join(names)}) | RMSE |")
    print("|---|---|---|---|---|")
    for name, r in study.results.items():
        if r.nees is None:
            print(f"| {name} | – | – | – | {' / '.join(f'{v:.4g}' for v in r.rmse)} |")
            continue
        nees = " / ".join(f"{v:.3f}" for v in r.nees)
        cover = " / ".join(f"{100 * v:.1f}" for v in r.coverage_2sigma)
        print(f"| {name} | {r.std_source} | {nees} | {cover} | {' / '.join(f'{v:.4g}' for v in r.rmse)} |")
    if args.split:
        print(split_table(study, filters, args.split))
    print(f"\nreport: {args.out / 'report.md'}")


def split_table(study, filters: dict, split: int) -> str:
    """NEES and ±2σ coverage per state over the start-up (t ≤ split) and after it, for every filter with a std;
    for a learned filter also those of a constant σ per state, its head's offset (the RMS error on the head's
    training data): what the head adds beyond the right average size."""
    truth = study.data["state"]
    parts = {f"t ≤ {split}": slice(0, split), f"t > {split}": slice(split, None)}
    head = [f"{k} {part}" for k in ("NEES", "±2σ [%]") for part in parts]
    lines = ["", f"| filter | σ | {' | '.join(head)} | NEES all | ±2σ [%] all |", "|---|---|" + "---|" * 6]

    def row(name, what, estimates, std):
        c = {part: calibration(estimates[:, sl], truth[:, sl], std[:, sl]) for part, sl in parts.items()}
        every = calibration(estimates, truth, std)
        cells = [" / ".join(f"{v:.3f}" for v in c[part]["nees"]) for part in parts]
        cells += [" / ".join(f"{100 * v:.1f}" for v in c[part]["coverage"]) for part in parts]
        cells += [
            " / ".join(f"{v:.3f}" for v in every["nees"]),
            " / ".join(f"{100 * v:.1f}" for v in every["coverage"]),
        ]
        return f"| {name} | {what} | " + " | ".join(cells) + " |"

    for name, filt in filters.items():
        if filt.std_source is None:
            continue
        estimates, std = filt.run_with_std(study.data)
        estimates, std = estimates.cpu(), std.cpu()
        lines.append(row(name, filt.std_source, estimates, std))
        if isinstance(filt, LearnedFilter):
            constant = (0.5 * filt.uncertainty.log_variance_offset).exp().expand_as(std)
            lines.append(row(name, "constant σ (head's offset)", estimates, constant))
    return "\n".join(lines)


if __name__ == "__main__":
    main()
