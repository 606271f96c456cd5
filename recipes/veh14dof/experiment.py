"""Experiment II end to end: train DAOF-v2 and SLF on veh14dof, run the Monte Carlo study, write the report.

    python recipes/veh14dof/experiment.py                 # quick profile
    python recipes/veh14dof/experiment.py profile=paper   # the paper-size study (R = 100, T = 500)

The trainings are the recipes of Experiment I (``recipes/veh2dof/train_daof.py``, ``train_slf.py``)
run with this directory's ``config.yaml`` / ``slf.yaml`` as subprocesses (finished ones are
reused, interrupted ones resumed). veh14dof is a data source only (no model for filters), so the
study holds the two model-free learned filters against each other; the report is the paper's
Table II layout in its units. Simulations are memoised in ``cache_dir`` (``envs/recorded.py``),
and the study caches every finished filter, so the same command continues after an interruption.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
from daof.envs import make_system
from daof.envs.recorded import RecordedSystem
from omegaconf import DictConfig

from daof.evaluate.experiment import (
    command_line,
    learning_curves,
    run_trained_study,
    select_profile,
    select_scenarios,
    train,
    training_costs,
    validation_references,
)
from daof.evaluate.jobs import TrainingJob
from daof.evaluate.report import write_report

HERE = Path(__file__).resolve().parent
TRAINERS = HERE.parent / "veh2dof"  # the recipe scripts are shared; this directory holds the configs


def _system_overrides(p: DictConfig) -> dict:
    return {str(k): v for k, v in (p.get("system_overrides") or {}).items()}


def training_jobs(cfg: DictConfig, p: DictConfig, root: Path) -> dict[str, TrainingJob]:
    """SLF and every DAOF-v2 row with the same window and network (configs' defaults + rows' + profile's overrides)."""
    n = int(cfg.window)
    common = [
        f"scenario={cfg.scenario}",
        f"seed={cfg.training_seed}",
        f"window={n}",
        f"overrides.replay.cache_dir={Path(cfg.cache_dir).resolve()}",
        *(f"++overrides.{k}={v}" for k, v in _system_overrides(p).items()),
    ]

    def config(name: str) -> list[str]:
        return ["--config-path", str(HERE), "--config-name", name]

    daof = [*config("config"), *common, "version=v2", f"overrides.replay.runs={p.bank_runs}"]
    jobs = {
        "SLF": TrainingJob(
            "SLF",
            TRAINERS / "train_slf.py",
            root / f"slf-N{n}",
            int(p.slf_frames),
            [*config("slf"), *common, *p.slf_overrides],
        )
    }
    for name, row in cfg.v2_rows.items():
        jobs[name] = TrainingJob(
            name,
            TRAINERS / "train_daof.py",
            root / f"{row.dir}-N{n}",
            int(p.daof_frames),
            [*daof, *row.overrides, *p.daof_overrides],
        )
    return jobs


def notes(cfg: DictConfig, p: DictConfig, filters: dict) -> list[str]:
    nets = "; ".join(
        f"{name}: {f.config.depth} × {f.config.num_cells} GELU, N = {f.config.window}" for name, f in filters.items()
    )
    out = [
        "veh14dof is a data source only (no model for filters), so EKF, UKF and the particle filters do not apply: "
        "there is no PF-oracle, hence no ratio column, and a diverged run is one with a non-finite estimate.",
        f"Same network size and input window for both learned filters ({nets}); inputs are normalised per channel "
        "with statistics of simulated training data stored in each checkpoint.",
        f"DAOF-v2 (DSAC-T) learned from a bank of {p.bank_runs} simulated episodes (seed {cfg.training_seed}) "
        "replayed to the env (envs/recorded.py; the trajectories do not depend on the estimates); SLF by regression "
        "on fresh simulated batches. Both are their best-validation checkpoints (validation seed 9100).",
        "RMSE in the paper's units (deg, deg/s, km/h, g): the SI errors times the system's report_scale.",
    ]
    out += [
        f"{name}: overrides of recipes/veh14dof/config.yaml {[*row.overrides, *p.daof_overrides] or 'none'}."
        for name, row in cfg.v2_rows.items()
    ]
    out.append(f"SLF: overrides of recipes/veh14dof/slf.yaml {list(p.slf_overrides) or 'none'}.")
    if _system_overrides(p):
        out.append(f"System overrides of this profile: {_system_overrides(p)} (not the spec's simulator settings).")
    return out


def study_and_report(cfg: DictConfig, p: DictConfig, jobs: dict[str, TrainingJob], start: float) -> Path:
    """Steps 2 and 3: the Monte Carlo study of the trained filters and the Table II report."""
    print("2/3 Monte Carlo study (model-free filters only)")
    system = RecordedSystem(make_system("veh14dof", cfg.scenario, **_system_overrides(p)), cache_dir=cfg.cache_dir)
    study, filters = run_trained_study(
        system,
        jobs,
        runs=int(p.runs),
        steps=int(p.steps),
        seed=int(cfg.seed),
        timing_threads=int(cfg.timing_threads),
        cache_dir=Path(cfg.output_root) / "study",
        expect={"system": "veh14dof", "window": int(cfg.window)},
    )

    print("3/3 report")
    wall = time.perf_counter() - start
    return write_report(
        study,
        Path(cfg.report_dir),
        title=f"Experiment II: veh14dof ({cfg.scenario}), model-free filtering",
        profile=cfg.profile,
        curves=learning_curves(filters),
        curve_references=validation_references(filters),
        training=training_costs(jobs),
        notes=notes(cfg, p, filters),
        meta={
            "wall_time_s": round(wall, 1),
            "command": command_line("recipes/veh14dof/experiment.py", f"profile={cfg.profile}"),
        },
        per_state=True,
    )


@hydra.main(config_path=".", config_name="experiment", version_base="1.3")
def main(cfg: DictConfig) -> None:
    p = select_profile(cfg)
    select_scenarios("veh14dof", cfg.scenario)
    start = time.perf_counter()
    print(f"Experiment II ({cfg.profile} profile, scenario {cfg.scenario}) -> {cfg.output_root}")
    print("1/3 training the learned filters")
    jobs = training_jobs(cfg, p, Path(cfg.output_root))
    train(list(jobs.values()), parallel=int(cfg.parallel_jobs))
    report = study_and_report(cfg, p, jobs, start)
    print(f"report: {report}  ({(time.perf_counter() - start) / 60:.1f} min)")


if __name__ == "__main__":
    main()
