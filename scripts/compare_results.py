"""Compare the RMSE values of two study reports (``results.json``), filter by filter and state by state.

    python scripts/compare_results.py OLD/results.json NEW/results.json            # bit for bit
    python scripts/compare_results.py OLD/results.json NEW/results.json --digits 4  # to 4 significant digits

Compares every filter's pooled RMSE and per-run RMSE (and the window study's RMSE where present).
Costs and wall times are not compared. Exit status 0 when all agree, 1 otherwise (the differences
are printed, one line each).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def rmse_values(results: dict) -> dict[str, float]:
    """Every RMSE number of a report, keyed ``filter/kind/index``."""
    out = {}
    for name, row in results["filters"].items():
        for i, value in enumerate(row["rmse"]):
            out[f"{name}/rmse/{i}"] = value
        for r, per_state in enumerate(row.get("per_run_rmse") or []):
            for i, value in enumerate(per_state):
                out[f"{name}/run{r}/{i}"] = value
    for row in results.get("window_study") or []:
        for i, value in enumerate(row["rmse"]):
            out[f"window N={row['window']}/rmse/{i}"] = value
    return out


def agree(a: float, b: float, digits: int | None) -> bool:
    if digits is None or not (math.isfinite(a) and math.isfinite(b)):
        return a == b or (math.isnan(a) and math.isnan(b))
    return f"{a:.{digits - 1}e}" == f"{b:.{digits - 1}e}"


def compare(old: dict, new: dict, digits: int | None) -> list[str]:
    a, b = rmse_values(old), rmse_values(new)
    problems = [f"only in one report: {key}" for key in sorted(set(a) ^ set(b))]
    shared = sorted(set(a) & set(b))
    problems += [f"{key}: {a[key]!r} -> {b[key]!r}" for key in shared if not agree(a[key], b[key], digits)]
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--digits", type=int, default=None, help="significant digits to compare (default: exact)")
    args = parser.parse_args(argv)
    old, new = (json.loads(p.read_text()) for p in (args.old, args.new))
    problems = compare(old, new, args.digits)
    count = len(rmse_values(old))
    for line in problems:
        print(line)
    how = "bit for bit" if args.digits is None else f"to {args.digits} significant digits"
    print(f"{count - len(problems)} of {count} RMSE values agree {how}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
