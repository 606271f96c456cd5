"""When did a training run beat its reference on the validation set, in wall time?

Reads each run directory's ``learning_curve.csv`` (validation RMSE per state against frames and
wall seconds) and ``summary.json`` (the reference's validation RMSE, e.g. the UKF's) and prints,
per run: the first validation point below the reference, the point from which every later one
stays below, and the best. "Below" is the mean over states of RMSE / the reference's under 1,
and separately every state below the reference's.

    .venv/bin/python diagnostics/time_to_reference.py runs/experiment1/paper/nominal/daof-v1-N20-s*
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path


def load_run(directory: Path) -> tuple[list[dict], str, list[float]]:
    """(validation records, reference name, reference RMSE per state) of one run directory."""
    with open(directory / "learning_curve.csv") as fh:
        records = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]
    refs = json.loads((directory / "summary.json").read_text()).get("validation_references") or {}
    if not refs:
        raise SystemExit(f"{directory}: summary.json has no validation reference")
    name, values = next(iter(refs.items()))
    return records, name, values


def first_and_settled(records: list[dict], below) -> tuple[dict | None, dict | None]:
    """The first record that is ``below`` and the first from which all later records are."""
    first = next((r for r in records if below(r)), None)
    settled = None
    for r in reversed(records):
        if not below(r):
            break
        settled = r
    return first, settled


def minutes(record: dict | None) -> str:
    return "never" if record is None else f"{record['wall_s'] / 60:.1f} min ({record['frames'] / 1e3:.0f}k frames)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (with learning_curve.csv)")
    args = parser.parse_args()
    for directory in args.runs:
        records, name, ref = load_run(directory)
        states = [k[len("rmse_") :] for k in records[0] if k.startswith("rmse_")]

        def mean_ratio(r, states=states, ref=ref):
            return sum(r[f"rmse_{s}"] / v for s, v in zip(states, ref)) / len(ref)

        def all_below(r, states=states, ref=ref):
            return all(r[f"rmse_{s}"] < v for s, v in zip(states, ref))

        best = min(records, key=mean_ratio)
        print(f"{directory} (reference {name}: {', '.join(f'{s} {v:.4g}' for s, v in zip(states, ref))})")
        for label, below in (
            ("mean ratio < 1", lambda r: mean_ratio(r) < 1.0),
            ("every state below", all_below),
        ):
            first, settled = first_and_settled(records, below)
            print(f"  {label:18s} first at {minutes(first)}; stays from {minutes(settled)}")
        ratios = ", ".join(f"{best[f'rmse_{s}'] / v:.3f}" for s, v in zip(states, ref))
        print(f"  best: mean ratio {mean_ratio(best):.4f} at {minutes(best)}; RMSE / {name} per state {ratios}")
        print(f"  run: {records[-1]['wall_s'] / 60:.1f} min, {records[-1]['updates']:.0f} updates")


if __name__ == "__main__":
    main()
