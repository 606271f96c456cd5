"""Training jobs as Ray tasks: a local Ray by default, a cluster by address (needs ``pip install -e ".[ray]"``).

Each job is one task of one CPU (the training runs one torch thread) that starts the training as
its child process (``daof.experiments.training_process``) in the driver's working directory and
reports when it started and how it ended. A cluster must see the code and the run directories at
the same paths as the driver (a shared file system). Closing ``run_on_ray`` early (an error,
Ctrl-C, SIGTERM in the driver) cancels every task with force: Ray kills its worker, and the
training dies with it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

import ray

from daof.experiments.training_process import launch, resumes, stop

__all__ = ["ray_session", "run_on_ray", "start_ray"]


def _train(job, cwd: str):
    """The task: ``("started", resumes)`` once the training runs, then ``("ended", its exit code)``."""
    os.chdir(cwd)  # the job's relative paths are the driver's
    proc = launch(job)
    try:
        yield "started", resumes(proc)
        yield "ended", proc.wait()
    finally:  # the task stopped in the worker (a cancel without force); a forced one kills the worker
        stop(proc)


#: says, at every start of a local Ray, that it uses token authentication (Ray's default)
_AUTH_LOGGER = "ray._private.authentication.authentication_token_setup"
#: Ray's environment variable for its workers' niceness (``ray._private.ray_constants``)
WORKER_NICENESS = "RAY_worker_niceness"
_task = ray.remote(num_cpus=1, max_retries=0, num_returns="streaming")(_train)


def start_ray(address: str | None = None, num_cpus: int | None = None) -> None:
    """Connect to the cluster at ``address``, or start a local Ray of ``num_cpus`` CPUs (null: every core).

    Quiet: no dashboard, no banner, the workers' output not copied to this terminal (a training's
    output is in its ``train.log``), and no warning that a local Ray uses token authentication
    (Ray's default for a new local cluster; its token is ``~/.ray/auth_token``). A local Ray's
    workers run at the driver's priority, as the trainings of the one-at-a-time path do: Ray's
    default, nice 15, lets any other process on the machine take the cores from them (measured
    2026-12-07: 4 % of a core each beside two ordinary trainings). ``RAY_worker_niceness`` set in
    the environment still wins; a cluster's workers keep the cluster's setting.
    """
    logging.getLogger(_AUTH_LOGGER).setLevel(logging.ERROR)
    if address is None:
        os.environ.setdefault(WORKER_NICENESS, "0")
    ray.init(
        address=address,
        num_cpus=num_cpus if address is None else None,
        include_dashboard=False,
        log_to_driver=False,
        logging_level=logging.WARNING,
    )


@contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None):
    """Ray as this process has it (initialised already, e.g. by the tests), else started here and shut down after."""
    if ray.is_initialized():
        yield
        return
    start_ray(address, num_cpus)
    try:
        yield
    finally:
        ray.shutdown()


def _why(error: ray.exceptions.RayError) -> str:
    """One line: the task's own exception, or what happened to it (its worker died, it was cancelled)."""
    lines = str(error).strip().splitlines()
    return lines[-1] if lines else type(error).__name__


def run_on_ray(jobs: list) -> Iterator[tuple | None]:
    """Run ``jobs`` as tasks of the Ray this process is connected to (``ray_session``); yield ``(job,
    "started", resumes)`` and ``(job, "ended", exit code or why it failed)`` as they happen, and ``None``
    every 2 s in between. Closed early, it cancels the tasks still running with force: Ray kills their
    workers (within a second on a local Ray), and each training with its worker."""
    cwd = os.getcwd()
    tasks = {_task.remote(job, cwd): job for job in jobs}
    try:
        while tasks:
            ready, _ = ray.wait(list(tasks), num_returns=1, timeout=2.0)
            for task in ready:
                try:
                    what, detail = ray.get(next(task))
                except ray.exceptions.RayError as error:
                    what, detail = "ended", _why(error)
                yield (tasks[task] if what == "started" else tasks.pop(task)), what, detail
            yield None
    finally:
        for task in tasks:
            ray.cancel(task, force=True)
