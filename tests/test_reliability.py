"""Faults of docs/reliability.md: wild measurements are flagged as diverged, the PF's weights survive a
1e9 measurement, learned filters count their bound hits and take float64 data, bad parameters and
seeds are one line."""

import sys
from pathlib import Path

import pytest
import torch
from daof.envs import make_system

from daof.evaluate.study import FilterResult, _add_oracle_metrics
from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter

sys.path.insert(0, str(Path(__file__).parent))
from test_learned_filters import FORMS, small_form  # noqa: E402


@pytest.fixture(scope="module")
def veh():
    return make_system("veh2dof")


@pytest.fixture(scope="module")
def veh_data(veh):
    return veh.simulate(4, 100, seed=0)


def glitch(data, value, channel, run=0, step=10):
    """``data`` with one measurement replaced by ``value``."""
    out = data.clone()
    out["measurement"][run, step, channel] = value
    return out


# ----------------------------------------------------------------- divergence flags
@pytest.mark.parametrize("make", [EKF, UKF], ids=["EKF", "UKF"])
def test_a_lateral_acceleration_glitch_is_flagged_as_a_diverged_run(make, veh, veh_data):
    """One 1e4 m/s² a_y sample leaves the EKF/UKF tens of rad off (finite): that run is counted."""
    filt = make(veh)
    clean = filt.run(veh_data)
    assert filt.stats["diverged"] == 0
    estimates = filt.run(glitch(veh_data, 1e4, channel=0))
    assert torch.isfinite(estimates).all()  # finite: a non-finite check alone would not see it
    assert (estimates[0] - clean[0]).abs().max() > 1.0
    assert filt.stats["diverged"] == 1
    assert veh.diverged_runs(estimates).tolist() == [True, False, False, False]


def test_an_outlier_into_the_kalman_filter_is_flagged():
    lin = make_system("linear")
    data = lin.simulate(3, 60, seed=1)
    kf = KalmanFilter(lin)
    estimates = kf.run(glitch(data, 1e6, channel=0, run=1))
    assert torch.isfinite(estimates).all() and estimates.abs().max() > 1e4
    assert kf.stats["diverged"] == 1 and lin.diverged_runs(estimates).tolist() == [False, True, False]


def test_the_study_flags_a_run_far_above_the_reference_on_that_run():
    """10x the reference's RMSE on the same run, not its pooled RMSE (which a hard run dominates)."""
    rows = {
        "PF-oracle": FilterResult(
            rmse=[0.07, 0.07], per_run_rmse=[[0.01, 0.01], [0.1, 0.1]], cost_ms=1, threads=1, throughput_per_s=1
        ),
        "F": FilterResult(
            rmse=[0.1, 0.1], per_run_rmse=[[0.2, 0.01], [0.1, 0.1]], cost_ms=1, threads=1, throughput_per_s=1
        ),
    }
    _add_oracle_metrics(rows)
    assert (rows["F"].diverged, rows["F"].diverged_runs) == (1, [0])  # 0.2 > 10 x 0.01 on run 0
    assert rows["PF-oracle"].diverged == 0


def test_the_study_flags_an_estimate_outside_the_plausible_range(veh):
    """An RMSE below 10x the reference's is still diverged when an estimate leaves the limits."""
    estimates = torch.zeros(2, 5, 2)
    low, high = veh.divergence_limits()  # the output range widened by its width on each side
    assert torch.allclose(high - low, 3 * (veh.state_high - veh.state_low).double())
    estimates[1, 3, 0] = float(high[0]) * 1.05  # just past β's limit
    rows = {
        name: FilterResult(
            rmse=[1.0, 1.0], per_run_rmse=[[1.0, 1.0], [1.0, 1.0]], cost_ms=1, threads=1, throughput_per_s=1
        )
        for name in ("PF-oracle", "F")
    }
    _add_oracle_metrics(rows, estimates={"PF-oracle": torch.zeros(2, 5, 2), "F": estimates}, system=veh)
    assert (rows["F"].diverged, rows["F"].diverged_runs) == (1, [1]) and rows["PF-oracle"].diverged == 0


