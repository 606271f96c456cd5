"""The typed experiment configuration: what one experiment trains, studies and reports, per system.

An experiment is a YAML file in ``daof/conf/experiment/`` (``veh2dof``, ``linear``, ``veh14dof``)
over the dataclasses below, registered with Hydra's ConfigStore as ``experiment_schema``. What
differs between experiments is config, not code: the learned rows (training filter, run
directory, budget and overrides per profile), the classical filters and the study's reference,
the report's layout, its checks and its notes. What belongs to a system (its scenarios, units and
reporting scale, whether it has a model) is read from the system. ``compose_experiment`` composes
and checks one; every problem (an unknown experiment, key, profile or scenario, a wrong type, an
impossible value) is one ``ValueError`` line, raised before any work.

Every key: ``docs/experiments.md``.
"""

from __future__ import annotations

import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from daof.config_checks import check_override_keys, one_line
from daof.device import resolve_device
from daof.evaluate.report import PAPER_TABLES, Layout
from daof.train.config import CONF_DIR as TRAIN_CONF_DIR

__all__ = [
    "CLASSICAL_FILTERS",
    "EXPERIMENT_DIR",
    "NOTE_FIELDS",
    "PARTICLE_FILTERS",
    "ClassicalFilter",
    "ConvergenceCheck",
    "DropoutStudy",
    "EXACT_FILTERS",
    "ExperimentConfig",
    "LearnedRow",
    "Profile",
    "RaySettings",
    "Tolerance",
    "check_experiment",
    "compose_experiment",
    "experiment_file",
    "experiment_names",
    "for_scenario",
    "note_fields",
]

#: the experiments: one YAML file each
EXPERIMENT_DIR = TRAIN_CONF_DIR / "experiment"
#: the classes of daof.filters an experiment may name as classical filters (particle filters need a count)
CLASSICAL_FILTERS = (
    "EKF",
    "UKF",
    "KalmanFilter",
    "StationaryKalmanFilter",
    "ParticleFilter",
    "JointParameterPF",
    "ProposalParticleFilter",
)
PARTICLE_FILTERS = ("ParticleFilter", "JointParameterPF", "ProposalParticleFilter")
#: the filter that may be marked ``exact``: the posterior mean itself on a linear-Gaussian system
EXACT_FILTERS = ("KalmanFilter",)
#: what ``logger=`` may name ("" logs nothing beyond the trainings' CSV files)
LOGGERS = ("", "wandb")


@dataclass
class LearnedRow:
    """One learned filter of the report: ``python -m daof.train filter=<filter> system=<system> window=N ...``."""

    filter: str = MISSING  # the training's filter group: daof_v1 | daof_v2 | slf | kalmannet
    dir: str | None = None  # run directory <output_root>/<dir>-N<window> (null: the filter, e.g. daof-v1)
    overrides: list[str] = field(default_factory=list)  # training overrides of this row in every profile


@dataclass
class ClassicalFilter:
    """One model-based filter of the study, a class of ``daof.filters`` built on the scenario's system."""

    filter: str = MISSING  # one of CLASSICAL_FILTERS
    seed: int = 0  # particle filters: their generator's seed (the count is the profile's particles[<name>])
    scenarios: list[str] | None = None  # run on these scenarios only (null: on every one)
    exact: bool = False  # the posterior mean itself (a KalmanFilter on a linear-Gaussian system): a reference unchecked
    fallback: bool = False  # a reference candidate run only when those before it fail their convergence check


@dataclass
class Profile:
    """One size of the experiment (tiny | quick | paper): the study's size and every budget."""

    runs: int = MISSING  # Monte Carlo runs R
    steps: int = MISSING  # steps T per run
    frames: dict[str, int] = MISSING  # learned row -> training budget (samples)
    particles: dict[str, int] = field(default_factory=dict)  # particle filter -> particle count
    overrides: dict[str, list[str]] = field(default_factory=dict)  # learned row -> this profile's training overrides
    windows: list[int] = field(default_factory=list)  # the window study's N (window_study's row at each; []: none)
    system: dict[str, Any] = field(default_factory=dict)  # system parameters of the study and of every training
    uncertainty_runs: int = 256  # episodes each learned filter's uncertainty head is fitted on (0: no heads)


