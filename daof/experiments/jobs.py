"""Training jobs (``python -m daof.train``) run as Ray tasks, reusing finished runs and resuming broken ones.

A job is one training with its overrides and its own output directory. A job whose
``summary.json`` records at least the requested number of frames is finished and reused; one
with a ``checkpoint.pt`` is resumed from it; anything else starts fresh. Either only if the
directory's ``run_config.json`` (the resolved config its trainer ran with) equals the config the
job asks for now, apart from what a continuation may change (the budget, the output directory,
threads and logger: ``daof.train.base.RESUMABLE_CHANGES``), so a results root can be moved or
copied and is still reused. A directory from another config is moved aside to
``<dir>.stale-<n>`` and the job starts fresh. A trainer holds a lock on its directory
(``daof.train.lock``), so a second trainer never runs in it, whichever process or machine starts it.
A ``HeadJob`` fits a finished training's uncertainty head the same way, after the trainings.

The unfinished jobs run as Ray tasks (``daof.experiments.ray_jobs``): on a local Ray of ``parallel``
CPUs (None: every core), one training per CPU, or on the cluster at ``address``. Without the
``ray`` package they run one at a time as children of this process, and ``run_jobs`` says once
that ``pip install -e ".[ray]"`` runs them in parallel. Either way each training is a child
process that dies with its parent (``daof.experiments.training_process``), and stopping
``run_jobs`` (an exception, Ctrl-C or SIGTERM) stops the trainings it started.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import json
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from omegaconf import OmegaConf
from tqdm import tqdm

from daof.experiments.training_process import launch, resumes, stop
from daof.filters.learned.uncertainty import head_path, load_head
from daof.io import safe_load
from daof.train.base import PROGRESS, RUN_CONFIG, comparable_config
from daof.train.config import compose_config
from daof.train.uncertainty import HeadSettings, head_arguments, head_fitted

__all__ = ["HeadJob", "TrainingJob", "run_jobs"]


@dataclass
class TrainingJob:
    """One training run: ``python -m daof.train overrides... output_dir=out``."""

    name: str
    output_dir: Path
    total_frames: int
    overrides: list[str] = field(default_factory=list)
    #: the command that trains, before the overrides (another interpreter, or a stand-in in tests);
    #: None: ``python -m daof.train`` with the interpreter of the process that starts it (a Ray worker's)
    launcher: list[str] | None = None
    #: folders the training must import from (a system of the user's code), put first on its PYTHONPATH
    pythonpath: list[str] = field(default_factory=list)
    #: what its process does, what it leaves when it succeeds, and the file in ``output_dir`` of its output
    doing: ClassVar[str] = "training"
    output: ClassVar[str] = "a summary and a readable best.pt"
    log_name: ClassVar[str] = "train.log"

    @property
    def log_path(self) -> Path:
        return self.output_dir / self.log_name

    @property
    def summary_path(self) -> Path:
        return self.output_dir / "summary.json"

    def finished(self) -> bool:
        """Its summary records the budget, its config is the one asked for, and its ``best.pt`` reads.

        A truncated or damaged ``best.pt`` is no finished run: the job resumes from its checkpoint,
        which writes ``best.pt`` again.
        """
        best = self.output_dir / "best.pt"
        if not self.summary_path.is_file() or not best.is_file():
            return False
        try:
            done = json.loads(self.summary_path.read_text()).get("frames", 0) >= self.total_frames
        except (OSError, ValueError):  # a summary cut short is no finished run
            return False
        if not (done and self.config_matches()):
            return False
        try:
            safe_load(best)
        except ValueError:
            return False
        return True

    @property
    def arguments(self) -> list[str]:
        """The overrides of ``python -m daof.train`` for this job (without ``resume``)."""
        return [*self.overrides, f"collector.total_frames={self.total_frames}", f"output_dir={self.output_dir}"]

    @functools.cached_property
    def requested_config(self) -> dict:
        """The resolved config this job trains with (composed once, in-process)."""
        try:
            return OmegaConf.to_container(compose_config(self.arguments))
        except ValueError as error:
            raise RuntimeError(f"{self.name}: {error}") from None

    def config_matches(self) -> bool:
        """Whether the run in ``output_dir`` was started with the config this job asks for."""
        path = self.output_dir / RUN_CONFIG
        if not path.is_file():
            return False
        try:
            saved = json.loads(path.read_text())
        except ValueError:
            return False
        return comparable_config(saved) == comparable_config(self.requested_config)

    def set_aside_if_stale(self) -> Path | None:
        """Move a run of another config out of the way (nothing is deleted); returns where it went."""
        if not self.output_dir.is_dir() or not any(self.output_dir.iterdir()) or self.config_matches():
            return None
        k = 1
        while (target := self.output_dir.with_name(f"{self.output_dir.name}.stale-{k}")).exists():
            k += 1
        shutil.move(str(self.output_dir), str(target))
        return target

    def command(self, with_resume: bool = True) -> list[str]:
        cmd = [*(self.launcher or [sys.executable, "-m", "daof.train"]), *self.arguments]
        checkpoint = self.output_dir / "checkpoint.pt"
        if with_resume and checkpoint.is_file():
            cmd.append(f"resume={checkpoint}")
        return cmd

    def summary(self) -> dict:
        return json.loads(self.summary_path.read_text())

    def progress(self) -> str:
        return progress_line(self)

    def environment(self, base: dict[str, str]) -> dict[str, str]:
        """``base`` (the process environment) with ``pythonpath`` first on ``PYTHONPATH``, output unbuffered."""
        paths = [*self.pythonpath, *([base["PYTHONPATH"]] if base.get("PYTHONPATH") else [])]
        return {**base, "PYTHONUNBUFFERED": "1", **({"PYTHONPATH": os.pathsep.join(paths)} if paths else {})}


@dataclass
class HeadJob:
    """Fitting the uncertainty head of a finished training: ``python -m daof.train.uncertainty RUN_DIR``.

    Run by ``run_jobs`` like a training (in parallel on Ray), with its output in ``uncertainty.log``;
    finished when the head beside ``best.pt`` was fitted to that very file.
    """

    training: TrainingJob
    settings: HeadSettings
    doing: ClassVar[str] = "fitting"
    output: ClassVar[str] = "head fitted to best.pt"
    log_name: ClassVar[str] = "uncertainty.log"
    requested_config: ClassVar[dict] = {}  # nothing to pin: the head's settings are its arguments

    @property
    def name(self) -> str:
        return f"{self.training.name} uncertainty head"

    @property
    def output_dir(self) -> Path:
        return self.training.output_dir

    @property
    def log_path(self) -> Path:
        return self.output_dir / self.log_name

    def finished(self) -> bool:
        return head_fitted(self.output_dir / "best.pt")

    def set_aside_if_stale(self) -> None:
        return None  # a head of another best.pt is fitted again in place

    def command(self) -> list[str]:
        return [sys.executable, "-m", "daof.train.uncertainty", str(self.output_dir), *head_arguments(self.settings)]

    def environment(self, base: dict[str, str]) -> dict[str, str]:
        return self.training.environment(base)  # the training's system code, if it is the user's

    def summary(self) -> dict:
        return {"wall_s": load_head(head_path(self.output_dir / "best.pt")).extra.get("wall_s")}

    def progress(self) -> str:
        return self.doing  # a head's fit writes no progress file


def _count(n: float) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k" if n >= 1e3 else f"{n:g}"


def progress_line(job: TrainingJob) -> str:
    """Where a running training is: frames of its budget, wall time, ETA, latest validation RMSE."""
    try:
        p = json.loads((job.output_dir / PROGRESS).read_text())
    except (OSError, ValueError):
        return "starting"
    frames, total, wall = p["frames"], max(int(p["total"]), 1), float(p["wall_s"])
    line = f"{_count(frames)}/{_count(total)} frames ({100 * frames / total:.0f} %), {wall / 60:.1f} min"
    if 0 < frames < total:
        line += f", ETA {wall / frames * (total - frames) / 60:.1f} min"
    if p.get("rmse"):
        line += ", validation RMSE " + " ".join(f"{k} {v:.4g}" for k, v in p["rmse"].items())
    return line


class _Status:
    """One live line per running job on a terminal; elsewhere a status line per job every ``every`` s."""

    def __init__(self, log, every: float):
        self.log, self.every, self.last = log, every, time.monotonic()
        self.live = sys.stdout.isatty()
        self.bars: dict[str, tqdm] = {}

    def show(self, running: list[TrainingJob]) -> None:
        if self.live:
            for name in [n for n in self.bars if n not in {j.name for j in running}]:
                self.bars.pop(name).close()
            for job in running:
                if job.name not in self.bars:
                    self.bars[job.name] = tqdm(total=0, bar_format="{desc}", position=len(self.bars))
                self.bars[job.name].set_description_str(f"  {job.name}: {job.progress()}")
        elif running and time.monotonic() - self.last > self.every:
            self.last = time.monotonic()
            for job in running:
                self.log(f"  {job.name}: {job.progress()}")

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()


def _unfinished(jobs: list[TrainingJob], log) -> list[TrainingJob]:
    """The jobs left to train: finished ones are reused, a run of another config is moved aside."""
    pending = []
    for job in jobs:
        if job.finished():
            log(f"  {job.name}: finished earlier, reusing {job.output_dir}")
            continue
        stale = job.set_aside_if_stale()
        if stale is not None:
            log(f"  {job.name}: {job.output_dir} was trained with another config; moved to {stale}")
        _ = job.requested_config  # pinned now: a config edited while the job runs does not fail it
        pending.append(job)
    return pending


def _one_at_a_time(jobs: list[TrainingJob]) -> Iterator[tuple | None]:
    """Without Ray: each training in turn as a child of this process; the events of ``run_on_ray``."""
    for job in jobs:
        proc = launch(job)
        try:
            yield job, "started", resumes(proc)
            while proc.poll() is None:
                time.sleep(2.0)
                yield None
        finally:
            stop(proc)
        yield job, "ended", proc.returncode


def _ray_installed() -> bool:
    return importlib.util.find_spec("ray") is not None


@contextlib.contextmanager
def _events(jobs: list[TrainingJob], parallel: int | None, address: str | None, log):
    """The jobs' events as Ray tasks (Ray is up for the whole ``with``), or one training at a time
    when the ``ray`` package is missing."""
    if _ray_installed():
        from daof.experiments.ray_jobs import ray_session, run_on_ray

        with ray_session(address, parallel):
            yield run_on_ray(jobs)
        return
    if address is not None:
        raise RuntimeError(f'ray.address={address} needs Ray, which is not installed: pip install -e ".[ray]"')
    log('  Ray is not installed: the trainings run one at a time (pip install -e ".[ray]" runs them in parallel)')
    yield _one_at_a_time(jobs)


@contextlib.contextmanager
def _sigterm_noted():
    """A list that SIGTERM appends to while the ``with`` lasts (handlers live in the main thread only).

    The handler raises nothing: an exception raised inside Ray's wait becomes Ray's own exit.
    """
    received = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    previous = signal.signal(signal.SIGTERM, lambda *_: received.append(True))
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)


def _ended(job: TrainingJob, exit_code: int | str, log) -> bool:
    """Log how a job ended (``exit_code``: its exit code, or why its task failed); whether it succeeded."""
    if exit_code == 0 and job.finished():
        log(f"  {job.name}: done ({job.summary().get('wall_s')} s)")
        return True
    if exit_code == 0:
        why = f"exit 0, but no {job.output}"
    else:
        why = f"exit {exit_code}" if isinstance(exit_code, int) else exit_code
    log(f"  {job.name}: FAILED ({why}); see {job.log_path}")
    return False


def run_jobs(
    jobs: list[TrainingJob],
    parallel: int | None = None,
    address: str | None = None,
    log=print,
    status_every: float = 300.0,
) -> None:
    """Train the unfinished jobs, as Ray tasks where Ray is installed (module docstring); raise if any fails.

    ``parallel``: CPUs of the local Ray, i.e. trainings at once (None: every core); ``address``: a Ray
    cluster's instead (``auto``, ``host:6379``; not Ray Client's ``ray://``, which has no streaming
    tasks). Progress: one live line per running job on a terminal, else a line per job every
    ``status_every`` seconds. Whatever ends this function early (an error, Ctrl-C, SIGTERM) stops
    the trainings it started.
    """
    pending = _unfinished(jobs, log)
    if not pending:
        return
    running: dict[str, TrainingJob] = {}
    failed: list[str] = []
    status = _Status(log, status_every)
    # SIGTERM's handler is set after Ray starts: Ray's own would end this process without a cleanup
    with _events(pending, parallel, address, log) as events, _sigterm_noted() as sigterm, contextlib.closing(events):
        try:
            for event in events:
                if sigterm:
                    sys.exit("stopped by SIGTERM")
                if event is not None:
                    job, what, detail = event
                    if what == "started":
                        running[job.name] = job
                        resuming = " (resuming)" if detail else ""
                        log(f"  {job.name}: {job.doing}{resuming}, log {job.log_path}")
                    else:
                        running.pop(job.name, None)
                        if not _ended(job, detail, log):
                            failed.append(job.name)
                status.show(list(running.values()))
        finally:
            status.close()
    if failed:
        raise RuntimeError(f"{pending[0].doing} failed for {failed}; rerun the same command to resume")