def test_a_1e9_measurement_keeps_the_particle_filters_weights_normalised(veh, veh_data):
    """In float32, log-weights of ~-1e10 lost their normalisation (weights summing to k > 1)."""
    pf = ParticleFilter(veh, num_particles=500)
    estimates = pf.run(glitch(veh_data, 1e9, channel=0))
    assert torch.isfinite(estimates).all()
    assert (estimates >= veh.state_low).all() and (estimates <= veh.state_high).all()
    assert (estimates - veh_data["state"]).abs().amax((0, 1)).tolist() < [0.2, 0.5]
    assert pf.stats["diverged"] == 0


# ----------------------------------------------------------------- learned filters: bounds and dtypes
@pytest.mark.parametrize("form", list(FORMS))
def test_learned_filters_count_the_estimates_at_their_bounds(form, veh_data):
    filt = small_form(form)
    data = veh_data[:2, :40]
    estimates = filt.run(data)
    assert filt.stats["saturated"] == filt.saturation(estimates).tolist()
    assert len(filt.stats["saturated"]) == 2
    with torch.no_grad():  # loc ≫ 0 (and an update bound wider than the range): pushed to the upper end
        filt.policy.mlp[-1].bias.fill_(50.0)
        if filt.acts_by_update:
            filt.correction_scale.fill_(100.0)
    pushed = filt.run(data)
    at_high = torch.isclose(pushed, filt.state_high.expand_as(pushed), rtol=0, atol=1e-6)
    assert at_high.any()
    assert filt.stats["saturated"] == pytest.approx(at_high.reshape(-1, 2).double().mean(0).tolist())
    assert max(filt.stats["saturated"]) > 0


def test_saturation_is_the_share_at_either_end():
    filt = small_form("DAOF-v1")
    low, high = filt.state_low, filt.state_high
    est = torch.stack([low, high, (low + high) / 2, low + 1e-3 * (high - low)]).unsqueeze(0)  # [1, 4, 2]
    assert filt.saturation(est).tolist() == [0.5, 0.5]


@pytest.mark.parametrize("form", list(FORMS))
def test_learned_filters_take_float64_data(form, veh_data):
    """Cast at the entry; the estimates are those of the float32 data, in the network's dtype."""
    filt = small_form(form)
    data = veh_data[:2, :30]
    expected = filt.run(data)
    wide = data.clone().apply(lambda v: v.double())
    assert wide["measurement"].dtype == torch.float64
    got = filt.run(wide)
    assert got.dtype == torch.float32 and torch.equal(got, expected)
    assert torch.equal(filt.run_streaming(wide), filt.run_streaming(data))
    too_big = glitch(wide, 1e300, channel=1)
    with pytest.raises(ValueError, match=r"'measurement' at \[run, step, channel\] = \[0, 10, 1\] is 1e\+300") as e:
        filt.run(too_big)
    assert "\n" not in str(e.value)


class Glitched:
    """A filter that sees one wild lateral acceleration in run 0 (what a sensor glitch would feed it)."""

    def __init__(self, filt):
        self.filt = filt

    def run(self, data):
        return self.filt.run(glitch(data, 1e4, channel=0))

    run_streaming = run

    @property
    def stats(self):
        return self.filt.stats