@dataclass
class Tolerance:
    """A requirement on one filter: its RMSE ≤ ``tolerance`` × the study reference's, per state."""

    tolerance: float = MISSING
    settled_step: int | None = None  # also every filter's ratios over the steps after this one (start-up excluded)


@dataclass
class ConvergenceCheck:
    """Is a particle-filter reference converged? Run again with twice its particles; its RMSE should barely move.

    Every particle filter that becomes the study's reference is checked (``daof.experiments.reference``).
    """

    seed: int = 3  # the doubled filter's seed
    limit_percent: float = 1.0  # converged: the RMSE changes by less than this on every state


@dataclass
class DropoutStudy:
    """The same study once more with sensor gaps (``daof.evaluate.Dropout``) -> <report_dir>/dropout/."""

    enabled: bool = False
    p: float = 0.1  # each channel missing with this probability per step
    blackout: list[Any] | None = None  # [channel, start_s, duration_s]: that channel lost in every run (null: none)
    seed: int = 0


@dataclass
class RaySettings:
    """Where the trainings run as Ray tasks (``daof.experiments.ray_jobs``)."""

    address: str | None = None  # null: a local Ray of parallel_jobs CPUs; auto or host:6379: that cluster


@dataclass
class ExperimentConfig:
    system: str = MISSING  # a registered name, an import path pkg.mod:Cls or an entry point (daof.envs.make_system)
    title: str = MISSING  # the report's title; {scenario} is replaced by the scenario
    root: str = MISSING  # results root of one profile
    profile: str = "quick"
    profiles: dict[str, Profile] = MISSING
    scenario: str = "nominal"  # the one scenario of a default run
    scenarios: list[str] = field(default_factory=lambda: ["${scenario}"])  # several: each, plus a combined report
    output_root: str = "${root}/${scenario}"  # one scenario's trainings, study cache and report
    report_dir: str = "${output_root}/report"
    combined_report_dir: str = "${root}/report"  # written when there are several scenarios
    cache_dir: str | None = None  # memoise the study's simulated data here (daof.envs.recorded); null: simulate
    seed: int = 20261122  # evaluation seed: disjoint from training (1..) and validation (9100) seeds
    # every learned row trains once per seed; with several, its report rows are "<row> (seed <s>)"
    training_seeds: list[int] = field(default_factory=lambda: [1])
    window: int = 20  # N of every learned row (the window study's row also at the profile's windows)
    parallel_jobs: int | None = None  # trainings at once: a local Ray's CPUs, one thread each (null: every core)
    ray: RaySettings = field(default_factory=RaySettings)
    timing_threads: int = 1  # torch threads while timing cost per estimate
    logger: str = ""  # wandb: every training and the report log an (offline) wandb run; "" none (docs/experiments.md)
    device: str = "cpu"  # cpu | cuda | cuda:<k> | auto: where the trainings and the study's learned filters run
    learned: dict[str, LearnedRow] = field(default_factory=dict)  # report row -> its training, in report order
    training_overrides: list[str] = field(default_factory=list)  # overrides of every training
    sweep_override: str | None = None  # one training override applied after all others (daof.experiments.sweep)
    window_study: str | None = None  # a learned row trained again at every N of the profile's windows
    classical_only: bool = False  # leave out the learned rows: study and report the classical filters (a first check)
    classical: dict[str, ClassicalFilter] = field(default_factory=dict)  # study row -> model-based filter
    # the study's reference candidates, in order: the first that runs and is exact or converged (else the best filter)
    reference: list[str] = field(default_factory=list)
    convergence_check: ConvergenceCheck = field(default_factory=ConvergenceCheck)
    requirements: dict[str, Tolerance] = field(default_factory=dict)  # filter -> its tolerance to the reference
    report: Layout = field(default_factory=Layout)
    dropout: DropoutStudy = field(default_factory=DropoutStudy)
    notes: list[str] = field(default_factory=list)  # the report's notes; {field} placeholders: note_fields
    scenario_notes: dict[str, list[str]] = field(default_factory=dict)  # scenario -> notes on that scenario only
    combined_notes: list[str] = field(default_factory=list)  # notes of the combined report


