"""Write a study's report directory: report.md, results.csv, results.json and the figures.

What a report holds beyond the study's own numbers is a ``ReportSpec``: its ``Layout`` (one
column of all states or one per state, the filter every other one is compared with run by run,
the paper's table shown for context), the learned filters' training record, a window study,
requirements checked against the numbers, and notes. Nothing here depends on which system it is:
units and scales come from the system (``in_report_units``), everything else from the spec.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import platform
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import torch

from daof.evaluate import figures
from daof.evaluate.metrics import DIVERGENCE_FACTOR, paired_rmse_ratio
from daof.evaluate.study import ORACLE
from daof.io import atomic_write_text

__all__ = [
    "Layout",
    "PaperTable",
    "ReportSpec",
    "Requirement",
    "Training",
    "SeedSpread",
    "WindowStudy",
    "environment_info",
    "in_report_units",
    "ratio_label",
    "scenario_winners",
    "write_report",
    "write_scenario_report",
    "PAPER_TABLES",
    "PAPER_TABLE_I",
    "PAPER_TABLE_II",
]

#: The paper's Table I (Experiment I): RMSE β [rad], RMSE r [rad/s], cost [ms]. Context only: the
#: paper does not publish its system parameters, so the absolute numbers are not comparable.
PAPER_TABLE_I = {
    "UKF": (39.91, 0.94, 0.28),
    "PF": (0.19, 0.47, 21.4),
    "SLF": (0.14, 0.68, 0.92),
    "DAOF-v2": (0.04, 0.19, 0.63),
    "DAOF-v1": (0.03, 0.09, 0.65),
}
PAPER_WINDOWS = {1: (0.29, 0.29), 5: (0.21, 0.29), 10: (0.16, 0.31), 20: (0.11, 0.34)}
#: The paper's Table II (Experiment II, 14-DOF): RMSE pitch [°], roll [°], yaw rate [°/s], side slip
#: [°], Vx [km/h], ax [g], cost [ms]. Context only, as for Table I.
PAPER_TABLE_II = {
    "SLF": (0.262, 1.863, 1.513, 0.587, 4.545, 0.020, 0.45),
    "DAOF-v2": (0.012, 0.022, 0.082, 0.015, 0.105, 0.002, 0.63),
}


@dataclass(frozen=True)
class PaperTable:
    """One of the paper's tables, shown in a report for context (``Layout.paper_table``)."""

    number: str
    caveat: str
    columns: tuple[str, ...]
    rows: dict[str, tuple]
    #: the paper's window study (N -> RMSE per state), a column of the report's window study
    windows: dict[int, tuple] = field(default_factory=dict)
    windows_column: str = ""


PAPER_TABLES = {
    "I": PaperTable(
        "I",
        "The paper does not publish its system parameters; its absolute numbers are not comparable with ours, "
        "only the ordering and ratios between filters are.",
        ("RMSE β [rad]", "RMSE r [rad/s]", "cost [ms]"),
        PAPER_TABLE_I,
        PAPER_WINDOWS,
        "paper RMSE β / r (for context)",
    ),
    "II": PaperTable(
        "II",
        "The paper does not publish its vehicle parameters, manoeuvre or sensor set-up; its absolute numbers are "
        "not comparable with ours, only the ordering and ratios between filters are.",
        ("RMSE pitch [deg]", "roll [deg]", "yaw rate [deg/s]", "side slip [deg]", "Vx [km/h]", "ax [g]", "cost [ms]"),
        PAPER_TABLE_II,
    ),
}


@dataclass
class Layout:
    """How a report lays out its study (an experiment config's ``report:``)."""

    per_state: bool = False  # one RMSE column per state, a per-run spread table and a figure per state (Table II)
    paired_with: str | None = None  # every other filter compared run by run with this one (``paired_comparison``)
    paper_table: str | None = None  # the paper's table shown for context: a key of PAPER_TABLES (I | II)


@dataclass
class Requirement:
    """A requirement decided from the study's numbers, stated as met or not met."""

    requirement: str
    met: bool
    detail: str = ""


@dataclass
class Training:
    """The learned filters' training: validation curves, reference lines beside them, costs."""

    curves: dict[str, list[dict]] = field(default_factory=dict)  # filter -> validation history
    references: dict[str, list[float]] = field(default_factory=dict)  # e.g. UKF -> its RMSE on the validation set
    costs: dict[str, dict] = field(default_factory=dict)  # filter -> frames, updates, wall_s, threads