def test_the_report_shows_diverged_runs_and_bound_hits(veh, tmp_path):
    import csv
    import json

    from daof.evaluate.report import write_report
    from daof.evaluate.study import run_study

    learned = small_form("DAOF-v2")
    filters = {"PF-oracle": ParticleFilter(veh, 300), "EKF": Glitched(EKF(veh)), "DAOF-v2": learned}
    study = run_study(veh, filters, runs=3, steps=40, seed=0, measure_cost=False, log=lambda *_: None)
    assert (study.results["EKF"].diverged, study.results["EKF"].diverged_runs) == (1, [0])
    report = write_report(study, tmp_path, title="t", profile="tiny")
    results = json.loads((tmp_path / "results.json").read_text())["filters"]
    assert results["EKF"]["diverged_runs"] == [0] and results["EKF"]["saturated"] is None
    assert results["DAOF-v2"]["saturated"] == learned.stats["saturated"]
    rows = {row["filter"]: row for row in csv.DictReader((tmp_path / "results.csv").open())}
    assert rows["DAOF-v2"]["saturated_beta"] != "" and rows["EKF"]["saturated_beta"] == ""
    text = report.read_text()
    assert "| at a bound (beta / yaw_rate) |" in text
    ekf_row = next(line for line in text.splitlines() if line.startswith("| EKF |"))
    assert ekf_row.endswith("| 1 | 0 | – |")
    low, high = veh.divergence_limits()
    limits = f"beta [{low[0]:.3g}, {high[0]:.3g}] rad, yaw_rate [{low[1]:.3g}, {high[1]:.3g}] rad/s"
    assert f"widened again by its width on each side ({limits})" in " ".join(text.split())
    assert "above 10x PF-oracle's RMSE on the same run" in text


# ----------------------------------------------------------------- veh2dof and linear parameters
@pytest.mark.parametrize(
    "system, override, message",
    [
        ("veh2dof", {"mu": -0.9}, "mu must be > 0, got -0.9"),
        ("veh2dof", {"mu": float("nan")}, "mu must be finite, got nan"),
        ("veh2dof", {"m": -1500.0}, "m must be > 0"),
        ("veh2dof", {"dt": 0.0}, "dt must be > 0"),
        ("veh2dof", {"vx": 0.0}, "vx must be > 0"),
        ("veh2dof", {"prior_std": (0.0, 0.0)}, "prior_std must be > 0"),
        ("veh2dof", {"mixture_weights": (1.2, -0.2)}, "mixture_weights must be non-negative weights summing to 1"),
        ("veh2dof", {"mismatch_mu": (1.0, 0.7)}, r"mismatch_mu must be a range \(low, high\) with low <= high"),
        ("veh2dof", {"outlier_prob": 1.5}, r"outlier_prob must be in \[0, 1\]"),
        ("linear", {"omega": -1.0}, "omega must be > 0"),
        ("linear", {"dt": -0.05}, "dt must be > 0"),
        ("linear", {"process_std": (0.01, float("inf"))}, "process_std must be finite"),
        ("linear", {"zeta": -0.1}, "zeta must be >= 0"),
        ("linear", {"force_period_s": (6.0, 2.0)}, "force_period_s must be a range"),
    ],
)
def test_physical_parameters_are_checked_in_one_line(system, override, message):
    with pytest.raises(ValueError, match=message) as error:
        make_system(system, **override)
    assert "\n" not in str(error.value)


def test_training_with_a_bad_physical_override_exits_with_one_line_before_any_work(tmp_path):
    """``python -m daof.train overrides.mu=-0.9`` trained and exited 0."""
    import subprocess

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "daof.train", "filter=slf", "overrides.mu=-0.9", f"output_dir={out}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert done.stderr.strip().splitlines() == ["error: mu must be > 0, got -0.9"]
    assert not out.exists()


