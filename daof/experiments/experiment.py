"""One experiment entry for every system: train the learned filters, run the Monte Carlo study, write the report.

    python -m daof.experiments experiment=veh2dof                  # Experiment I, quick profile
    python -m daof.experiments experiment=linear profile=paper     # the optimality check against the KF
    python -m daof.experiments experiment=veh14dof profile=tiny    # Experiment II, a smoke test
    python -m daof.experiments experiment=veh2dof 'scenarios=[nominal,mismatch,outliers]'   # side by side

The experiment is a config (``daof/conf/experiment/<name>.yaml`` over ``daof.experiments.config``);
``recipes/<system>/experiment.py`` is the same entry with its experiment fixed. Everything is
checked first (the config, every scenario, every training's config and classical filter): a bad
input ends the run with one line (``SystemExit``) before anything trains. Then:

1. the learned rows train as subprocesses of ``python -m daof.train`` (finished ones are reused,
   interrupted ones resumed);
2. per scenario, every trained filter's uncertainty head (fitted once per checkpoint, profile key
   ``uncertainty_runs``), the study of the classical filters and every trained filter (cached per
   filter, so the same command continues after an interruption), and optionally the same study
   with sensor dropout;
3. per scenario a report in ``<output_root>/report`` and, with several scenarios, a combined one.

Model-based filters keep the system's nominal model in every scenario: a scenario changes how the
data is simulated, not ``f`` and ``g``. Data-driven parts train on the scenario's own data.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from daof.dashboard import log_report
from daof.device import resolve_device
from daof.evaluate import Dropout
from daof.evaluate.metrics import pooled_rmse
from daof.evaluate.report import (
    Layout,
    ReportSpec,
    Requirement,
    SeedSpread,
    Training,
    WindowStudy,
    write_report,
    write_scenario_report,
)
from daof.experiments.config import (
    PARTICLE_FILTERS,
    ExperimentConfig,
    Profile,
    check_experiment,
    compose_experiment,
    for_scenario,
)
from daof.experiments.jobs import HeadJob, TrainingJob
from daof.experiments.reference import ReferenceChoice, choose_reference
from daof.experiments.runner import (
    command_line,
    learning_curves,
    run_trained_study,
    train,
    training_costs,
    validation_references,
)
from daof.io import writable_directory
from daof.train.uncertainty import HeadSettings

__all__ = ["Plan", "ScenarioPlan", "main", "plan_experiment", "run_experiment"]

DROPOUT_NOTE = (
    "The same evaluation data as the main report, with measurement entries set missing (NaN). "
    "Kalman-type filters skip the update of a missing channel, the PFs weight on the present ones, "
    "DAOF-v1 reads a missing channel as its predicted measurement and DAOF-v2 and the SLF hold its "
    "last value (docs/missing_data.md)."
)


@dataclass
class ScenarioPlan:
    """One scenario's config (paths resolved for it) and its training jobs."""

    cfg: ExperimentConfig
    profile: Profile
    jobs: dict[str, TrainingJob]  # report row -> its training
    windows: dict[str, int]  # report row -> N

    @property
    def scenario(self) -> str:
        return self.cfg.scenario


@dataclass
class Plan:
    """A checked experiment: every scenario's plan and how to write the command that reproduces it."""

    cfg: ExperimentConfig  # the first scenario's
    scenarios: dict[str, ScenarioPlan]
    program: str  # what follows ``python``: a recipe script, or ``-m daof.experiments experiment=NAME``
    given: list[str]  # the command line's overrides

    def command(self, *pinned: str, drop=()) -> str:
        return command_line(self.program, *pinned, given=self.given, drop=drop)


# ----------------------------------------------------------------------------------------- planning
def seed_row(row: str, seed: int, seeds) -> str:
    """The report row of ``row`` trained on ``seed``: the row itself with one seed, else "<row> (seed <s>)"."""
    return row if len(seeds) == 1 else f"{row} (seed {seed})"


