"""Sweep one config key over values through the experiment machinery, with one summary table.

    python -m daof.experiments.sweep --key network.num_cells --values 64 256 -- experiment=linear profile=quick
    python -m daof.experiments.sweep --key window --values 5 20 -- experiment=veh2dof
    python -m daof.experiments.sweep --key scenario --values nominal outliers -- experiment=veh2dof

A key of the experiment config (``window``, ``scenario``, ``training_seeds``, ``profiles...``) is an
experiment override; any other key is a training override of every learned row. Each value is one
experiment (trainings reused or resumed as usual) under ``<root>/sweep/<key>/<value>``; the summary
(``summary.md`` and ``summary.json`` in ``<root>/sweep/<key>/``) gives every filter's RMSE per
state, and its ratio to the study's reference, at each value.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from daof.experiments.config import ExperimentConfig, compose_experiment, for_scenario
from daof.experiments.experiment import plan_experiment, run_experiment
from daof.io import atomic_write_text

__all__ = ["main", "summary_table", "value_overrides"]

EXPERIMENT_KEYS = {f.name for f in dataclasses.fields(ExperimentConfig)}


def value_overrides(key: str, value: str, overrides: list[str]) -> list[str]:
    """``overrides`` with ``key=value`` as an experiment key, or as the training override every learned
    row applies last (``sweep_override``: it wins over the rows' and profiles' own overrides)."""
    if key.split(".")[0] in EXPERIMENT_KEYS:
        return [*overrides, f"{key}={value}"]
    return [*overrides, f"sweep_override='{key}={value}'"]


def summary_table(key: str, results: dict[str, dict]) -> list[str]:
    """Markdown lines: one row per filter and value (value -> a report's results.json)."""
    first = next(iter(results.values()))
    states, reference = first["states"], first.get("reference")
    head = f"| filter | {key} | " + " | ".join(f"RMSE {s}" for s in states)
    head += (" | " + " | ".join(f"{s} / {reference}" for s in states)) if reference else ""
    lines = [head + " |", "|---|---|" + "---|" * (len(states) * (2 if reference else 1))]
    names = list(dict.fromkeys(n for r in results.values() for n in r["filters"]))
    for name in names:
        for value, r in results.items():
            row = r["filters"].get(name)
            if row is None:
                continue
            cells = [f"{x:.4g}" for x in row["rmse"]]
            if reference:
                cells += [
                    f"{x:.3f}" if x is not None else "–" for x in (row.get("ratio_to_oracle") or [None] * len(states))
                ]
            lines.append(f"| {name} | {value} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--key", required=True, help="a config key (experiment or training)")
    parser.add_argument("--values", nargs="+", required=True, help="the values to sweep")
    parser.add_argument("overrides", nargs="*", help="experiment=NAME and further key=value overrides")
    args = parser.parse_args(argv)
    chosen = [a.split("=", 1)[1] for a in args.overrides if a.startswith("experiment=")]
    if len(chosen) != 1:
        raise SystemExit("give one experiment=NAME after --")
    given = [a for a in args.overrides if not a.startswith("experiment=")]
    try:
        raw = compose_experiment(chosen[0], given)
        base = for_scenario(raw, raw.scenario)
        plans = {}
        for value in args.values:
            root = Path(base.root) / "sweep" / args.key / str(value)
            plans[value] = plan_experiment(chosen[0], value_overrides(args.key, value, [*given, f"root={root}"]))
    except ValueError as error:
        raise SystemExit(str(error)) from None
    results = {}
    for value, plan in plans.items():
        print(f"== {args.key}={value}")
        report = run_experiment(plan)[0]
        results[value] = json.loads(report.with_name("results.json").read_text())
    out = Path(base.root) / "sweep" / args.key
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# Sweep of `{args.key}` ({chosen[0]}, {base.profile} profile)", "", *summary_table(args.key, results)]
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "summary.json", json.dumps({"key": args.key, "results": results}, indent=1))
    print("\n".join(lines))
    print(f"summary: {out / 'summary.md'}")
    return out / "summary.md"


if __name__ == "__main__":
    sys.exit(main() and 0)
