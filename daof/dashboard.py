"""wandb dashboards: what a training run and a report log besides their scalars.

A training run (``logger.backend=wandb``) is named after what it trains, grouped and tagged by its
experiment, and logs its full resolved config; at its end its learning curve (figure and
``wandb.Table``) and summary. A report (``python -m daof.experiments ... logger=wandb``) is a run of
its own in the same group: the results table as a ``wandb.Table``, every figure, and the report
directory as an artifact. Runs are offline unless ``logger.mode`` says otherwise (``wandb sync``
uploads them later).
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["log_report", "log_training_end", "training_identity"]


def training_identity(cfg) -> dict:
    """wandb's ``name``, ``group`` and ``tags`` of a training config (``logger.name/group/tags`` win)."""
    lc = cfg.logger
    name = lc.name or f"{cfg.kind} {cfg.system}/{cfg.scenario} N={cfg.window} seed={cfg.seed}"
    tags = list(dict.fromkeys([cfg.kind, cfg.system, cfg.scenario, f"N={cfg.window}", f"seed={cfg.seed}", *lc.tags]))
    return {"name": name, "group": lc.group, "tags": tags}


def log_training_end(logger, history: list[dict], state_names, figure: Path, summary: dict) -> None:
    """The learning curve as a table and a figure, the summary's numbers, then close the run."""
    import wandb

    run = logger.experiment
    columns = ["frames", *(f"rmse_{s}" for s in state_names)]
    rows = [[h.get(c) for c in columns] for h in history]
    payload = {"learning_curve": wandb.Table(columns=columns, data=rows)}
    if figure.is_file():
        payload["learning_curve_figure"] = wandb.Image(str(figure))
    run.log(payload)
    for key in ("frames", "updates", "wall_s"):
        run.summary[key] = summary[key]
    if summary.get("best"):
        run.summary["best_score"] = summary["best"].get("score")
        run.summary["best_frames"] = summary["best"].get("frames")
    run.finish()


def _results_table(results: dict):
    """One row per filter of a report's results.json: RMSE and ratio per state, cost, diverged runs."""
    import wandb

    states = results["states"]
    columns = ["filter", *(f"rmse_{s}" for s in states), *(f"ratio_{s}" for s in states), "cost_ms", "diverged"]
    rows = []
    for name, r in results["filters"].items():
        ratio = r.get("ratio_to_oracle") or [None] * len(states)
        rows.append([name, *r["rmse"], *ratio, r.get("cost_ms"), r.get("diverged")])
    return wandb.Table(columns=columns, data=rows)


def log_report(report_dir: Path, *, name: str, group: str, tags: list[str], project: str, mode: str) -> str:
    """Log report ``report_dir`` (results.json, figures, the directory as an artifact) as a wandb run.

    Returns the run's local directory."""
    import wandb

    report_dir = Path(report_dir)
    results = json.loads((report_dir / "results.json").read_text())
    run = wandb.init(
        project=project,
        mode=mode,
        dir=str(report_dir.parent),  # <report_dir>/../wandb/: the report directory holds the report only
        name=name,
        group=group,
        tags=tags,
        job_type="report",
        config={
            k: results[k] for k in ("profile", "system", "scenario", "runs", "steps", "seed", "commit") if k in results
        },
    )
    payload = {"results": _results_table(results)}
    payload.update({f"figures/{p.stem}": wandb.Image(str(p)) for p in sorted(report_dir.glob("*.png"))})
    run.log(payload)
    artifact = wandb.Artifact(name=f"report-{group}".replace("/", "-"), type="report")
    for path in sorted(report_dir.iterdir()):
        if path.is_file():
            artifact.add_file(str(path))
    run.log_artifact(artifact)
    where = run.dir
    run.finish()
    return where