def training_jobs(cfg: ExperimentConfig, p: Profile, label: str = "") -> tuple[dict[str, TrainingJob], dict[str, int]]:
    """Every learned row at the experiment's window on every training seed (``seed_row``), and the window
    study's row at each of the profile's other windows (``"<row> (N=<n>)"``, largest first; first seed
    only); ``label`` is appended to the job names in the log."""
    root = Path(cfg.output_root)
    seeds = list(cfg.training_seeds)
    common = [f"system={cfg.system}", f"scenario={cfg.scenario}"]
    common += [f"device={cfg.device}"] if cfg.device != "cpu" else []  # the CPU default: the commands as before
    extra = [*cfg.training_overrides, *(f"overrides.{k}={v}" for k, v in p.system.items())]
    if cfg.logger:  # logger keys never make a finished run stale (daof.train.base.RESUMABLE_CHANGES)
        extra += [f"logger.backend={cfg.logger}", f"logger.group={_group(cfg)}", f"logger.tags=[{cfg.profile}]"]
    rows = []
    for name in cfg.learned:
        rows += [(seed_row(name, s, seeds), name, cfg.window, s) for s in seeds]
        if name == cfg.window_study:
            others = sorted(p.windows, reverse=True)
            rows += [(f"{name} (N={n})", name, n, seeds[0]) for n in others if n != cfg.window]
    from daof.envs.registry import import_root

    root_of_system = import_root(cfg.system)  # a system of the user's code: where the trainings import it from
    pythonpath = [str(root_of_system)] if root_of_system is not None else []
    jobs, windows = {}, {}
    for name, row_name, n, seed in rows:
        row = cfg.learned[row_name]
        overrides = [f"filter={row.filter}", *common, f"seed={seed}", f"window={n}", *extra, *row.overrides]
        overrides += [*p.overrides.get(row_name, []), *([cfg.sweep_override] if cfg.sweep_override else [])]
        out = root / f"{row.dir or row.filter.replace('_', '-')}-N{n}-s{seed}"
        jobs[name] = TrainingJob(name + label, out, int(p.frames[row_name]), overrides, pythonpath=pythonpath)
        windows[name] = n
    return jobs, windows


def _group(cfg: ExperimentConfig) -> str:
    """The wandb group of an experiment's runs: its system and profile."""
    return f"{cfg.system}-{cfg.profile}"


def study_system(cfg: ExperimentConfig, p: Profile):
    """The scenario's system with the profile's parameters; its simulations memoised in ``cache_dir`` if set."""
    from daof.envs import make_system
    from daof.envs.recorded import RecordedSystem

    system = make_system(cfg.system, cfg.scenario, **p.system)
    return RecordedSystem(system, cache_dir=cfg.cache_dir) if cfg.cache_dir else system


def classical_filters(cfg: ExperimentConfig, p: Profile, system, fallback: bool = False) -> dict:
    """The classical filters that run on this scenario (name -> filter), in config order: the study's rows,
    or with ``fallback`` the reference candidates that run only when those before them fail their check."""
    import daof.filters as filters

    out = {}
    for name, spec in cfg.classical.items():
        if (spec.scenarios is not None and cfg.scenario not in spec.scenarios) or spec.fallback != fallback:
            continue
        cls = getattr(filters, spec.filter)
        try:
            particle = spec.filter in PARTICLE_FILTERS
            out[name] = cls(system, int(p.particles[name]), seed=spec.seed) if particle else cls(system)
        except (TypeError, ValueError) as error:
            raise ValueError(f"classical.{name}: {str(error).splitlines()[0]}") from None
    return out


def reference_of(cfg: ExperimentConfig, names) -> str | None:
    """The first of ``cfg.reference`` that runs on this scenario, before any check (``choose_scenario_reference``)."""
    return next((r for r in cfg.reference if r in names), None)


def plan_experiment(name: str, overrides: list[str], program: str | None = None) -> Plan:
    """Compose and check experiment ``name`` with ``overrides``, and build its training jobs: no work yet.

    Every problem is one ``ValueError`` line.
    """
    raw = compose_experiment(name, overrides)
    first = for_scenario(raw, raw.scenario)
    p = check_experiment(first)
    per = {s: for_scenario(raw, s) for s in first.scenarios}
    roots = [Path(c.output_root).resolve() for c in per.values()]
    if len(set(roots)) != len(roots):
        raise ValueError(
            f"scenarios {list(per)} would share the output directory {roots[0]}: with several scenarios set root=DIR "
            "(one subdirectory per scenario), not output_root"
        )
    scenarios = {}
    for s, c in per.items():
        label = f" [{s}]" if len(per) > 1 else ""
        jobs, windows = training_jobs(c, c.profiles[c.profile], label)
        for job in jobs.values():  # the training configs, composed (and pinned) before anything runs
            try:
                _ = job.requested_config
            except RuntimeError as error:
                raise ValueError(str(error)) from None
        if c.classical:  # each one builds on this scenario's system
            classical_filters(c, p, study_system(c, p))
            classical_filters(c, p, study_system(c, p), fallback=True)
        scenarios[s] = ScenarioPlan(c, c.profiles[c.profile], jobs, windows)
        _notes(scenarios[s], {})  # every note's fields exist
    _format(first.combined_notes, _fields(scenarios[first.scenarios[0]], {}))
    program = program or f"-m daof.experiments experiment={name}"
    return Plan(first, scenarios, program, list(overrides))


