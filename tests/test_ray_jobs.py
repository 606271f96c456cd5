"""An experiment's trainings as Ray tasks (``daof.experiments.ray_jobs``): at once, reused, failures named,
stopped with the driver; one at a time without Ray.

Stand-in trainers (a job's ``launcher``) keep these fast; the tiny profile runs end to end through
Ray in test_evaluate.py (``test_experiment_tiny_profile_writes_a_complete_report``).
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

import daof.experiments.jobs as jobs
from daof.experiments.jobs import TrainingJob, run_jobs

#: a stand-in trainer: ``<mode> <overrides...>``; "together" finishes only once every job of the
#: test has started, "alone" at once, "fail" exits 3, "sleep" sleeps two minutes
STAND_IN = """
import json, os, pathlib, sys, time
mode = sys.argv[1]
out = pathlib.Path(next(a for a in sys.argv if a.startswith("output_dir=")).split("=", 1)[1])
(out / "pid").write_text(str(os.getpid()))
if mode == "fail":
    print("out of memory")
    sys.exit(3)
if mode == "sleep":
    time.sleep(120)
deadline = time.monotonic() + 60
while mode == "together" and len(list(out.parent.glob("*/pid"))) < 2:
    if time.monotonic() > deadline:
        sys.exit("ran alone")
    time.sleep(0.1)