#: the placeholders a note may use, and what they are
NOTE_FIELDS = {
    "system": "the system's name",
    "scenario": "the scenario",
    "profile": "the profile's name",
    "seed": "the evaluation seed",
    "training_seeds": "the training seeds (a list)",
    "window": "N of the learned rows",
    "runs": "the profile's runs",
    "steps": "the profile's steps",
    "frames": "learned row -> budget ({frames[SLF]})",
    "particles": "particle filter -> count ({particles[PF]})",
    "windows": "the window study's N",
    "overrides": "learned row -> its overrides beyond the common ones, or 'none' ({overrides[SLF]})",
    "train": "learned row -> its resolved training config ({train[SLF].optim.lr})",
    "networks": "every learned filter's network: '<row>: <depth> × <cells> GELU, N = <window>; ...'",
}


def note_fields(template: str) -> set[str]:
    """The placeholder names a note template uses (``{particles[PF]}`` -> ``particles``)."""
    names = set()
    for _, name, _, _ in string.Formatter().parse(template):
        if name is not None:
            names.add(name.split(".")[0].split("[")[0])
    return names


def experiment_names() -> list[str]:
    return sorted(p.stem for p in EXPERIMENT_DIR.glob("*.yaml"))


def experiment_file(name: str) -> tuple[Path, str]:
    """(config folder, config name) of experiment ``name``: one of daof's, or a path to a YAML file of the user's.

    A name ending in ``.yaml`` or holding a ``/`` is a path (relative to the working directory), so
    an experiment kept in the user's own project runs as ``experiment=path/to/experiment.yaml``.
    """
    if not (name.endswith(".yaml") or "/" in name):
        if name not in experiment_names():
            raise ValueError(
                f"unknown experiment {name!r}; valid: {', '.join(experiment_names())} or a path to a YAML file"
            )
        return EXPERIMENT_DIR, name
    path = Path(name).expanduser().resolve()
    if not path.is_file():
        raise ValueError(f"no experiment file {name!r} (looked for {path})")
    if path.suffix != ".yaml":
        raise ValueError(f"experiment file {name!r} is not a .yaml file")
    return path.parent, path.stem


def register_configs() -> None:
    """Register the schema (``defaults: [experiment_schema, _self_]`` in ``daof/conf/experiment/*.yaml``)."""
    ConfigStore.instance().store(name="experiment_schema", node=ExperimentConfig)
    OmegaConf.register_new_resolver("abspath", lambda p: None if p is None else str(Path(p).resolve()), replace=True)


# ----------------------------------------------------------------------------------------- compose
def compose_experiment(name: str, overrides: list[str] = ()) -> DictConfig:
    """Experiment ``name``'s config with command-line style ``overrides``, unresolved (``for_scenario``
    resolves it per scenario); an unknown experiment, key or choice, or a wrong type, is one ``ValueError`` line."""
    overrides = list(overrides)
    config_dir, config_name = experiment_file(name)
    check_override_keys(ExperimentConfig, overrides, "experiment", "docs/experiments.md lists every key")
    register_configs()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as error:
        raise ValueError(one_line(error)) from None
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise ValueError(f"experiment {name}: key(s) {missing} have no value")
    if cfg.classical_only:  # no learned row, no budget, no window study; what names a learned row goes too
        learned = set(cfg.learned)
        cfg.learned, cfg.window_study = {}, None
        cfg.reference = [r for r in cfg.reference if r not in learned]
        cfg.requirements = {k: v for k, v in cfg.requirements.items() if k not in learned}
        if cfg.report.paired_with in learned:
            cfg.report.paired_with = None
        for profile in cfg.profiles.values():
            profile.frames, profile.overrides, profile.windows = {}, {}, []
    return cfg


def for_scenario(cfg: DictConfig, scenario: str) -> ExperimentConfig:
    """``cfg`` with ``scenario`` set and every path resolved for it, as the typed ``ExperimentConfig``."""
    out = cfg.copy()
    out.scenario = scenario
    try:
        OmegaConf.resolve(out)
        return OmegaConf.to_object(out)
    except OmegaConfBaseException as error:
        raise ValueError(one_line(error)) from None


# ----------------------------------------------------------------------------------------- checks
def _at_least(value, low, what: str) -> None:
    if value is None or value < low:
        raise ValueError(f"{what} must be >= {low}, got {value}")