@dataclass
class WindowStudy:
    """One learned filter at several input windows N: ``{"window", "name", "rmse", "cost_ms"}`` per N
    (``name``: the study's row of that N)."""

    filter: str
    rows: list[dict]


@dataclass
class SeedSpread:
    """Learned rows trained on several seeds: row -> its report rows, one per seed (seed -> name)."""

    rows: dict[str, dict[int, str]]


def seed_spread(study, spread: SeedSpread, paired: dict | None, paired_with: str | None) -> dict:
    """Per learned row over its seeds: mean and std (n − 1) of RMSE and of the ratio to the study's
    reference per state, the per-seed values, and per seed the paired ratio to ``paired_with`` with
    how many seeds beat it on every state."""
    out = {}
    for row, names in spread.rows.items():
        rmse = torch.tensor([study.results[n].rmse for n in names.values()], dtype=torch.float64)
        entry = {
            "seeds": list(names),
            "rmse_mean": rmse.mean(0).tolist(),
            "rmse_std": rmse.std(0).tolist() if len(names) > 1 else [0.0] * rmse.shape[1],
            "rmse": {seed: study.results[n].rmse for seed, n in names.items()},
        }
        ratios = [study.results[n].ratio_to_oracle for n in names.values()]
        if all(r is not None for r in ratios):
            r = torch.tensor(ratios, dtype=torch.float64)
            entry["ratio_mean"] = r.mean(0).tolist()
            entry["ratio_std"] = r.std(0).tolist() if len(names) > 1 else [0.0] * r.shape[1]
        if paired and all(n in paired for n in names.values()):
            entry["paired_with"] = paired_with
            entry["paired"] = {seed: paired[n] for seed, n in names.items()}
            entry["seeds_better"] = sum(all(x < 1 for x in paired[n]["ratio"]) for n in names.values())
        out[row] = entry
    return out


def _seed_lines(spread: dict, study) -> list[str]:
    if not spread:
        return []
    names = study.system.state_names
    ref = study.reference
    lines = ["## Over training seeds", ""]
    head = "| filter | seeds | " + " | ".join(f"RMSE {n}: mean ± std" for n in names)
    head += (" | " + " | ".join(f"{n} / {ref}: mean ± std" for n in names)) if ref else ""
    lines += [head + " |", "|---|---|" + "---|" * (len(names) * (2 if ref else 1))]
    for row, e in spread.items():
        cells = [f"{m:.4g} ± {sd:.2g}" for m, sd in zip(e["rmse_mean"], e["rmse_std"])]
        if ref and "ratio_mean" in e:
            cells += [f"{m:.3f} ± {sd:.3f}" for m, sd in zip(e["ratio_mean"], e["ratio_std"])]
        lines.append(f"| {row} | {', '.join(map(str, e['seeds']))} | " + " | ".join(cells) + " |")
    for row, e in spread.items():
        if "paired" not in e:
            continue
        lines += [
            "",
            f"{row} per seed, paired with the {e['paired_with']} (ratio [95 % interval] per state): "
            + "; ".join(
                f"seed {seed}: "
                + ", ".join(f"{r:.3f} [{lo:.3f}, {hi:.3f}]" for r, lo, hi in zip(c["ratio"], c["low"], c["high"]))
                for seed, c in e["paired"].items()
            )
            + f". **{e['seeds_better']} of {len(e['seeds'])} seeds beat the {e['paired_with']} on every state.**",
        ]
    return lines + [""]


@dataclass
class ReportSpec:
    """What ``write_report`` writes beyond the study's own numbers."""

    layout: Layout = field(default_factory=Layout)
    training: Training | None = None
    window_study: WindowStudy | None = None
    seeds: SeedSpread | None = None  # learned rows trained on several seeds
    requirements: list[Requirement] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)  # provenance: the command, wall time, ...


def environment_info() -> dict:
    """Commit, machine and package versions, for the report's provenance."""
    import tensordict
    import torchrl

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], capture_output=True, text=True).stdout.strip()
        commit += "+dirty" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "commit": commit,
        "machine": f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}",
        "versions": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "torchrl": torchrl.__version__,
            "tensordict": tensordict.__version__,
        },
    }


def _fmt(values, digits=4) -> str:
    if values is None:
        return "–"
    return " / ".join(f"{v:.{digits}g}" for v in values)


