"""Write a study's report directory: report.md, results.csv, results.json and the figures."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import platform
import subprocess
from pathlib import Path

import torch

from daof.evaluate import figures
from daof.evaluate.metrics import paired_rmse_ratio
from daof.evaluate.study import ORACLE

__all__ = [
    "environment_info",
    "in_report_units",
    "ratio_label",
    "scenario_winners",
    "write_report",
    "write_scenario_report",
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


def _reference_lines(study) -> list[str]:
    """One sentence under the results table on what the ratios and the diverged count compare with."""
    ref = getattr(study, "reference", None)
    if ref is None:
        return []
    if ref == ORACLE and study.system.scenario != "nominal":
        return [
            f"Scenario `{study.system.scenario}`: the PF-oracle is the near-optimal reference only on `nominal`. "
            "Here it filters with the nominal model like every model-based filter, so the ratios are relative "
            "to the nominal-model PF-oracle (a ratio below 1 is possible), not to the optimum; a diverged run "
            "has a non-finite estimate or an RMSE above 10x its pooled RMSE.",
            "",
        ]
    return [
        f"Ratios are per state, relative to {ref}; a diverged run has a non-finite estimate or an RMSE above 10x "
        f"{ref}'s pooled RMSE.",
        "",
    ]


def _results_table(study) -> list[str]:
    s = study.system
    states = " / ".join(f"{n} [{u}]" for n, u in zip(s.state_names, s.state_units))
    lines = [
        f"| filter | RMSE {states} | {ratio_label(study)} ({' / '.join(s.state_names)}) "
        "| per-run RMSE median (IQR) | cost per estimate [ms] (batch 1) | throughput [estimates/s] (batch R) "
        "| diverged runs | covariance repairs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in study.results.items():
        runs = torch.tensor(r.per_run_rmse)
        q = torch.quantile(runs, torch.tensor([0.25, 0.5, 0.75]), dim=0)
        spread = " / ".join(f"{q[1, j]:.3g} ({q[0, j]:.3g}–{q[2, j]:.3g})" for j in range(runs.shape[1]))
        cost = f"{r.cost_ms:.3f}" if r.cost_ms is not None else "–"
        lines.append(
            f"| {name} | {_fmt(r.rmse)} | {_fmt(r.ratio_to_oracle, 3)} | {spread} | {cost} | "
            f"{r.throughput_per_s:,.0f} | {r.diverged} | {r.repairs} |"
        )
    return lines


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
    systems); without an oracle a diverged run is a non-finite one.
    """
    s = study.system
    results = study.results
    has_ratio = any(r.ratio_to_oracle is not None for r in results.values())
    has_repairs = any(r.repairs for r in results.values())
    head = ["filter", *(f"RMSE {n} [{u}]" for n, u in zip(s.state_names, units))]
    head += [ratio_label(study)] if has_ratio else []
    head += ["cost per estimate [ms] (batch 1)", "throughput [estimates/s] (batch R)"]
    head += ["diverged runs" if has_ratio else "diverged runs (non-finite)"]
    head += ["covariance repairs"] if has_repairs else []
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        row = [name, *(f"{v:.4g}" for v in r.rmse)]
        row += [_fmt(r.ratio_to_oracle, 3)] if has_ratio else []
        row += [f"{r.cost_ms:.3f}" if r.cost_ms is not None else "–", f"{r.throughput_per_s:,.0f}", str(r.diverged)]
        row += [str(r.repairs)] if has_repairs else []
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