def _subset(keys, valid, what: str, of: str) -> None:
    unknown = [k for k in keys if k not in valid]
    if unknown:
        raise ValueError(f"{what} {unknown} {'is' if len(unknown) == 1 else 'are'} not {of}; valid: {list(valid)}")


def _check_reference(cfg: ExperimentConfig, systems: dict, particle: list[str]) -> None:
    """Every reference candidate can be trusted or checked: exact, or a particle filter the check can double."""
    from daof.envs.noise import GaussianNoise

    checkable = [*particle, *(n for n, c in cfg.classical.items() if c.exact)]
    _subset(cfg.reference, checkable, "reference", "an exact or particle filter of classical (a reference is checked)")
    if len(set(cfg.reference)) != len(cfg.reference):
        raise ValueError(f"reference {list(cfg.reference)} names a filter more than once")
    for name, spec in cfg.classical.items():
        if spec.fallback and name not in cfg.reference:
            raise ValueError(f"classical.{name}.fallback: only a reference candidate runs as a fallback")
        if spec.fallback and spec.exact:
            raise ValueError(f"classical.{name}: an exact filter needs no fallback; set exact or fallback, not both")
        if not spec.exact:
            continue
        if spec.filter not in EXACT_FILTERS:
            raise ValueError(f"classical.{name}.exact: only {list(EXACT_FILTERS)} can be exact, not {spec.filter}")
        for scenario, system in systems.items():
            noises = (system.prior, system.process_noise, system.measurement_noise)
            if not all(type(noise) is GaussianNoise for noise in noises):
                raise ValueError(
                    f"classical.{name}.exact: {cfg.system} ({scenario}) has non-Gaussian noise, so the Kalman "
                    "filter is not its posterior mean"
                )
    if not cfg.convergence_check.limit_percent > 0:
        raise ValueError(f"convergence_check.limit_percent must be > 0, got {cfg.convergence_check.limit_percent}")