def ratio_label(study) -> str:
    """What the ratio column is relative to: the study's reference filter, and on a scenario other
    than nominal, that the PF-oracle filters with the nominal model there (so it is no optimum)."""
    ref = getattr(study, "reference", None) or ORACLE
    if ref == ORACLE and study.system.scenario != "nominal":
        return f"ratio to {ref} (nominal model)"
    return f"ratio to {ref}"


def _divergence_sentence(study, ref: str | None) -> str:
    """What the diverged count counts (``daof.evaluate.study._add_oracle_metrics``), with the system's limits."""
    s = study.system
    low, high = s.divergence_limits()
    limits = ", ".join(f"{n} [{lo:.3g}, {hi:.3g}] {u}" for n, u, lo, hi in zip(s.state_names, s.state_units, low, high))
    text = (
        "a diverged run has a non-finite estimate, or one outside the output range (the range of the system's "
        "simulated states widened by its width on each side) widened again by its width on each side "
        f"({limits})"
    )
    if ref is not None:
        text += f", or an RMSE above {DIVERGENCE_FACTOR:g}x {ref}'s RMSE on the same run"
    return text + "."


def _saturation_sentence(study) -> list[str]:
    """What the bound column counts, when some filter has bounds (the learned filters)."""
    if not any(r.saturated is not None for r in study.results.values()):
        return []
    return [
        "At a bound: per state, the share of a learned filter's estimates at an end of its output range (the "
        "plausible state range it is clamped or squashed to; within 1e-6 of the range's width); – for filters "
        "without bounds.",
        "",
    ]


def _reference_lines(study) -> list[str]:
    """Sentences under the results table: what the ratios, the diverged count and the bound column compare with."""
    ref = getattr(study, "reference", None)
    lines = _saturation_sentence(study)
    if ref is None:
        return ["In the diverged count, " + _divergence_sentence(study, None), "", *lines]
    if ref == ORACLE and study.system.scenario != "nominal":
        return [
            f"Scenario `{study.system.scenario}`: the PF-oracle is the near-optimal reference only on `nominal`. "
            "Here it filters with the nominal model like every model-based filter, so the ratios are relative "
            "to the nominal-model PF-oracle (a ratio below 1 is possible), not to the optimum; "
            + _divergence_sentence(study, ref),
            "",
            *lines,
        ]
    return [f"Ratios are per state, relative to {ref}; " + _divergence_sentence(study, ref), "", *lines]