# ----------------------------------------------------------------------------------------- notes
def _networks(filters: dict) -> str:
    def describe(f) -> str:  # a filter without a window says what it is (KalmanNet)
        c = f.config
        return getattr(f, "architecture", None) or f"{c.depth} × {c.num_cells} GELU, N = {c.window}"

    return "; ".join(f"{name}: {describe(f)}" for name, f in filters.items())


def _fields(sp: ScenarioPlan, learned: dict) -> dict:
    """What a note's ``{placeholders}`` can name (``daof.experiments.config.NOTE_FIELDS``)."""
    cfg, p = sp.cfg, sp.profile
    return {
        "system": cfg.system,
        "scenario": cfg.scenario,
        "profile": cfg.profile,
        "seed": cfg.seed,
        "training_seeds": list(cfg.training_seeds),
        "window": cfg.window,
        "runs": p.runs,
        "steps": p.steps,
        "frames": dict(p.frames),
        "particles": dict(p.particles),
        "windows": list(p.windows),
        "overrides": {
            name: [*cfg.learned[name].overrides, *p.overrides.get(name, [])] or "none" for name in cfg.learned
        },
        "train": {name: OmegaConf.create(job.requested_config) for name, job in sp.jobs.items()},
        "networks": _networks(learned),
    }


def _format(notes, fields: dict) -> list[str]:
    try:
        return [note.format(**fields) for note in notes]
    except (AttributeError, IndexError, KeyError, ValueError) as error:
        raise ValueError(f"a note names a field that does not exist: {error!r}") from None


def _notes(sp: ScenarioPlan, learned: dict, choice: ReferenceChoice | None = None, study=None) -> list[str]:
    """The report's notes: the reference and its check, the config's notes and the scenario's, the ratios after
    the start-up of every requirement with a settled step, and the profile's system parameters."""
    cfg, p = sp.cfg, sp.profile
    fields = _fields(sp, learned)
    out = (choice.lines() if choice is not None else []) + _format(
        [*cfg.notes, *cfg.scenario_notes.get(cfg.scenario, [])], fields
    )
    if study is not None and study.reference is not None:
        for step in dict.fromkeys(r.settled_step for r in cfg.requirements.values() if r.settled_step is not None):
            if study.steps > step:
                rows = ", ".join(
                    f"{name} " + " / ".join(f"{r:.3f}" for r in _ratios(study, name, step))
                    for name in study.results
                    if name != study.reference
                )
                out.append(
                    f"Ratio to {study.reference} per state over the steps after the first {step} "
                    f"(the start-up excluded): {rows}."
                )
    if p.system:
        out.append(f"System parameters of this profile: {dict(p.system)} (not the system's defaults).")
    return out


# ----------------------------------------------------------------------------------------- checks on the numbers
def _ratios(study, name: str, start: int = 0) -> list[float]:
    """RMSE of ``name`` / the reference's per state, over the steps from index ``start`` on."""
    truth = study.data["state"][:, start:]
    mine = pooled_rmse(study.estimates[name][:, start:], truth)
    ref = pooled_rmse(study.estimates[study.reference][:, start:], truth)
    return (mine / ref).tolist()


def requirements(cfg: ExperimentConfig, study) -> list[Requirement]:
    """Each ``requirements`` entry, met or not from the study's numbers."""
    out = []
    ref, names = study.reference, study.system.state_names
    seeds = list(cfg.training_seeds)
    rows = {}  # a learned row's requirement holds for each of its seeds
    for r, req in cfg.requirements.items():
        rows.update({seed_row(r, s, seeds): req for s in seeds} if r in cfg.learned else {r: req})
    for name, req in rows.items():
        text = f"{name} RMSE ≤ {req.tolerance:g}× {ref} per state"
        ratio = study.results[name].ratio_to_oracle if name in study.results else None
        if ratio is None:
            out.append(Requirement(text, False, f"{name} or the reference did not run on this scenario."))
            continue
        detail = f"{name} / {ref} over all steps: " + ", ".join(f"{n} {r:.3f}" for n, r in zip(names, ratio))
        if req.settled_step is not None and study.steps > req.settled_step:
            after = _ratios(study, name, req.settled_step)
            detail += f"; after the first {req.settled_step} steps: " + ", ".join(
                f"{n} {r:.3f}" for n, r in zip(names, after)
            )
        out.append(Requirement(text, all(r <= req.tolerance for r in ratio), detail + "."))
    return out