(out / "run_config.json").write_text((out.parent / f"{out.name}.json").read_text())
(out / "summary.json").write_text(json.dumps({"frames": 100, "wall_s": 1.0}))
import torch
torch.save({}, out / "best.pt")
"""


def stand_in_jobs(tmp_path, **modes) -> list[TrainingJob]:
    """One job per name -> mode, in ``tmp_path/runs/<name>``, trained by the stand-in in that mode."""
    script = tmp_path / "stand_in.py"
    script.write_text(STAND_IN)
    made = []
    for name, mode in modes.items():
        job = TrainingJob(name, tmp_path / "runs" / name, 100, ["filter=slf"], [sys.executable, str(script), mode])
        (tmp_path / "runs").mkdir(exist_ok=True)
        (tmp_path / "runs" / f"{name}.json").write_text(json.dumps(job.requested_config))
        made.append(job)
    return made


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not reaped by its new parent, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_jobs_train_at_once_as_ray_tasks_and_finished_ones_are_reused(local_ray, tmp_path):
    together = stand_in_jobs(tmp_path, A="together", B="together")  # each waits until the other has started
    lines = []
    run_jobs(together, log=lines.append)
    for name in "AB":
        assert f"  {name}: training, log {tmp_path / 'runs' / name / 'train.log'}" in lines, lines
        assert f"  {name}: done (1.0 s)" in lines, lines
    lines.clear()
    run_jobs(together, log=lines.append)
    assert lines == [f"  {name}: finished earlier, reusing {tmp_path / 'runs' / name}" for name in "AB"]


def test_a_failing_job_is_named_with_its_log_or_its_task_error(local_ray, tmp_path):
    crashing, missing = stand_in_jobs(tmp_path, A="fail", B="alone")
    missing.launcher = [str(tmp_path / "no-such-trainer")]
    lines = []
    with pytest.raises(RuntimeError, match=r"^training failed for \['(A', 'B|B', 'A)'\]; rerun the same command"):
        run_jobs([crashing, missing], log=lines.append)
    assert f"  A: FAILED (exit 3); see {tmp_path / 'runs' / 'A' / 'train.log'}" in lines, lines
    assert "out of memory" in (tmp_path / "runs" / "A" / "train.log").read_text()
    [failed] = [line for line in lines if line.startswith("  B: FAILED")]
    assert "FileNotFoundError" in failed and "no-such-trainer" in failed, failed


def test_an_error_in_the_driver_cancels_its_tasks_and_no_training_outlives_them(local_ray, tmp_path):
    sleepers = stand_in_jobs(tmp_path, A="sleep", B="sleep")
    pids = [job.output_dir / "pid" for job in sleepers]

    class Stop(Exception):
        pass

    def log(line: str) -> None:  # the driver fails once both trainings run
        if line.startswith("  B: training") or line.startswith("  A: training"):
            started.append(line)
        deadline = time.monotonic() + 60
        while len(started) == 2 and not all(p.is_file() and p.read_text() for p in pids):
            assert time.monotonic() < deadline
            time.sleep(0.1)
        if len(started) == 2:
            assert all(alive(int(p.read_text())) for p in pids)
            raise Stop

    started = []
    begin = time.monotonic()
    with pytest.raises(Stop):
        run_jobs(sleepers, log=log)
    children = [int(p.read_text()) for p in pids]
    deadline = time.monotonic() + 10
    while any(alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(pid) for pid in children), "a training outlived its cancelled task"
    assert time.monotonic() - begin < 60


def test_without_ray_the_jobs_run_one_at_a_time_and_say_so(tmp_path, monkeypatch):
    monkeypatch.setattr(jobs, "_ray_installed", lambda: False)
    job, other = stand_in_jobs(tmp_path, A="alone", B="alone")
    lines = []
    run_jobs([job], parallel=2, log=lines.append)
    note = '  Ray is not installed: the trainings run one at a time (pip install -e ".[ray]" runs them in parallel)'
    assert lines == [note, f"  A: training, log {job.output_dir / 'train.log'}", "  A: done (1.0 s)"]
    with pytest.raises(
        RuntimeError, match=r'^ray.address=auto needs Ray, which is not installed: pip install -e ".\[ray'
    ):
        run_jobs([other], address="auto", log=lines.append)


def test_a_training_dies_with_the_process_that_launched_it_even_by_sigkill(tmp_path):
    """Without Ray the driver launches the trainings itself; killed outright, it takes them along."""
    [job] = stand_in_jobs(tmp_path, A="sleep")
    driver = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path\n"
        "from daof.experiments.jobs import TrainingJob\n"
        "from daof.experiments.training_process import launch\n"
        f"launch(TrainingJob('A', Path({str(job.output_dir)!r}), 100, [], {job.launcher!r}))\n"
        "time.sleep(120)\n"
    )])  # fmt: skip
    pid = job.output_dir / "pid"
    deadline = time.monotonic() + 60
    while not (pid.is_file() and pid.read_text()):
        assert driver.poll() is None and time.monotonic() < deadline
        time.sleep(0.1)
    child = int(pid.read_text())
    try:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        deadline = time.monotonic() + 10
        while alive(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(child), "the training outlived the process that launched it"
    finally:
        if alive(child):
            os.kill(child, signal.SIGKILL)


def test_a_trainer_in_a_ray_task_takes_its_run_directory_lock(local_ray, tmp_path):
    """A run directory another training holds (here: this process) fails the job; nothing trains in it."""
    from test_reliability import TINY_SLF

    from daof.train.base import RUN_CONFIG
    from daof.train.lock import lock_run_directory

    job = TrainingJob("SLF", tmp_path / "slf", 400, TINY_SLF)
    job.output_dir.mkdir()
    (job.output_dir / RUN_CONFIG).write_text(json.dumps(job.requested_config))  # a run of this config: not stale
    held = lock_run_directory(job.output_dir)
    try:
        with pytest.raises(RuntimeError, match=r"^training failed for \['SLF'\]"):
            run_jobs([job], log=lambda _: None)
    finally:
        held.close()
    log = (job.output_dir / "train.log").read_text()
    assert f"is in use by another training (pid {os.getpid()})" in log, log
    assert not (job.output_dir / "summary.json").exists()


def test_a_local_rays_trainings_run_at_the_drivers_priority(local_ray):
    """Ray's default nice 15 would let any other process take the cores from the trainings."""
    import ray

    if os.nice(0) != 0:
        pytest.skip("the tests themselves run niced")
    niceness = ray.remote(num_cpus=1)(lambda: os.nice(0))
    assert ray.get(niceness.remote()) == 0