# ----------------------------------------------------------------- veh14dof parameters
@pytest.mark.parametrize(
    "override, message",
    [
        ({"m_s": -965.7}, "m_s must be > 0, got -965.7"),
        ({"m_uf": 0.0}, "m_uf must be > 0"),
        ({"dt": 0.0}, "dt must be > 0"),
        ({"dt": -0.02}, "dt must be > 0"),
        ({"h": 0.0}, "h must be > 0"),
        ({"I_zz": float("nan")}, "I_zz must be finite"),
        ({"k_t": float("inf")}, "k_t must be finite"),
        ({"c_sf": -1.0}, "c_sf must be >= 0"),
        ({"gnss_pos_std": -1.5}, "gnss_pos_std must be >= 0"),
        ({"dist_weights": (1.2, -0.2)}, "dist_weights must be non-negative weights summing to 1"),
        ({"dist_weights": (0.5, 0.4)}, "dist_weights must be non-negative weights summing to 1"),
        ({"v0_kmh": (80.0, 60.0)}, r"v0_kmh must be a range \(low, high\) with low <= high"),
        ({"brake_front": 1.5}, r"brake_front must be in \[0, 1\]"),
        ({"gnss_period_steps": 0}, "gnss_period_steps must be > 0"),
        ({"gnss_period_steps": 2.5}, "gnss_period_steps must be a whole number"),
        ({"a_cmd_min": 2.0}, "a_cmd_min must be <= a_cmd_max"),
        ({"spin_speeds_kmh": (80.0, 60.0, 70.0)}, "spin_speeds_kmh must be >= 2 increasing speeds"),
        ({"mu_scale": "high"}, "mu_scale must be a number"),
    ],
)
def test_veh14dof_parameters_are_checked_up_front_in_one_line(override, message, monkeypatch):
    from daof.envs.vehicle14dof import system as veh14

    def no_simulation(self):
        raise AssertionError("the prior was simulated before the parameters were checked")

    monkeypatch.setattr(veh14.Vehicle14DOF, "_derive_prior", no_simulation)
    with pytest.raises(ValueError, match=message) as error:
        make_system("veh14dof", **override)
    assert "\n" not in str(error.value)


# ----------------------------------------------------------------- seeds
def seed_users(tmp_path):
    from daof.envs import make_env
    from daof.envs.recorded import RecordedSystem, cache_key

    from daof.evaluate.dropout import Dropout
    from daof.evaluate.study import run_study

    lin = make_system("linear")
    data = lin.simulate(2, 5, seed=0)
    return {
        "simulate": lambda seed: lin.simulate(2, 5, seed),
        "run_study": lambda seed: run_study(lin, {}, 2, 5, seed, measure_cost=False, log=lambda *_: None),
        "ParticleFilter": lambda seed: ParticleFilter(lin, 10, seed=seed),
        "make_env": lambda seed: make_env("linear", batch_size=2, window=2, seed=seed),
        "Dropout": lambda seed: Dropout(p=0.1, blackout=None, seed=seed).apply(data, lin),
        "RecordedSystem": lambda seed: RecordedSystem(lin, runs=2, steps=5, seed=seed),
        "cache_key": lambda seed: cache_key(lin, 2, 5, seed),
        "veh2dof simulate": lambda seed: make_system("veh2dof").simulate(2, 5, seed),
    }


@pytest.mark.parametrize(
    "user", ["simulate", "run_study", "ParticleFilter", "make_env", "Dropout", "RecordedSystem", "cache_key",
             "veh2dof simulate"]
)  # fmt: skip
def test_a_fractional_seed_is_refused_not_truncated(user, tmp_path):
    call = seed_users(tmp_path)[user]
    for bad in (1.9, "1", True):
        with pytest.raises(ValueError, match=r"seed must be an integer, got") as error:
            call(bad)
        assert "\n" not in str(error.value)
    call(2)  # an integer seed works
    call(2.0)  # and an integral float loses nothing


# ----------------------------------------------------------------- files and directories
TINY_SLF = [
    "filter=slf",
    "window=4",
    "network.num_cells=16",
    "validation.runs=2",
    "validation.steps=30",
    "validation.every_frames=200",
    "collector.env_batch=4",
    "collector.episode_steps=50",
    "checkpoint.every_frames=200",
    "logger.backend=csv",
]