def check_experiment(cfg: ExperimentConfig) -> Profile:
    """Refuse an impossible experiment before any work, in one line naming the key; returns its profile."""
    from daof.envs import make_system
    from daof.evaluate.dropout import dropout_mask

    resolve_device(cfg.device)  # a GPU that is not there: one line, before any work
    if cfg.profile not in cfg.profiles:
        raise ValueError(f"unknown profile {cfg.profile!r}; valid: {list(cfg.profiles)}")
    p = cfg.profiles[cfg.profile]
    where = f"profiles.{cfg.profile}"
    for key in ("runs", "steps"):
        _at_least(getattr(p, key), 1, f"{where}.{key}")
    for key in ("window", "timing_threads"):
        _at_least(getattr(cfg, key), 1, key)
    if str(cfg.ray.address).startswith("ray://"):
        raise ValueError(
            f"ray.address={cfg.ray.address}: Ray Client cannot run the trainings (they stream their start); "
            "run the experiment on a node of the cluster with ray.address=auto or its head's host:6379"
        )
    if cfg.parallel_jobs is not None:
        _at_least(cfg.parallel_jobs, 1, "parallel_jobs")
        if cfg.ray.address is not None:
            address = cfg.ray.address
            raise ValueError(f"parallel_jobs sizes a local Ray; the cluster at ray.address={address} has its own CPUs")
    seeds = list(cfg.training_seeds)
    if not seeds or len(set(seeds)) != len(seeds) or any(isinstance(x, bool) or not isinstance(x, int) for x in seeds):
        raise ValueError(f"training_seeds must be distinct integers, at least one, got {seeds}")
    if cfg.logger not in LOGGERS:
        raise ValueError(f"logger must be one of {list(LOGGERS)}, got {cfg.logger!r}")

    scenarios = cfg.scenarios
    if not scenarios:
        raise ValueError(f"scenarios must be one or more scenario names of {cfg.system}, got []")
    if len(set(scenarios)) != len(scenarios):
        raise ValueError(f"scenarios {list(scenarios)} name a scenario more than once")
    try:
        systems = {s: make_system(cfg.system, s, **p.system) for s in scenarios}
    except (TypeError, ValueError) as error:
        raise ValueError(str(error).splitlines()[0]) from None
    system = systems[scenarios[0]]
    valid_scenarios = list(system.scenarios)
    _subset(cfg.scenario_notes, valid_scenarios, "scenario_notes", f"scenarios of {cfg.system}")

    learned = cfg.learned
    groups = sorted(p.stem for p in (TRAIN_CONF_DIR / "filter").glob("*.yaml"))
    for name, row in learned.items():
        if row.filter not in groups:
            raise ValueError(f"learned.{name}.filter={row.filter!r} is not valid; valid: {groups}")
        if name not in p.frames:
            raise ValueError(f"{where}.frames has no budget for the learned row {name!r}")
        _at_least(p.frames[name], 1, f"{where}.frames.{name}")
    _subset(p.frames, learned, f"{where}.frames", "learned rows")
    _subset(p.overrides, learned, f"{where}.overrides", "learned rows")
    if cfg.window_study is not None:
        _subset([cfg.window_study], learned, "window_study", "a learned row")
        for n in p.windows:  # none: this profile has no window study
            _at_least(n, 1, f"{where}.windows")
        if len(set(p.windows)) != len(p.windows):
            raise ValueError(f"{where}.windows {list(p.windows)} names a window more than once")
    elif p.windows:
        raise ValueError(f"{where}.windows is set but window_study names no learned row")

    classical = cfg.classical
    clash = sorted(set(classical) & set(learned))
    if clash:
        raise ValueError(f"{clash} are both classical filters and learned rows")
    if classical and not system.has_model:
        raise ValueError(f"{cfg.system} has no model for filters: the classical filters {list(classical)} cannot run")
    particle = [n for n, c in classical.items() if c.filter in PARTICLE_FILTERS]
    for name, spec in classical.items():
        if spec.filter not in CLASSICAL_FILTERS:
            raise ValueError(f"classical.{name}.filter={spec.filter!r} is not valid; valid: {list(CLASSICAL_FILTERS)}")
        _subset(spec.scenarios or [], valid_scenarios, f"classical.{name}.scenarios", f"scenarios of {cfg.system}")
        if name in particle:
            if name not in p.particles:
                raise ValueError(f"{where}.particles has no particle count for {name!r}")
            _at_least(p.particles[name], 1, f"{where}.particles.{name}")
    _subset(p.particles, particle, f"{where}.particles", "particle filters of classical")
    if not classical and not learned:
        raise ValueError("the experiment has no filters: set learned and/or classical")

    rows = [*classical, *learned]
    _check_reference(cfg, systems, particle)
    for name, req in cfg.requirements.items():
        _subset([name], rows, "requirements", "filters of the study")
        if not req.tolerance > 0:
            raise ValueError(f"requirements.{name}.tolerance must be > 0, got {req.tolerance}")
        if req.settled_step is not None:
            _at_least(req.settled_step, 0, f"requirements.{name}.settled_step")
        if not cfg.reference:
            raise ValueError(f"requirements.{name} is relative to the study's reference, but reference is empty")
    if cfg.report.paired_with is not None:
        _subset([cfg.report.paired_with], rows, "report.paired_with", "a filter of the study")
    if cfg.report.paper_table is not None:
        _subset([cfg.report.paper_table], PAPER_TABLES, "report.paper_table", "a paper table")

    d = cfg.dropout
    if not 0.0 <= d.p <= 1.0:
        raise ValueError(f"dropout.p must be in [0, 1], got {d.p}")
    if d.blackout is not None and len(d.blackout) != 3:
        raise ValueError(f"dropout.blackout must be [channel, start_s, duration_s] or null, got {list(d.blackout)}")
    if d.enabled:
        try:
            blackout = tuple(d.blackout) if d.blackout is not None else None
            shape = (1, p.steps, system.measurement_dim)
            dropout_mask(shape, d.p, blackout, d.seed, dt=system.dt, channel_names=system.measurement_names)
        except (TypeError, ValueError) as error:
            raise ValueError(f"dropout: {error}") from None

    for note in [*cfg.notes, *cfg.combined_notes, *(n for notes in cfg.scenario_notes.values() for n in notes)]:
        unknown = sorted(note_fields(note) - set(NOTE_FIELDS))
        if unknown:
            raise ValueError(f"note {note[:40]!r}... uses unknown field(s) {unknown}; valid: {sorted(NOTE_FIELDS)}")
    return p
