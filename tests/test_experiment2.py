"""Experiment II (recipes/veh14dof): the pipeline writes a complete Table II report.

The fast test runs the recipe's own pieces in process (its training jobs' configs and overrides,
the shared trainers, ``study_and_report``) at the tiny profile; the slow one runs the script end
to end twice (the second run reuses every training and study result).
"""

import importlib.util
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from daof.train.dsac import DSACTTrainer
from daof.train.supervised import SLFTrainer

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "veh14dof"
STATES = ["pitch", "roll", "yaw_rate", "side_slip", "vx", "ax"]
UNITS = ["deg", "deg", "deg/s", "deg", "km/h", "g"]
ROWS = {"SLF", "DAOF-v2"}  # experiment.yaml: SLF and v2_rows
FIGURES = [f"run0_{s}.png" for s in STATES] + ["per_run_rmse_box.png", "learning_curves.png"]


def _recipe():
    spec = importlib.util.spec_from_file_location("experiment2", RECIPE / "experiment.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _train_in_process(job) -> None:
    """What run_jobs would start as a subprocess: the job's config name and Hydra overrides."""
    args = list(job.overrides)
    name = args[args.index("--config-name") + 1]
    overrides = [a for a in args if not a.startswith("--") and a not in (str(RECIPE), name)]
    overrides += [f"collector.total_frames={job.total_frames}", f"output_dir={job.output_dir}"]
    with initialize_config_dir(config_dir=str(RECIPE), version_base="1.3"):
        cfg = compose(config_name=name, overrides=overrides)
    trainer = (SLFTrainer if name == "slf" else DSACTTrainer)(cfg)
    trainer.train()
    assert job.finished(), job.name


def _check_report(report: Path, runs: int) -> dict:
    for name in ["report.md", "results.csv", "results.json", *FIGURES]:
        assert (report / name).is_file(), name
    results = json.loads((report / "results.json").read_text())
    assert results["system"] == "veh14dof" and results["runs"] == runs
    assert results["states"] == STATES and results["units"] == UNITS
    assert results["si_units"] == ["rad", "rad", "rad/s", "rad", "m/s", "m/s^2"]
    assert set(results["filters"]) == ROWS  # model-free only: no EKF / UKF / PF / PF-oracle
    for name, row in results["filters"].items():
        assert len(row["rmse"]) == 6 and all(math.isfinite(v) for v in row["rmse"]), name
        assert len(row["per_run_rmse"]) == runs
        assert row["ratio_to_oracle"] is None and row["diverged"] == 0
        assert row["cost_ms"] > 0 and row["throughput_per_s"] > 0
    assert set(results["training"]) == ROWS
    text = (report / "report.md").read_text()
    header = "| filter | " + " | ".join(f"RMSE {s} [{u}]" for s, u in zip(STATES, UNITS))
    assert header in text and "ratio to PF-oracle" not in text
    assert "| SLF |" in text and "| DAOF-v2 |" in text and "Table II, for context" in text
    csv_head = (report / "results.csv").read_text().splitlines()[0]
    assert csv_head.startswith("filter,rmse_pitch [deg],rmse_roll [deg],rmse_yaw_rate [deg/s]")
    return results


def test_pipeline_writes_table2_report_in_paper_units(tmp_path):
    """Tiny profile in process: both trainings (recipe configs + the experiment's overrides), the
    study and the report; RMSEs are reported in deg, deg/s, km/h and g (SI × report_scale)."""
    recipe = _recipe()
    with initialize_config_dir(config_dir=str(RECIPE), version_base="1.3"):
        cfg = compose(
            config_name="experiment",
            overrides=["profile=tiny", f"output_root={tmp_path}", f"cache_dir={tmp_path / 'cache'}"],
        )
    p = cfg.profiles.tiny
    jobs = recipe.training_jobs(cfg, p, tmp_path)
    # the DAOF-v2 row trains with its own form, in its own directory
    assert "network.critic_form=reward_quadratic" in jobs["DAOF-v2"].overrides
    assert not any("v2_action" in a for a in jobs["DAOF-v2"].overrides)  # the paper's x̂ = π(h)
    assert "collector.feedback=mean" in jobs["DAOF-v2"].overrides  # fed back as at run time
    assert len({job.output_dir for job in jobs.values()}) == len(ROWS)
    for job in jobs.values():
        _train_in_process(job)
    report = recipe.study_and_report(cfg, p, jobs, time.perf_counter())
    results = _check_report(report.parent, runs=int(p.runs))
    # the SI RMSE of the cached study result times the scale is what the report shows
    study_file = tmp_path / "study" / "SLF.pt"
    si = torch.tensor(torch.load(study_file, weights_only=False)["result"]["rmse"], dtype=torch.float64)
    shown = torch.tensor(results["filters"]["SLF"]["rmse"], dtype=torch.float64)
    torch.testing.assert_close(shown, si * torch.tensor(results["unit_scale"], dtype=torch.float64))
    # the DAOF-v2 run learned from the replayed bank of the profile's size
    assert list((tmp_path / "cache").glob(f"veh14dof-nominal-r{p.bank_runs}-t101-s1-*.pt"))


@pytest.mark.slow
def test_experiment2_tiny_profile_end_to_end(tmp_path):
    """The script as a user runs it (subprocess trainings); a second run reuses everything."""
    cmd = [
        sys.executable,
        str(RECIPE / "experiment.py"),
        "profile=tiny",
        f"output_root={tmp_path}",
        f"cache_dir={tmp_path / 'cache'}",
    ]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    _check_report(tmp_path / "report", runs=3)
    command = json.loads((tmp_path / "report" / "results.json").read_text())["command"]
    assert command == " ".join(["python recipes/veh14dof/experiment.py", *cmd[2:]])  # every override, as given
    second = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert second.returncode == 0, second.stderr[-3000:]
    assert second.stdout.count("finished earlier, reusing") == len(ROWS)
    assert second.stdout.count("reused finished result") == len(ROWS)