def choose_scenario_reference(sp: ScenarioPlan, study, classical: dict, fallbacks: dict) -> ReferenceChoice:
    """Check the scenario's reference candidates on the study (``daof.experiments.reference``) and make the
    chosen one its reference; a fallback that ran joins ``classical`` (so the dropout study has it too)."""
    cfg = sp.cfg
    candidates = {**classical, **fallbacks}
    choice = choose_reference(
        study,
        list(cfg.reference),
        {name: candidates[name] for name in cfg.reference if name in candidates},
        {name for name in cfg.reference if name in cfg.classical and cfg.classical[name].exact},
        limit_percent=float(cfg.convergence_check.limit_percent),
        seed=int(cfg.convergence_check.seed),
        cache_dir=Path(cfg.output_root) / "study",
        timing_threads=int(cfg.timing_threads),
    )
    classical.update({name: f for name, f in fallbacks.items() if name in study.results})
    for line in choice.lines():
        print(line)
    return choice


# ----------------------------------------------------------------------------------------- running
def fit_heads(jobs: dict, settings: HeadSettings, cfg) -> None:
    """Every trained filter's uncertainty head (a ``HeadJob`` each, in parallel like the trainings):
    fitted once per checkpoint."""
    print(f"   uncertainty heads ({settings.runs} runs × {settings.steps} steps; kept if fitted to this best.pt)")
    trainings = {job.output_dir: job for job in jobs.values()}.values()
    train([HeadJob(job, settings) for job in trainings], parallel=cfg.parallel_jobs, address=cfg.ray.address)


def run_scenario(plan: Plan, sp: ScenarioPlan, start: float):
    """Steps 2 and 3 for one scenario: the study (and its dropout twin) and the report -> (study, report.md)."""
    cfg, p, scenario = sp.cfg, sp.profile, sp.scenario
    title = cfg.title.format(scenario=scenario)
    if int(p.uncertainty_runs) > 0:
        fit_heads(sp.jobs, HeadSettings(runs=int(p.uncertainty_runs), steps=int(p.steps)), cfg)
    print(f"2/3 Monte Carlo study ({scenario})")
    system = study_system(cfg, p)
    classical = classical_filters(cfg, p, system)
    studied = dict(
        classical=classical,
        runs=int(p.runs),
        steps=int(p.steps),
        seed=int(cfg.seed),
        timing_threads=int(cfg.timing_threads),
        device=resolve_device(cfg.device),
        cache_dir=Path(cfg.output_root) / "study",
        reference=reference_of(cfg, [*classical, *sp.jobs]),
        expect=lambda name: {"system": cfg.system, "scenario": scenario, "window": sp.windows[name]},
    )
    study, filters = run_trained_study(system, sp.jobs, **studied)
    choice = choose_scenario_reference(sp, study, classical, classical_filters(cfg, p, system, fallback=True))
    pinned = (f"profile={cfg.profile}", f"scenario={scenario}")
    if cfg.dropout.enabled:
        d = cfg.dropout
        dropout = Dropout(float(d.p), tuple(d.blackout) if d.blackout else None, int(d.seed))
        print(f"2/3 the same study with sensor dropout ({scenario})")
        gappy, _ = run_trained_study(system, sp.jobs, **{**studied, "reference": choice.name}, dropout=dropout)
        gappy.reference_check = {**study.reference_check, "on": "the complete data of the main study"}
        spec = ReportSpec(
            layout=Layout(per_state=cfg.report.per_state),
            notes=[DROPOUT_NOTE],
            meta={"command": plan.command(*pinned, "dropout.enabled=true", drop=["scenarios"])},
        )
        out = Path(cfg.report_dir) / "dropout"
        write_report(gappy, out, title=f"{title} with sensor dropout", profile=cfg.profile, spec=spec)

    print(f"3/3 report ({scenario})")
    learned = {name: filters[name] for name in sp.jobs}
    seeds = list(cfg.training_seeds)
    rows = [seed_row(r, s, seeds) for r in cfg.learned for s in seeds]  # learning curves: every row and seed
    study_rows = None
    if cfg.window_study and p.windows:
        row = cfg.window_study
        first = seed_row(row, cfg.training_seeds[0], cfg.training_seeds)
        names = {n: first if n == cfg.window else f"{row} (N={n})" for n in sorted(p.windows)}
        study_rows = WindowStudy(
            row,
            [
                {"window": n, "name": name, "rmse": study.results[name].rmse, "cost_ms": study.results[name].cost_ms}
                for n, name in names.items()
            ],
        )
    checks = requirements(cfg, study)
    spread = SeedSpread({r: {s: seed_row(r, s, seeds) for s in seeds} for r in cfg.learned}) if len(seeds) > 1 else None
    spec = ReportSpec(
        layout=cfg.report,
        seeds=spread,
        training=Training(
            learning_curves(filters, rows), validation_references(filters, rows), training_costs(sp.jobs)
        ),
        window_study=study_rows,
        requirements=checks,
        notes=_notes(sp, learned, choice, study),
        meta={
            "wall_time_s": round(time.perf_counter() - start, 1),
            "command": plan.command(*pinned, drop=["scenarios"]),
        },
    )
    report = write_report(study, Path(cfg.report_dir), title=title, profile=cfg.profile, spec=spec)
    if cfg.logger == "wandb":
        run_dir = log_report(
            Path(cfg.report_dir),
            name=f"report {cfg.system}/{cfg.scenario} {cfg.profile}",
            group=_group(cfg),
            tags=[cfg.system, cfg.scenario, cfg.profile, "report"],
            project="daof",
            mode="offline",
        )
        print(f"wandb run of the report: {run_dir}")
    for check in checks:
        print(f"{check.requirement}: {'met' if check.met else 'NOT met'} ({check.detail})")
    return study, report