def _calibration_lines(study) -> list[str]:
    """The calibration table (``FilterResult.nees``, ``coverage_2sigma``), when some filter gives an error std."""
    rows = {name: r for name, r in study.results.items() if r.nees is not None}
    if not rows:
        return []
    names = " / ".join(study.system.state_names)
    lines = [
        "## Calibration of the error std",
        "",
        "Filters that give an error std σ beside each estimate: the mean NEES e²/σ² per state (1 when σ is right; "
        "above 1 the filter is overconfident, below 1 too cautious) and the share of errors within ±2σ (95.45 % "
        f"for Gaussian errors with the right σ), over all {study.runs} × {study.steps} estimates. σ comes from "
        "the Kalman-type filters' covariance P⁺, the PFs' weighted particle spread, and the learned filters' "
        "uncertainty head, fitted after the filter on data of its own seed (docs/uncertainty.md). Left out: "
        "entries with a non-finite error or σ, or σ ≤ 0.",
        "",
        f"| filter | σ from | NEES ({names}) | ±2σ coverage [%] ({names}) | left out |",
        "|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        cover = " / ".join(f"{100 * v:.1f}" for v in r.coverage_2sigma)
        left_out = " / ".join(str(v) for v in r.std_excluded) if any(r.std_excluded) else "0"
        lines.append(f"| {name} | {r.std_source} | {_fmt(r.nees, 3)} | {cover} | {left_out} |")
    return lines + [""]


def _saturated(r) -> str:
    return _fmt(r.saturated, 3) if r.saturated is not None else "–"


def _results_table(study) -> list[str]:
    s = study.system
    states = " / ".join(f"{n} [{u}]" for n, u in zip(s.state_names, s.state_units))
    lines = [
        f"| filter | RMSE {states} | {ratio_label(study)} ({' / '.join(s.state_names)}) "
        "| per-run RMSE median (IQR) | cost per estimate [ms] (batch 1) | throughput [estimates/s] (batch R) "
        f"| diverged runs | covariance repairs | at a bound ({' / '.join(s.state_names)}) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in study.results.items():
        runs = torch.tensor(r.per_run_rmse)
        q = torch.quantile(runs, torch.tensor([0.25, 0.5, 0.75]), dim=0)
        spread = " / ".join(f"{q[1, j]:.3g} ({q[0, j]:.3g}–{q[2, j]:.3g})" for j in range(runs.shape[1]))
        cost = f"{r.cost_ms:.3f}" if r.cost_ms is not None else "–"
        lines.append(
            f"| {name} | {_fmt(r.rmse)} | {_fmt(r.ratio_to_oracle, 3)} | {spread} | {cost} | "
            f"{r.throughput_per_s:,.0f} | {r.diverged} | {r.repairs} | {_saturated(r)} |"
        )
    return lines


#: the fields of each filter in the scenario report's results.json
_SCENARIO_FIELDS = (
    *("rmse", "ratio_to_oracle", "cost_ms", "diverged", "diverged_runs", "repairs", "saturated"),
    *("std_source", "nees", "coverage_2sigma"),
)

#: bootstrap resamples of the report's paired comparison
PAIRED_DRAWS = 4000


def paired_comparison(study, reference: str) -> dict[str, dict]:
    """Every other filter's pooled-RMSE ratio to ``reference`` with its paired bootstrap interval."""
    base = torch.tensor(study.results[reference].per_run_rmse)
    return {
        name: paired_rmse_ratio(torch.tensor(r.per_run_rmse), base, draws=PAIRED_DRAWS)
        for name, r in study.results.items()
        if name != reference
    }


def _paired_lines(study, reference: str, comparison: dict[str, dict]) -> list[str]:
    names = study.system.state_names
    level = round(100 * next(iter(comparison.values()))["level"])
    lines = [
        f"## Paired with the {reference}",
        "",
        f"Pooled RMSE over the {reference}'s on the same {study.runs} runs, with a {level} % paired bootstrap "
        f"interval over runs ({PAIRED_DRAWS:,} resamples; `daof.evaluate.metrics.paired_rmse_ratio`): how far a "
        "difference in the results table stands out of the run-to-run spread. Below 1 is better.",
        "",
        "| filter | "
        + " | ".join(f"{n}: ratio [{level} % interval]" for n in names)
        + f" | runs better ({' / '.join(names)}) |",
        "|---|" + "---|" * (len(names) + 1),
    ]
    for name, c in comparison.items():
        cells = [f"{c['ratio'][j]:.3f} [{c['low'][j]:.3f}, {c['high'][j]:.3f}]" for j in range(len(names))]
        better = " / ".join(f"{b}/{c['runs']}" for b in c["better_runs"])
        lines.append(f"| {name} | {' | '.join(cells)} | {better} |")
    return lines + [""]


def _dropout_lines(study) -> list[str]:
    """What was missing, when the study ran on data with measurement gaps (``run_study(dropout=...)``)."""
    info = getattr(study, "dropout", None)
    if info is None:
        return []
    names = study.system.measurement_names
    text = f"**Sensor dropout**: every measurement channel missing (NaN) with probability {info['p']:g} per step"
    if info.get("blackout"):
        b = info["blackout"]
        text += f", plus `{b['channel']}` blacked out from {b['start_s']:g} s for {b['duration_s']:g} s in every run"
    fractions = ", ".join(f"`{n}` {100 * f:.1f} %" for n, f in zip(names, info.get("missing_fraction", [])))
    text += f" (dropout seed {info['seed']}; measured missing: {fractions}). See docs/missing_data.md."
    return [text, ""]


def in_report_units(study):
    """(study, units, scale): the study in its system's reporting units, if it has them.

    A system with ``report_scale`` / ``report_units`` (veh14dof: degrees, deg/s, km/h, g) is
    reported in those: RMSEs, per-run RMSEs, estimates and truth are multiplied by the scale (ratios
    are unit-free). Otherwise the study is returned unchanged with ``scale = None``.
    """
    s = study.system
    scale = getattr(s, "report_scale", None)
    if scale is None:
        return study, tuple(s.state_units), None
    k = torch.as_tensor(scale, dtype=torch.float64).cpu()
    results = {
        name: dataclasses.replace(
            r,
            rmse=(torch.tensor(r.rmse, dtype=torch.float64) * k).tolist(),
            per_run_rmse=(torch.tensor(r.per_run_rmse, dtype=torch.float64) * k).tolist(),
        )
        for name, r in study.results.items()
    }
    kf = k.float()
    estimates = {name: e * kf.to(e.device) for name, e in study.estimates.items()}
    data = study.data.clone().set("state", study.data["state"] * kf.to(study.data["state"].device))
    view = dataclasses.replace(study, results=results, estimates=estimates, data=data)
    return view, tuple(s.report_units), k


def _state_columns_table(study, units) -> list[str]:
    """The paper's Table II layout: one RMSE column per state, then cost; per-run spread below.

    The ratio-to-oracle column appears only if some filter has one (no oracle on model-free
    systems); without one a diverged run is one with an estimate non-finite or outside the plausible range.
    """
    s = study.system
    results = study.results
    has_ratio = any(r.ratio_to_oracle is not None for r in results.values())
    has_repairs = any(r.repairs for r in results.values())
    head = ["filter", *(f"RMSE {n} [{u}]" for n, u in zip(s.state_names, units))]
    head += [ratio_label(study)] if has_ratio else []
    head += ["cost per estimate [ms] (batch 1)", "throughput [estimates/s] (batch R)"]
    head += ["diverged runs"]
    head += ["covariance repairs"] if has_repairs else []
    head += [f"at a bound ({' / '.join(s.state_names)})"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        row = [name, *(f"{v:.4g}" for v in r.rmse)]
        row += [_fmt(r.ratio_to_oracle, 3)] if has_ratio else []
        row += [f"{r.cost_ms:.3f}" if r.cost_ms is not None else "–", f"{r.throughput_per_s:,.0f}", str(r.diverged)]
        row += [str(r.repairs)] if has_repairs else []
        row += [_saturated(r)]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        f"Per-run RMSE over the {study.runs} runs, median (25 %–75 %) [min–max]:",
        "",
        "| filter | " + " | ".join(f"{n} [{u}]" for n, u in zip(s.state_names, units)) + " |",
        "|---|" + "---|" * s.state_dim,
    ]
    for name, r in results.items():
        runs = torch.tensor(r.per_run_rmse, dtype=torch.float64)
        q = torch.quantile(runs, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=torch.float64), dim=0)
        cells = [
            f"{q[2, j]:.3g} ({q[1, j]:.3g}–{q[3, j]:.3g}) [{q[0, j]:.3g}–{q[4, j]:.3g}]" for j in range(s.state_dim)
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def write_report(study, out_dir: str | Path, *, title: str, profile: str, spec: ReportSpec | None = None) -> Path:
    """Write ``report.md``, ``results.csv``, ``results.json`` and figures into ``out_dir``.

    Numbers are in the system's reporting units where it has them (``in_report_units``); what the
    report holds beyond them is ``spec``.
    """
    spec = spec or ReportSpec()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    si_units = tuple(study.system.state_units)
    study, units, scale = in_report_units(study)
    layout = spec.layout
    paired = paired_comparison(study, layout.paired_with) if layout.paired_with else None
    info = {**environment_info(), **spec.meta}
    payload = {"profile": profile, **study.to_json(), **info}
    if scale is not None:
        payload.update(units=list(units), si_units=list(si_units), unit_scale=scale.tolist())
    if spec.window_study:
        payload["window_study"] = spec.window_study.rows
    if spec.training and spec.training.costs:
        payload["training"] = spec.training.costs
    if spec.requirements:
        payload["requirements"] = [dataclasses.asdict(r) for r in spec.requirements]
    if paired:
        payload["paired_with"] = {"reference": layout.paired_with, "filters": paired}
    spread = seed_spread(study, spec.seeds, paired, layout.paired_with) if spec.seeds else {}
    if spread:
        payload["seeds"] = spread
    atomic_write_text(out / "results.json", json.dumps(payload, indent=2))
    _write_csv(study, out / "results.csv", units if scale is not None else None)
    figs = _figures(study, out, spec, units, scale, paired)

    paper = PAPER_TABLES[layout.paper_table] if layout.paper_table else None
    lines = _header_lines(title, profile) + _system_lines(study)
    lines += ["## Results", "", *(_state_columns_table(study, units) if layout.per_state else _results_table(study))]
    lines += ["", *_reference_lines(study), *(_paired_lines(study, layout.paired_with, paired) if paired else [])]
    lines += _calibration_lines(study) + _seed_lines(spread, study)
    lines += _requirement_lines(spec.requirements) + _window_lines(spec.window_study, paper)
    lines += _training_lines(spec.training.costs if spec.training else {}) + _paper_lines(paper)
    if spec.notes:
        lines += ["## Notes", "", *[f"- {n}" for n in spec.notes], ""]
    lines += ["## Figures", ""] + [f"![{k}]({p.name})" for k, p in figs.items()] + [""]
    lines += _provenance_lines(info, spec.meta)
    atomic_write_text(out / "report.md", "\n".join(lines))
    return out / "report.md"


def _write_csv(study, path: Path, units) -> None:
    """One row per filter: RMSE per state (in ``units`` when given), ratio per state, cost, counts, calibration."""
    s = study.system
    names = s.state_names
    rmse = [f"rmse_{n}" for n in names] if units is None else [f"rmse_{n} [{u}]" for n, u in zip(names, units)]
    fh = io.StringIO()  # written whole, then renamed into place
    writer = csv.writer(fh)
    writer.writerow(
        ["filter"]
        + rmse
        + [f"ratio_{n}" for n in names]
        + ["cost_ms", "threads", "throughput_per_s", "diverged", "repairs"]
        + [f"saturated_{n}" for n in names]
        + [f"nees_{n}" for n in names]
        + [f"coverage_2sigma_{n}" for n in names]
    )
    for name, r in study.results.items():
        ratio = r.ratio_to_oracle or [None] * s.state_dim
        saturated = r.saturated or [None] * s.state_dim
        nees, cover = r.nees or [None] * s.state_dim, r.coverage_2sigma or [None] * s.state_dim
        writer.writerow(
            [name, *r.rmse, *ratio, r.cost_ms, r.threads, r.throughput_per_s, r.diverged, r.repairs, *saturated]
            + [*nees, *cover]
        )
    atomic_write_text(path, fh.getvalue())


def _figures(study, out: Path, spec: ReportSpec, units, scale, paired: dict | None = None) -> dict[str, Path]:
    """The report's figures (caption -> file): one run, per-run RMSE, learning curves, window study."""
    s = study.system
    if spec.layout.per_state:
        figs = {
            f"run 0: {n}": figures.plot_one_run_state(study, j, out / f"run0_{n}.png", units=units)
            for j, n in enumerate(s.state_names)
        }
    else:
        figs = {"one run": figures.plot_one_run(study, out / "run0_states_errors.png")}
    figs["per-run RMSE"] = figures.plot_per_run_boxes(study, out / "per_run_rmse_box.png", units=units)
    if any(r.nees is not None for r in study.results.values()):
        figs["calibration"] = figures.plot_calibration(study, out / "calibration.png")
    training = spec.training
    if training and training.curves:
        # reference lines on the validation set the curves are on (never the evaluation data's RMSEs)
        curves = training.curves
        refs = {f"{k} (validation set)": v for k, v in training.references.items()}
        if scale is not None:  # validation RMSEs are logged in SI units
            k = scale.tolist()
            curves = {
                name: [{**h, **{f"rmse_{n}": h[f"rmse_{n}"] * k[j] for j, n in enumerate(s.state_names)}} for h in hist]
                for name, hist in curves.items()
            }
            refs = {name: [v * k[j] for j, v in enumerate(values)] for name, values in refs.items()}
        figs["learning curves"] = figures.plot_learning_curves(
            curves, s.state_names, out / "learning_curves.png", refs, units=units
        )
    if spec.window_study:
        rows = spec.window_study.rows
        if paired and all(r.get("name") in paired for r in rows):  # the ratios with their intervals
            reference = spec.layout.paired_with
            rows = [{**r, **paired[r["name"]], "reference": reference} for r in rows]
        figs["window study"] = figures.plot_window_study(rows, s.state_names, out / "window_study.png", units)
    return figs


def _system_lines(study) -> list[str]:
    s = study.system
    return [
        f"System `{s.name}`, scenario `{s.scenario}`; {study.runs} runs × {study.steps} steps, evaluation seed "
        f"{study.seed} (disjoint from every training and validation seed). Every filter filters the same data "
        "and starts from the prior. Cost per estimate: median wall time per step of one trajectory streamed "
        f"through the filter's own loop after a warm-up, torch threads = {next(iter(study.results.values())).threads}.",
        "",
        *_dropout_lines(study),
    ]


def _requirement_lines(requirements: list[Requirement]) -> list[str]:
    if not requirements:
        return []
    lines = ["## Requirements", ""]
    for r in requirements:
        verdict = "**met**" if r.met else "**not met**"
        lines.append(f"- {r.requirement}: {verdict}. {r.detail}".rstrip())
    return lines + [""]


def _window_lines(window_study: WindowStudy | None, paper: PaperTable | None) -> list[str]:
    if not window_study:
        return []
    context = paper.windows if paper is not None else {}
    extra = f" {paper.windows_column} |" if context else ""
    lines = [
        f"## Sliding-window study ({window_study.filter})",
        "",
        "| N | RMSE | cost [ms] |" + extra,
        "|---|---|---|" + ("---|" if context else ""),
    ]
    for r in window_study.rows:
        row = f"| {r['window']} | {_fmt(r['rmse'])} | {r['cost_ms']:.3f} |"
        if context:
            row += f" {_fmt(context[r['window']], 3) if r['window'] in context else '–'} |"
        lines.append(row)
    return lines + [""]


def _training_lines(costs: dict[str, dict]) -> list[str]:
    if not costs:
        return []
    lines = [
        "## Training cost",
        "",
        "| filter | samples (env steps) | updates | wall [s] | threads |",
        "|---|---|---|---|---|",
    ]
    for name, t in costs.items():
        frames, updates = (f"{t[k]:,}" if k in t else "–" for k in ("frames", "updates"))
        lines.append(f"| {name} | {frames} | {updates} | {t.get('wall_s', '–')} | {t.get('threads', '–')} |")
    return lines + [""]


def _paper_lines(paper: PaperTable | None) -> list[str]:
    if paper is None:
        return []
    return [
        f"## The paper's Table {paper.number}, for context",
        "",
        paper.caveat,
        "",
        "| filter | " + " | ".join(paper.columns) + " |",
        "|---|" + "---|" * len(paper.columns),
        *["| " + " | ".join([k, *map(str, v)]) + " |" for k, v in paper.rows.items()],
        "",
    ]


def scenario_winners(study) -> dict:
    """Which filter wins one study: the lowest RMSE per state, and overall the lowest mean over states
    of RMSE / best RMSE (unit-free), with and without the reference filters (the PF-oracle, the study's
    reference, e.g. PF-joint on mismatch, and every candidate its check tried: too costly to be practical
    filters; a best filter taken as the reference because none converged stays practical).

    A filter with a non-finite RMSE on any state (it failed) wins nothing.
    """
    names = list(study.results)
    rmse = torch.tensor([study.results[n].rmse for n in names], dtype=torch.float64)
    rmse[~torch.isfinite(rmse).all(1)] = math.inf
    score = (rmse / rmse.min(0).values).mean(1)

    def best(values, allowed) -> str | None:
        finite = [i for i in allowed if math.isfinite(values[i])]
        return names[min(finite, key=lambda i: values[i])] if finite else None

    every = list(range(len(names)))
    # the reference candidates the study tried; the reference itself unless it is the best filter (no candidate
    # converged), which is a practical filter
    check = getattr(study, "reference_check", None) or {}
    references = {ORACLE, *(c["name"] for c in check.get("candidates", []))}
    if check.get("how") != "best":
        references.add(getattr(study, "reference", None))
    practical = [i for i in every if names[i] not in references]
    return {
        "per_state": {st: best(rmse[:, j].tolist(), every) for j, st in enumerate(study.system.state_names)},
        "overall": best(score.tolist(), every),
        "overall_without_oracle": best(score.tolist(), practical),
        "score": {n: (v if math.isfinite(v) else None) for n, v in zip(names, score.tolist())},
    }


def write_scenario_report(
    studies: dict,
    out_dir: str | Path,
    *,
    title: str,
    profile: str,
    reports: dict[str, Path] | None = None,
    notes: list[str] | None = None,
    meta: dict | None = None,
) -> Path:
    """One report of the same filters on several scenarios (scenario -> ``Study`` of one system).

    ``report.md`` holds a summary table (RMSE per state per filter per scenario, the best of each
    column in bold), which filter wins each scenario (``scenario_winners``), then every scenario's
    results table with a link to its own full report (``reports``: scenario -> report.md). The
    same numbers go to ``results.csv`` / ``results.json``, and a bar chart of RMSE per scenario.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    first = next(iter(studies.values()))
    s = first.system
    names = list(dict.fromkeys(n for st in studies.values() for n in st.results))
    winners = {sc: scenario_winners(st) for sc, st in studies.items()}
    info = {**environment_info(), **(meta or {})}
    links = {sc: os.path.relpath(p, out) for sc, p in (reports or {}).items()}

    payload = {
        "profile": profile,
        "system": s.name,
        "scenarios": list(studies),
        "runs": first.runs,
        "steps": first.steps,
        "seed": first.seed,
        "states": list(s.state_names),
        "units": list(s.state_units),
        "studies": {
            sc: {
                "reference": st.reference,
                "filters": {n: {k: getattr(r, k) for k in _SCENARIO_FIELDS} for n, r in st.results.items()},
            }
            for sc, st in studies.items()
        },
        "winners": winners,
        "reports": links,
        **info,
    }
    atomic_write_text(out / "results.json", json.dumps(payload, indent=2))
    fh = io.StringIO()  # written whole, then renamed into place
    writer = csv.writer(fh)
    writer.writerow(
        ["scenario", "filter", *(f"rmse_{n}" for n in s.state_names), *(f"ratio_{n}" for n in s.state_names)]
        + ["cost_ms", "diverged"]
    )
    for sc, st in studies.items():
        for n, r in st.results.items():
            ratio = r.ratio_to_oracle or [None] * s.state_dim
            writer.writerow([sc, n, *r.rmse, *ratio, r.cost_ms, r.diverged])
    atomic_write_text(out / "results.csv", fh.getvalue())
    rmse = {sc: {n: r.rmse for n, r in st.results.items()} for sc, st in studies.items()}
    figure = figures.plot_scenario_rmse(rmse, s.state_names, s.state_units, out / "rmse_by_scenario.png")

    lines = _header_lines(title, profile)
    lines += [
        f"System `{s.name}`, scenarios {', '.join(f'`{sc}`' for sc in studies)}; each {first.runs} runs × "
        f"{first.steps} steps from evaluation seed {first.seed}, every filter on the same data within a scenario.",
        "",
        "## Summary: RMSE per state and scenario",
        "",
        "The lowest RMSE of each column is in bold; – : the filter was not run on that scenario.",
        "",
    ]
    head = ["filter", *(f"{sc}: {n} [{u}]" for sc in studies for n, u in zip(s.state_names, s.state_units))]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in names:
        row = [name]
        for sc, st in studies.items():
            for j in range(s.state_dim):
                r = st.results.get(name)
                cell = f"{r.rmse[j]:.4g}" if r is not None else "–"
                row.append(
                    f"**{cell}**" if r is not None and winners[sc]["per_state"].get(s.state_names[j]) == name else cell
                )
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "## Which filter wins each scenario",
        "",
        "Lowest RMSE per state; overall: the lowest mean over states of RMSE / (best RMSE of that state), "
        "with and without the reference filters (the PF-oracle, and the study's reference where it is another "
        "filter, such as PF-joint on mismatch: too costly to be practical filters).",
        "",
        "| scenario | " + " | ".join(f"lowest RMSE {n}" for n in s.state_names) + " | overall | overall without "
        "the references |",
        "|---|" + "---|" * (s.state_dim + 2),
    ]
    for sc, w in winners.items():
        cells = [w["per_state"][n] or "–" for n in s.state_names]
        lines.append(
            f"| {sc} | " + " | ".join(cells) + f" | {w['overall'] or '–'} | {w['overall_without_oracle'] or '–'} |"
        )
    lines.append("")
    for sc, st in studies.items():
        link = f" ([full report]({links[sc]}))" if sc in links else ""
        lines += [f"## Scenario `{sc}`{link}", "", *_results_table(st), "", *_reference_lines(st)]
    if notes:
        lines += ["## Notes", "", *[f"- {n}" for n in notes], ""]
    lines += ["## Figures", "", f"![RMSE per scenario]({figure.name})", ""]
    lines += _provenance_lines(info, meta)
    atomic_write_text(out / "report.md", "\n".join(lines))
    return out / "report.md"


def _header_lines(title: str, profile: str) -> list[str]:
    """The report's title, and a banner on any profile smaller than the paper's."""
    lines = [f"# {title}", ""]
    if profile != "paper":
        lines += [
            f"> **Profile `{profile}`**: reduced runs and training budgets for a quick check; "
            "not the paper-size study.",
            "",
        ]
    return lines


def _provenance_lines(info: dict, meta: dict | None) -> list[str]:
    """The report's provenance section: commit, machine, versions and the run's own metadata."""
    return [
        "## Provenance",
        "",
        f"- commit: `{info['commit']}`",
        f"- machine: {info['machine']}",
        f"- versions: {', '.join(f'{k} {v}' for k, v in info['versions'].items())}",
        *[f"- {k}: {v}" for k, v in (meta or {}).items()],
        "",
    ]