def write_report(
    study,
    out_dir: str | Path,
    *,
    title: str,
    profile: str,
    curves: dict[str, list[dict]] | None = None,
    curve_references: dict[str, list[float]] | None = None,
    window_rows: list[dict] | None = None,
    training: dict[str, dict] | None = None,
    notes: list[str] | None = None,
    meta: dict | None = None,
    per_state: bool = False,
    requirements: list[dict] | None = None,
    paired_with: str | None = None,
) -> Path:
    """Write ``report.md``, ``results.csv``, ``results.json`` and figures into ``out_dir``.

    Numbers are in the system's reporting units where it has them (``in_report_units``).
    ``per_state``: the paper's Table II layout (one column per state, a per-run spread table) and
    one state/error figure per state instead of one figure of all states.
    ``requirements``: ``{"requirement": text, "met": bool, "detail": text}`` each, stated as met or
    not met in a section of their own (and in results.json); the caller decides them from the numbers.
    ``paired_with``: a filter of the study every other one is compared with run by run (``paired_comparison``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = study.system
    study, units, scale = in_report_units(study)
    info = {**environment_info(), **(meta or {})}
    payload = {"profile": profile, **study.to_json(), **info}
    if scale is not None:
        payload.update(units=list(units), si_units=list(s.state_units), unit_scale=scale.tolist())
    if window_rows:
        payload["window_study"] = window_rows
    if training:
        payload["training"] = training
    if requirements:
        payload["requirements"] = requirements
    paired = paired_comparison(study, paired_with) if paired_with else None
    if paired:
        payload["paired_with"] = {"reference": paired_with, "filters": paired}
    (out / "results.json").write_text(json.dumps(payload, indent=2))
    with (out / "results.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(
            ["filter"]
            + [f"rmse_{n}" if scale is None else f"rmse_{n} [{u}]" for n, u in zip(s.state_names, units)]
            + [f"ratio_{n}" for n in s.state_names]
            + ["cost_ms", "threads", "throughput_per_s", "diverged", "repairs"]
        )
        for name, r in study.results.items():
            ratio = r.ratio_to_oracle or [None] * s.state_dim
            writer.writerow([name, *r.rmse, *ratio, r.cost_ms, r.threads, r.throughput_per_s, r.diverged, r.repairs])

    if per_state:
        figs = {
            f"run 0: {n}": figures.plot_one_run_state(study, j, out / f"run0_{n}.png", units=units)
            for j, n in enumerate(s.state_names)
        }
    else:
        figs = {"one run": figures.plot_one_run(study, out / "run0_states_errors.png")}
    figs["per-run RMSE"] = figures.plot_per_run_boxes(study, out / "per_run_rmse_box.png", units=units)
    if curves:
        # reference lines on the validation set the curves are on (never the evaluation data's RMSEs)
        refs = {f"{k} (validation set)": v for k, v in (curve_references or {}).items()}
        if scale is not None:  # validation RMSEs are logged in SI units
            k = scale.tolist()
            curves = {
                name: [{**h, **{f"rmse_{n}": h[f"rmse_{n}"] * k[j] for j, n in enumerate(s.state_names)}} for h in hist]
                for name, hist in curves.items()
            }
            refs = {name: [v * k[j] for j, v in enumerate(values)] for name, values in refs.items()}
        figs["learning curves"] = figures.plot_learning_curves(
            curves, s.state_names, out / "learning_curves.png", refs, units=units if scale is not None else None
        )
    if window_rows:
        figs["window study"] = figures.plot_window_study(window_rows, s.state_names, out / "window_study.png")

    lines = _header_lines(title, profile)
    lines += [
        f"System `{s.name}`, scenario `{s.scenario}`; {study.runs} runs × {study.steps} steps, evaluation seed "
        f"{study.seed} (disjoint from every training and validation seed). Every filter filters the same data "
        "and starts from the prior. Cost per estimate: median wall time per step of one trajectory streamed "
        f"through the filter's own loop after a warm-up, torch threads = {next(iter(study.results.values())).threads}.",
        "",
        *_dropout_lines(study),
        "## Results",
        "",
        *(_state_columns_table(study, units) if per_state else _results_table(study)),
        "",
        *_reference_lines(study),
        *(_paired_lines(study, paired_with, paired) if paired else []),
    ]
    if requirements:
        lines += ["## Requirements", ""]
        for r in requirements:
            verdict = "**met**" if r["met"] else "**not met**"
            lines.append(f"- {r['requirement']}: {verdict}. {r.get('detail', '')}".rstrip())
        lines.append("")
    if window_rows:
        lines += [
            "## Sliding-window study (DAOF-v1)",
            "",
            "| N | RMSE | cost [ms] | paper RMSE β / r (for context) |",
            "|---|---|---|---|",
        ]
        for r in window_rows:
            paper = PAPER_WINDOWS.get(r["window"])
            lines.append(
                f"| {r['window']} | {_fmt(r['rmse'])} | {r['cost_ms']:.3f} | {_fmt(paper, 3) if paper else '–'} |"
            )
        lines.append("")
    if training:
        lines += [
            "## Training cost",
            "",
            "| filter | samples (env steps) | updates | wall [s] | threads |",
            "|---|---|---|---|---|",
        ]
        for name, t in training.items():
            frames, updates = (f"{t[k]:,}" if k in t else "–" for k in ("frames", "updates"))
            lines.append(f"| {name} | {frames} | {updates} | {t.get('wall_s', '–')} | {t.get('threads', '–')} |")
        lines.append("")
    if s.name == "veh2dof":
        lines += [
            "## The paper's Table I, for context",
            "",
            "The paper does not publish its system parameters; its absolute numbers are not comparable with ours, "
            "only the ordering and ratios between filters are.",
            "",
            "| filter | RMSE β [rad] | RMSE r [rad/s] | cost [ms] |",
            "|---|---|---|---|",
            *[f"| {k} | {v[0]} | {v[1]} | {v[2]} |" for k, v in PAPER_TABLE_I.items()],
            "",
        ]
    elif s.name == "veh14dof":
        lines += [
            "## The paper's Table II, for context",
            "",
            "The paper does not publish its vehicle parameters, manoeuvre or sensor set-up; its absolute numbers are "
            "not comparable with ours, only the ordering and ratios between filters are.",
            "",
            "| filter | RMSE pitch [deg] | roll [deg] | yaw rate [deg/s] | side slip [deg] | Vx [km/h] | ax [g] "
            "| cost [ms] |",
            "|---|---|---|---|---|---|---|---|",
            *["| " + " | ".join([k, *map(str, v)]) + " |" for k, v in PAPER_TABLE_II.items()],
            "",
        ]
    if notes:
        lines += ["## Notes", "", *[f"- {n}" for n in notes], ""]
    lines += ["## Figures", ""] + [f"![{k}]({p.name})" for k, p in figs.items()] + [""]
    lines += _provenance_lines(info, meta)
    (out / "report.md").write_text("\n".join(lines))
    return out / "report.md"


def scenario_winners(study) -> dict:
    """Which filter wins one study: the lowest RMSE per state, and overall the lowest mean over states
    of RMSE / best RMSE (unit-free), with and without the reference filters (the PF-oracle and the study's
    reference, e.g. PF-joint on mismatch: too costly to be practical filters).

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
    references = {ORACLE, getattr(study, "reference", None)}
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
                "filters": {
                    n: {k: getattr(r, k) for k in ("rmse", "ratio_to_oracle", "cost_ms", "diverged", "repairs")}
                    for n, r in st.results.items()
                },
            }
            for sc, st in studies.items()
        },
        "winners": winners,
        "reports": links,
        **info,
    }
    (out / "results.json").write_text(json.dumps(payload, indent=2))
    with (out / "results.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(
            ["scenario", "filter", *(f"rmse_{n}" for n in s.state_names), *(f"ratio_{n}" for n in s.state_names)]
            + ["cost_ms", "diverged"]
        )
        for sc, st in studies.items():
            for n, r in st.results.items():
                ratio = r.ratio_to_oracle or [None] * s.state_dim
                writer.writerow([sc, n, *r.rmse, *ratio, r.cost_ms, r.diverged])
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
    (out / "report.md").write_text("\n".join(lines))
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
