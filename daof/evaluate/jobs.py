"""Run training recipes as parallel subprocesses, reusing finished runs and resuming broken ones.

A job is one recipe invocation with Hydra overrides and its own output directory. A job whose
``summary.json`` records at least the requested number of frames is finished and reused; one
with a ``checkpoint.pt`` is resumed from it; anything else starts fresh. Either only if the
directory's ``run_config.json`` (the resolved config its trainer ran with) equals the config the
job asks for now, apart from ``resume`` and the frame budget; a directory from another config is
moved aside to ``<dir>.stale-<n>`` and the job starts fresh. Progress: the latest progress-bar
line of every running job is printed periodically.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

from daof.train.checkpoint import RUN_CONFIG

__all__ = ["TrainingJob", "run_jobs"]


def _comparable(config: dict) -> dict:
    """A run's config without what may differ between a run and the job that reuses it."""
    config = {k: v for k, v in config.items() if k != "resume"}
    if isinstance(config.get("collector"), dict):
        config["collector"] = {k: v for k, v in config["collector"].items() if k != "total_frames"}
    return config


@dataclass
class TrainingJob:
    """One training run: ``python script overrides... output_dir=out``."""

    name: str
    script: Path
    output_dir: Path
    total_frames: int
    overrides: list[str] = field(default_factory=list)

    @property
    def summary_path(self) -> Path:
        return self.output_dir / "summary.json"

    def finished(self) -> bool:
        if not self.summary_path.is_file() or not (self.output_dir / "best.pt").is_file():
            return False
        done = json.loads(self.summary_path.read_text()).get("frames", 0) >= self.total_frames
        return done and self.config_matches()

    @functools.cached_property
    def requested_config(self) -> dict:
        """The resolved config this job's command would train with (the recipe's ``--cfg job``; asked once)."""
        cmd = [*self.command(with_resume=False), "--cfg", "job", "--resolve"]
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode != 0:
            cause = (out.stderr.strip() or out.stdout.strip()).replace("\n", " | ")[-300:]
            raise RuntimeError(f"{self.name}: {self.script} rejects its overrides: {cause}")
        return OmegaConf.to_container(OmegaConf.create(out.stdout))

    def config_matches(self) -> bool:
        """Whether the run in ``output_dir`` was started with the config this job asks for."""
        path = self.output_dir / RUN_CONFIG
        if not path.is_file():
            return False
        return _comparable(json.loads(path.read_text())) == _comparable(self.requested_config)

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
        cmd = [sys.executable, str(self.script), *self.overrides]
        cmd += [f"collector.total_frames={self.total_frames}", f"output_dir={self.output_dir}"]
        checkpoint = self.output_dir / "checkpoint.pt"
        if with_resume and checkpoint.is_file():
            cmd.append(f"resume={checkpoint}")
        return cmd

    def summary(self) -> dict:
        return json.loads(self.summary_path.read_text())


def _last_progress(log: Path) -> str:
    try:
        tail = log.read_bytes()[-4000:].decode(errors="replace")
    except OSError:
        return ""
    pieces = [p.strip() for p in tail.replace("\r", "\n").split("\n") if p.strip()]
    bars = [p for p in pieces if "fr/s" in p or "fr]" in p or "%|" in p]
    return (bars or pieces or [""])[-1][:160]


def run_jobs(jobs: list[TrainingJob], parallel: int = 2, log=print, status_every: float = 60.0) -> None:
    """Run the unfinished jobs, ``parallel`` at a time; raise if any of them fails."""
    pending = []
    for job in jobs:
        if job.finished():
            log(f"  {job.name}: finished earlier, reusing {job.output_dir}")
            continue
        stale = job.set_aside_if_stale()
        if stale is not None:
            log(f"  {job.name}: {job.output_dir} was trained with another config; moved to {stale}")
        _ = job.requested_config  # pinned now: a recipe config edited while the job runs does not fail it
        pending.append(job)
    running: list[tuple[TrainingJob, subprocess.Popen, Path, object]] = []
    failed = []
    last_status = time.monotonic()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    while pending or running:
        while pending and len(running) < parallel:
            job = pending.pop(0)
            job.output_dir.mkdir(parents=True, exist_ok=True)
            log_path = job.output_dir / "train.log"
            fh = log_path.open("ab")
            resumed = " (resuming)" if any("resume=" in c for c in job.command()) else ""
            log(f"  {job.name}: training{resumed}, log {log_path}")
            proc = subprocess.Popen(job.command(), stdout=fh, stderr=subprocess.STDOUT, env=env)
            running.append((job, proc, log_path, fh))
        time.sleep(2.0)
        for entry in list(running):
            job, proc, log_path, fh = entry
            if proc.poll() is None:
                continue
            fh.close()
            running.remove(entry)
            if proc.returncode == 0 and job.finished():
                log(f"  {job.name}: done ({job.summary().get('wall_s')} s)")
            else:
                failed.append(job.name)
                why = f"exit {proc.returncode}" if proc.returncode else "exit 0, but its summary or best.pt is missing"
                log(f"  {job.name}: FAILED ({why}); see {log_path}")
        if running and time.monotonic() - last_status > status_every:
            last_status = time.monotonic()
            for job, _, log_path, _ in running:
                log(f"  {job.name}: {_last_progress(log_path)}")
    if failed:
        raise RuntimeError(f"training failed for {failed}; rerun the same command to resume")