def run_experiment(plan: Plan) -> list[Path]:
    """Train, study and report every scenario of a checked plan; returns the report(s) written."""
    cfg = plan.cfg
    names = list(plan.scenarios)
    several = len(names) > 1
    where = Path(cfg.root) if several else Path(plan.scenarios[names[0]].cfg.output_root)
    start = time.perf_counter()
    print(f"{cfg.title.format(scenario=', '.join(names))} ({cfg.profile} profile) -> {where}")
    print("1/3 training the learned filters")
    jobs = [job for sp in plan.scenarios.values() for job in sp.jobs.values()]
    train(jobs, parallel=cfg.parallel_jobs, address=cfg.ray.address)

    studies, reports = {}, {}
    for s, sp in plan.scenarios.items():
        studies[s], reports[s] = run_scenario(plan, sp, start)
        if several:
            print(f"report ({s}): {reports[s]}")
    wall = time.perf_counter() - start
    if not several:
        print(f"report: {reports[names[0]]}  ({wall / 60:.1f} min)")
        return [reports[names[0]]]
    first = plan.scenarios[names[0]]
    combined = write_scenario_report(
        studies,
        Path(cfg.combined_report_dir),
        title=cfg.title.format(scenario="scenarios side by side"),
        profile=cfg.profile,
        reports=reports,
        notes=_format(cfg.combined_notes, _fields(first, {})),
        meta={
            "wall_time_s": round(wall, 1),
            "command": plan.command(f"profile={cfg.profile}", f"scenarios=[{','.join(names)}]"),
        },
    )
    print(f"combined report: {combined}  ({wall / 60:.1f} min)")
    return [*reports.values(), combined]


def main(argv: list[str] | None = None, *, experiment: str | None = None, program: str | None = None) -> list[Path]:
    """``python -m daof.experiments experiment=NAME [key=value ...]``; a recipe fixes ``experiment`` and
    its own ``program`` (the script the report's command names). A bad input exits with one line."""
    args = list(sys.argv[1:] if argv is None else argv)
    chosen = [a.split("=", 1)[1] for a in args if a.split("=", 1)[0] == "experiment"]
    overrides = [a for a in args if a.split("=", 1)[0] != "experiment"]
    if experiment is not None and chosen:
        raise SystemExit(f"{program or 'this script'} runs experiment={experiment}; leave out experiment=")
    if experiment is None:
        if len(chosen) != 1:
            from daof.experiments.config import experiment_names

            valid = ", ".join(experiment_names())
            raise SystemExit(f"give one experiment=NAME; valid: {valid} or a path to a YAML file")
        experiment = chosen[0]
    try:
        plan = plan_experiment(experiment, overrides, program)
        for sp in plan.scenarios.values():  # a read-only results root: one line before any work
            writable_directory(sp.cfg.output_root, "output directory")
    except ValueError as error:
        raise SystemExit(str(error)) from None
    return run_experiment(plan)
