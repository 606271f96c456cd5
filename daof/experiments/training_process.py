"""A training's child process: started with its output in ``train.log``, dying with whatever started it.

A training job runs as ``job.command()`` in a child process, started by a Ray task or, without
Ray, by the experiment itself. On Linux the child asks the kernel for SIGKILL when its parent dies
(``PR_SET_PDEATHSIG``), so a training never outlives the process that started it, however that
process ends (a driver killed with SIGKILL too); Ray also kills the children of a worker it kills.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys

__all__ = ["launch", "resumes", "stop"]

PR_SET_PDEATHSIG = 1  # linux/prctl.h
_PRCTL = ctypes.CDLL(None, use_errno=True).prctl if sys.platform == "linux" else None


def _die_with_parent() -> None:
    """Runs in the child between fork and exec: SIGKILL it when its parent dies (the setting survives exec)."""
    _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)


def launch(job) -> subprocess.Popen:
    """Start ``job``'s process (a ``TrainingJob`` or ``HeadJob``) with its output appended to ``job.log_path``."""
    job.output_dir.mkdir(parents=True, exist_ok=True)
    with job.log_path.open("ab") as log:  # the child keeps its own copy of the file
        return subprocess.Popen(
            job.command(),
            stdout=log,
            stderr=subprocess.STDOUT,
            env=job.environment(dict(os.environ)),
            preexec_fn=_die_with_parent if _PRCTL is not None else None,
        )


def resumes(proc: subprocess.Popen) -> bool:
    """Whether the training resumes from a checkpoint (its command names one)."""
    return any(str(arg).startswith("resume=") for arg in proc.args)


def stop(proc: subprocess.Popen) -> None:
    """Terminate the training if it still runs (its last checkpoint stays), killing it after 30 s."""
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
