"""Write a study's report directory: report.md, results.csv, results.json and the figures."""

from __future__ import annotations

import csv
import json
import platform
import subprocess
from pathlib import Path

import torch

from daof.evaluate import figures

__all__ = ["environment_info", "write_report", "PAPER_TABLE_I"]

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
    import os

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


def _results_table(study) -> list[str]:
    s = study.system
    states = " / ".join(f"{n} [{u}]" for n, u in zip(s.state_names, s.state_units))
    lines = [
        f"| filter | RMSE {states} | ratio to PF-oracle | per-run RMSE median (IQR) | cost per estimate [ms] "
        "(batch 1) | throughput [estimates/s] (batch R) | diverged runs | covariance repairs |",
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


def write_report(
    study,
    out_dir: str | Path,
    *,
    title: str,
    profile: str,
    curves: dict[str, list[dict]] | None = None,
    window_rows: list[dict] | None = None,
    training: dict[str, dict] | None = None,
    notes: list[str] | None = None,
    meta: dict | None = None,
) -> Path:
    """Write ``report.md``, ``results.csv``, ``results.json`` and figures into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = study.system
    info = {**environment_info(), **(meta or {})}
    payload = {"profile": profile, **study.to_json(), **info}
    if window_rows:
        payload["window_study"] = window_rows
    if training:
        payload["training"] = training
    (out / "results.json").write_text(json.dumps(payload, indent=2))
    with (out / "results.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(
            ["filter"]
            + [f"rmse_{n}" for n in s.state_names]
            + [f"ratio_{n}" for n in s.state_names]
            + ["cost_ms", "threads", "throughput_per_s", "diverged", "repairs"]
        )
        for name, r in study.results.items():
            ratio = r.ratio_to_oracle or [None] * s.state_dim
            writer.writerow([name, *r.rmse, *ratio, r.cost_ms, r.threads, r.throughput_per_s, r.diverged, r.repairs])

    figs = {
        "one run": figures.plot_one_run(study, out / "run0_states_errors.png"),
        "per-run RMSE": figures.plot_per_run_boxes(study, out / "per_run_rmse_box.png"),
    }
    if curves:
        refs = {k: study.results[k].rmse for k in ("UKF", "PF-oracle") if k in study.results}
        figs["learning curves"] = figures.plot_learning_curves(curves, s.state_names, out / "learning_curves.png", refs)
    if window_rows:
        figs["window study"] = figures.plot_window_study(window_rows, s.state_names, out / "window_study.png")

    lines = [f"# {title}", ""]
    if profile != "paper":
        lines += [
            f"> **Profile `{profile}`**: reduced runs and training budgets for a quick check; "
            "not the paper-size study.",
            "",
        ]
    lines += [
        f"System `{s.name}`, scenario `{s.scenario}`; {study.runs} runs × {study.steps} steps, evaluation seed "
        f"{study.seed} (disjoint from every training and validation seed). Every filter filters the same data "
        "and starts from the prior. Cost per estimate: median wall time per step of one trajectory streamed "
        f"through the filter's own loop after a warm-up, torch threads = {next(iter(study.results.values())).threads}.",
        "",
        "## Results",
        "",
        *_results_table(study),
        "",
    ]
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
    if notes:
        lines += ["## Notes", "", *[f"- {n}" for n in notes], ""]
    lines += ["## Figures", ""] + [f"![{k}]({p.name})" for k, p in figs.items()] + [""]
    lines += [
        "## Provenance",
        "",
        f"- commit: `{info['commit']}`",
        f"- machine: {info['machine']}",
        f"- versions: {', '.join(f'{k} {v}' for k, v in info['versions'].items())}",
        *[f"- {k}: {v}" for k, v in (meta or {}).items()],
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
    return out / "report.md"
