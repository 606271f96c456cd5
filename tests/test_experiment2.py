"""Experiment II (experiment=veh14dof, recipes/veh14dof/experiment.py): a complete Table II report.

The fast test runs the experiment's own pieces in process at the tiny profile (its planned training
jobs, the shared trainers, ``run_scenario``); the slow one runs the entry end to end twice (the
trainings as Ray tasks; the second run reuses every training and study result).
"""

import json
import math
import shlex
import time
from pathlib import Path

import pytest
import torch

from daof.experiments.experiment import main, plan_experiment, run_scenario
from daof.train.__main__ import train
from daof.train.config import compose_config

SCRIPT = "recipes/veh14dof/experiment.py"
STATES = ["pitch", "roll", "yaw_rate", "side_slip", "vx", "ax"]
UNITS = ["deg", "deg", "deg/s", "deg", "km/h", "g"]
ROWS = {"SLF", "DAOF-v2"}  # daof/conf/experiment/veh14dof.yaml: learned
FIGURES = [f"run0_{s}.png" for s in STATES] + ["per_run_rmse_box.png", "learning_curves.png"]


def _train_in_process(job) -> None:
    """What run_jobs would start as a subprocess: python -m daof.train with the job's arguments."""
    train(compose_config(job.arguments))
    assert job.finished(), job.name


def _check_report(report: Path, runs: int) -> dict:
    for name in ["report.md", "results.csv", "results.json", *FIGURES]:
        assert (report / name).is_file(), name
    results = json.loads((report / "results.json").read_text())
    assert results["system"] == "veh14dof" and results["runs"] == runs
    assert results["states"] == STATES and results["units"] == UNITS
    assert results["si_units"] == ["rad", "rad", "rad/s", "rad", "m/s", "m/s^2"]
    assert set(results["filters"]) == ROWS  # model-free only: no EKF / UKF / PF / PF-oracle
    assert results["reference"] is None
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
    assert "Same network size and input window for both learned filters (SLF: 3 × 16 GELU, N = 20; DAOF-v2" in text
    assert "System parameters of this profile: {'h': 0.01}" in text
    csv_head = (report / "results.csv").read_text().splitlines()[0]
    assert csv_head.startswith("filter,rmse_pitch [deg],rmse_roll [deg],rmse_yaw_rate [deg/s]")
    return results


def test_pipeline_writes_table2_report_in_paper_units(tmp_path, capsys):
    """Tiny profile in process: both trainings (the training configs + the experiment's overrides), the
    study and the report; RMSEs are reported in deg, deg/s, km/h and g (SI × report_scale)."""
    plan = plan_experiment("veh14dof", ["profile=tiny", f"output_root={tmp_path}", f"cache_dir={tmp_path / 'cache'}"])
    sp = plan.scenarios["nominal"]
    jobs = sp.jobs
    assert list(jobs) == ["SLF", "DAOF-v2"] and len({job.output_dir for job in jobs.values()}) == len(ROWS)
    v2 = jobs["DAOF-v2"].requested_config
    # DAOF-v2 trains with its critic and veh14dof's own budget (daof/conf/tuning/veh14dof_daof_v2.yaml), in its
    # own directory
    assert v2["network"]["critic_form"] == "reward_quadratic" and v2["network"]["critic_scale"] == "reward"
    assert v2["collector"]["feedback"] == "mean" and jobs["DAOF-v2"].output_dir == tmp_path / "daof-v2-rs-N20-s1"
    # from the profile's bank, in the experiment's cache; both trainings on the profile's system
    assert v2["overrides"]["replay"] == {**v2["overrides"]["replay"], "runs": 8, "cache_dir": str(tmp_path / "cache")}
    assert v2["overrides"]["h"] == jobs["SLF"].requested_config["overrides"]["h"] == 0.01
    for job in jobs.values():
        _train_in_process(job)
    _, report = run_scenario(plan, sp, time.perf_counter())
    results = _check_report(report.parent, runs=int(sp.profile.runs))
    assert "DAOF-v2 (DSAC-T) learned from a bank of 8 simulated episodes" in report.read_text()
    # the SI RMSE of the cached study result times the scale is what the report shows
    study_file = tmp_path / "study" / "SLF.pt"
    si = torch.tensor(torch.load(study_file, weights_only=False)["result"]["rmse"], dtype=torch.float64)
    shown = torch.tensor(results["filters"]["SLF"]["rmse"], dtype=torch.float64)
    torch.testing.assert_close(shown, si * torch.tensor(results["unit_scale"], dtype=torch.float64))
    # the DAOF-v2 run learned from the replayed bank of the profile's size
    assert list((tmp_path / "cache").glob("veh14dof-nominal-r8-t101-s1-*.pt"))


@pytest.mark.slow
def test_experiment2_tiny_profile_end_to_end(local_ray, tmp_path, capsys):
    """The entry as a user runs it (subprocess trainings); a second run reuses everything."""
    args = ["profile=tiny", f"output_root={tmp_path}", f"cache_dir={tmp_path / 'cache'}"]
    main(args, experiment="veh14dof", program=SCRIPT)
    _check_report(tmp_path / "report", runs=3)
    command = json.loads((tmp_path / "report" / "results.json").read_text())["command"]
    assert shlex.split(command) == ["python", SCRIPT, "profile=tiny", "scenario=nominal", *args[1:]]
    capsys.readouterr()
    main(args, experiment="veh14dof", program=SCRIPT)
    out = capsys.readouterr().out
    assert out.count("finished earlier, reusing") == 2 * len(ROWS)  # the trainings and their uncertainty heads
    assert out.count("reused finished result") == len(ROWS)