def test_a_truncated_best_pt_in_a_finished_job_is_written_again_from_its_checkpoint(local_ray, tmp_path):
    """It used to count as finished and end every rerun in the study's load of best.pt."""
    from daof.experiments.jobs import TrainingJob, run_jobs
    from daof.filters.learned import load_filter

    job = TrainingJob("SLF", tmp_path / "slf", 400, TINY_SLF)
    run_jobs([job], parallel=1, log=lambda _: None)
    best = job.output_dir / "best.pt"
    weights = load_filter(best).state_dict()
    best.write_bytes(best.read_bytes()[:100])  # a disk that filled while it was written
    assert not job.finished()
    lines = []
    run_jobs([job], parallel=1, log=lines.append)
    assert any("SLF: training (resuming)" in line for line in lines), lines
    assert job.finished() and job.summary()["frames"] == 400
    again = load_filter(best).state_dict()
    assert all(torch.equal(weights[k], again[k]) for k in weights)


def test_an_unwritable_run_or_output_directory_is_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    from daof.experiments.experiment import main as experiment_main
    from daof.train.__main__ import main as train_main

    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(SystemExit, match=f"^error: cannot write the run directory {blocker}/run: Not a directory$"):
        train_main([*TINY_SLF, f"output_dir={blocker}/run"])
    with pytest.raises(SystemExit, match=f"^cannot write the output directory {blocker}/x: Not a directory$"):
        experiment_main(["profile=tiny", f"output_root={blocker}/x"], experiment="veh2dof")

    import errno
    import tempfile

    def read_only(*args, **kwargs):  # what a read-only file system answers (root writes through chmod)
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    with pytest.raises(SystemExit, match="^error: cannot write the run directory .*: Read-only file system$"):
        train_main([*TINY_SLF, f"output_dir={tmp_path}/run"])
    with pytest.raises(SystemExit, match="^cannot write the output directory .*: Read-only file system$"):
        experiment_main(["profile=tiny", f"output_root={tmp_path}/x"], experiment="veh2dof")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "run", "x"]  # created, nothing written
    assert not any((tmp_path / "run").iterdir()) and not any((tmp_path / "x").iterdir())


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished tiny SLF training: its directory."""
    from daof.train.__main__ import main as train_main

    out = tmp_path_factory.mktemp("tiny") / "run"
    train_main([*TINY_SLF, f"output_dir={out}", "collector.total_frames=200"])
    return out


def damaged_checkpoints(blob: dict) -> dict:
    """A training checkpoint as a future, an older or a damaged version would leave it, and the expected line."""
    config, training = blob["config"], blob["training"]
    return {
        "future key": ({**blob, "config": {**config, "future_option": 3}}, "config key 'future_option', which this"),
        "missing key": ({**blob, "config": {k: v for k, v in config.items() if k != "window"}}, "no config key 'wind"),
        "no config": ({k: v for k, v in blob.items() if k != "config"}, "cannot be resumed: it has no config"),
        "config not a mapping": ({**blob, "config": 3}, "its config is a int, not a mapping"),
        "no filter": ({k: v for k, v in blob.items() if k != "filter"}, "cannot be resumed: it has no filter"),
        "no frames": (
            {**blob, "training": {k: v for k, v in training.items() if k != "frames"}},
            "it has no training/frames",
        ),
        "no optimiser": ({k: v for k, v in blob.items() if k != "optim"}, r"another version \(no 'optim' entry\)"),
    }


def test_a_future_or_incomplete_training_checkpoint_is_one_line_on_resume(tiny_run, tmp_path):
    from daof.io import atomic_save, safe_load
    from daof.train.__main__ import main as train_main

    blob = safe_load(tiny_run / "checkpoint.pt")
    for case, (damaged, message) in damaged_checkpoints(blob).items():
        path = tmp_path / f"{case}.pt"
        atomic_save(damaged, path)
        out = tmp_path / case.replace(" ", "-")
        with pytest.raises(SystemExit, match=f"^error: checkpoint {path} .*{message}") as error:
            train_main([*TINY_SLF, f"output_dir={out}", "collector.total_frames=400", f"resume={path}"])
        assert "\n" not in str(error.value), case
        assert not (out / "best.pt").exists(), case  # nothing trained


def test_a_filter_file_with_a_config_that_is_no_mapping_is_one_line(tiny_run, tmp_path):
    from daof.filters.learned import load_filter
    from daof.io import atomic_save, safe_load

    for name in ("best.pt", "checkpoint.pt"):
        blob = safe_load(tiny_run / name)
        path = tmp_path / name
        atomic_save({**blob, "config": 3}, path)
        with pytest.raises(ValueError, match=f"^{path} is not a learned-filter checkpoint: its 'config' is a int$"):
            load_filter(path)


def test_saving_a_filter_is_atomic(tmp_path, monkeypatch):
    """A failed write of best.pt leaves the old file whole and no .tmp beside it."""
    from daof.filters.learned import load_filter

    filt = small_form("SLF")
    path = tmp_path / "best.pt"
    filt.save(path, extra={"frames": 1})

    def disk_full(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"half a file")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        filt.save(path, extra={"frames": 2})
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["best.pt"]
    assert load_filter(path).extra == {"frames": 1}


def test_stopping_the_experiment_parent_stops_its_trainings(tmp_path):
    """SIGTERM to the process running ``run_jobs`` terminates the trainings it launched (they kept running)."""
    import os
    import signal
    import subprocess
    import time

    trainer = tmp_path / "trainer.py"
    trainer.write_text(
        "import os, pathlib, sys, time\n"
        f"pathlib.Path({str(tmp_path / 'child.pid')!r}).write_text(str(os.getpid()))\n"
        "time.sleep(120)\n"
    )
    parent = tmp_path / "parent.py"
    parent.write_text(
        "import sys\n"
        "from daof.experiments.jobs import TrainingJob, run_jobs\n"
        f"job = TrainingJob('SLF', __import__('pathlib').Path({str(tmp_path / 'slf')!r}), 100, ['filter=slf'],\n"
        f"                  launcher=[sys.executable, {str(trainer)!r}])\n"
        "run_jobs([job], parallel=1)\n"
    )
    proc = subprocess.Popen([sys.executable, str(parent)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pid_file = tmp_path / "child.pid"
    deadline = time.monotonic() + 120
    while not pid_file.is_file() or not pid_file.read_text():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    child = int(pid_file.read_text())
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    time.sleep(0.5)
    try:
        with pytest.raises(ProcessLookupError):
            os.kill(child, 0)  # gone (terminated and reaped by the parent)
        assert proc.returncode != 0 and "stopped by SIGTERM" in err
    finally:  # a failing run leaves no sleeping trainer behind
        try:
            os.kill(child, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_a_report_write_that_fails_leaves_the_old_files_whole(veh, tmp_path, monkeypatch):
    from daof.evaluate.report import write_report
    from daof.evaluate.study import run_study

    study = run_study(veh, {"EKF": EKF(veh)}, runs=2, steps=20, seed=0, measure_cost=False, log=lambda *_: None)
    write_report(study, tmp_path, title="t", profile="tiny")
    before = {name: (tmp_path / name).read_text() for name in ("results.json", "results.csv", "report.md")}
    real = Path.write_text

    def disk_full(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_report(study, tmp_path, title="another title", profile="tiny")
    monkeypatch.undo()
    assert {name: (tmp_path / name).read_text() for name in before} == before
    assert not list(tmp_path.glob("*.tmp"))


def test_a_damaged_memoised_simulation_is_simulated_again(tmp_path, monkeypatch):
    """A truncated or foreign file in the simulation cache was a torch traceback on every later read."""
    from daof.envs.recorded import cached_simulate

    lin = make_system("linear")
    first = cached_simulate(lin, 3, 5, 42, tmp_path)
    (path,) = tmp_path.glob("*.pt")
    for damage in (path.read_bytes()[:200], b"", b"not a checkpoint"):
        path.write_bytes(damage)
        again = cached_simulate(lin, 3, 5, 42, tmp_path)
        assert torch.equal(again["measurement"], first["measurement"])
        assert torch.equal(cached_simulate(lin, 3, 5, 42, tmp_path)["state"], first["state"])  # now read back

    def disk_full(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"half a file")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        cached_simulate(lin, 3, 5, 43, tmp_path)
    monkeypatch.undo()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]
