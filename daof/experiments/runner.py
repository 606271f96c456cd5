"""What every experiment does around the study: training jobs, trained filters, cached studies, provenance.

An experiment (``daof.experiments.experiment``) trains its learned filters as ``TrainingJob``s,
loads their best checkpoints, runs the study and writes the report; these helpers are the parts
that do not depend on the experiment's config. A bad input (a checkpoint of another run, a failed
training) ends the run with one line naming the problem (``SystemExit``), not a traceback.
"""

from __future__ import annotations

import copy
import json
import shlex
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from daof.device import resolve_device
from daof.evaluate.study import ORACLE, Study, run_study
from daof.experiments.jobs import TrainingJob, run_jobs
from daof.filters.learned import load_filter
from daof.filters.learned.uncertainty import head_path
from daof.fingerprint import checkpoint_fingerprint, classical_fingerprint

__all__ = [
    "command_line",
    "learning_curves",
    "load_trained",
    "run_trained_study",
    "train",
    "training_costs",
    "validation_references",
]


def command_line(program: str, *pinned: str, given: Sequence[str] = (), drop: Sequence[str] = ()) -> str:
    """The command that reproduces a report: ``python program``, the ``pinned`` key=value arguments,
    then every other override ``given`` on the command line (those of keys in ``drop`` left out)."""
    skip = {*drop, *(arg.split("=", 1)[0] for arg in pinned)}
    rest = [arg for arg in given if arg.split("=", 1)[0].lstrip("+~") not in skip]
    return " ".join(["python", program, *map(shlex.quote, [*pinned, *rest])])


def train(jobs: Sequence[TrainingJob], parallel: int | None = None, address: str | None = None, log=print) -> None:
    """``run_jobs``; a failed job (a training, a head) exits with one line naming it and its log, not a traceback."""
    try:
        run_jobs(list(jobs), parallel=parallel, address=address, log=log)
    except RuntimeError as error:
        raise SystemExit(str(error)) from None


def load_trained(
    jobs: dict[str, TrainingJob], system, expect: dict | Callable[[str], dict] | None = None, device="cpu"
) -> dict:
    """Each job's ``best.pt`` as a filter (name -> ``LearnedFilter``) on ``device``, checked against ``expect``.

    ``expect``: config fields every checkpoint must have (``{"system": ..., "window": ...}``), or a
    function of the job name giving them. A missing checkpoint, or one of another system, scenario
    or window (a stale output directory), exits with one line that names the job and its directory.
    """
    filters = {}
    device = resolve_device(device)
    if device.type != "cpu":  # the filters' own copy of the system (DAOF-v1 predicts with it); the study's stays
        system = copy.deepcopy(system).to(device)
    for name, job in jobs.items():
        fields = expect(name) if callable(expect) else expect
        path = job.output_dir / "best.pt"
        try:
            filters[name] = load_filter(path, system, expect=fields).to(device)
        except (FileNotFoundError, ValueError) as error:
            raise SystemExit(f"{name}: {error} (train it again: delete {job.output_dir})") from None
    return filters


def run_trained_study(
    system,
    jobs: dict[str, TrainingJob],
    *,
    runs: int,
    steps: int,
    seed: int,
    cache_dir: str | Path,
    classical: dict | None = None,
    expect: dict | Callable[[str], dict] | None = None,
    timing_threads: int = 1,
    reference: str | None = ORACLE,
    dropout=None,
    log=print,
    device="cpu",
) -> tuple[Study, dict]:
    """The study of ``classical`` filters (name -> filter) and every job's best checkpoint after them.

    Learned filters are cached under a digest of their checkpoint and uncertainty head
    (``checkpoint_fingerprint``), so a retrained filter or a refitted head is never scored from a stale
    cache entry; classical ones under a digest of their code and settings (``classical_fingerprint``), so
    an edited filter is run again.
    ``dropout`` (a ``Dropout``) runs the study on the same data with those measurement gaps.
    ``device``: where the learned filters run (the classical ones stay on the CPU).
    Returns the study and every filter.
    """
    filters = dict(classical or {})
    clash = sorted(set(filters) & set(jobs))
    if clash:
        raise ValueError(f"filter names {clash} are both classical filters and training jobs")
    filters.update(load_trained(jobs, system, expect, device))
    # the weights and how a missing channel is read (it changes the estimates under dropout)
    versions = {name: classical_fingerprint(filt, system) for name, filt in (classical or {}).items()}
    versions.update(
        {
            name: f"{checkpoint_fingerprint(_filter_files(job.output_dir / 'best.pt'))}-{filters[name].missing_fill}"
            for name, job in jobs.items()
        }
    )
    study = run_study(
        system,
        filters,
        runs,
        steps,
        seed,
        timing_threads,
        cache_dir=cache_dir,
        log=log,
        versions=versions,
        reference=reference,
        dropout=dropout,
        device=device,
    )
    return study, filters


def _filter_files(path: Path) -> list[Path]:
    """A filter's checkpoint and, where there is one, its uncertainty head (a refitted head is a new version)."""
    head = head_path(path)
    return [path, head] if head.is_file() else [path]


def learning_curves(filters: dict, names=None) -> dict[str, list[dict]]:
    """Validation history of each learned filter's training run (name -> list of records).

    From the run's ``final.pt`` beside the loaded checkpoint where there is one: a ``best.pt``
    holds the history only up to the best validation, so the curve would stop there.
    """
    names = names if names is not None else list(filters)
    return {name: _training_history(filters[name]) for name in names if name in filters}


def _training_history(filt) -> list[dict]:
    path = getattr(filt, "path", None)
    final = Path(path).with_name("final.pt") if path is not None else None
    if final is not None and final.is_file():
        return torch.load(final, map_location="cpu", weights_only=True).get("extra", {}).get("history", [])
    return getattr(filt, "extra", {}).get("history", [])


def validation_references(filters: dict, names=None) -> dict[str, list[float]]:
    """Reference filters' RMSE on the validation set of the training runs (e.g. ``{"UKF": [...]}``).

    Read from the ``summary.json`` beside the first of ``names`` whose run recorded them; the
    learning curves are on that set, so these are the lines to draw beside them.
    """
    for name in names if names is not None else list(filters):
        path = getattr(filters.get(name), "path", None)
        summary = Path(path).with_name("summary.json") if path is not None else None
        if summary is not None and summary.is_file():
            references = json.loads(summary.read_text()).get("validation_references") or {}
            if references:
                return references
    return {}


def training_costs(jobs: dict[str, TrainingJob]) -> dict[str, dict]:
    """Samples, updates, wall time and threads of every finished training job (the report's table)."""
    return {
        name: {k: job.summary().get(k) for k in ("frames", "updates", "wall_s", "threads")}
        for name, job in jobs.items()
    }
