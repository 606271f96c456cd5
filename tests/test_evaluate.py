"""The evaluator: metrics against hand-computed values, and the main job end to end (tiny profile)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from daof.evaluate.metrics import count_diverged, per_run_rmse, pooled_rmse
from daof.evaluate.study import FilterResult, _add_oracle_metrics

ROOT = Path(__file__).resolve().parents[1]


def test_pooled_and_per_run_rmse_by_hand():
    truth = torch.zeros(2, 2, 2)
    est = torch.tensor([[[1.0, 0.0], [3.0, 2.0]], [[0.0, 0.0], [0.0, 4.0]]])
    # state 0: errors 1, 3, 0, 0 -> sqrt(10/4); state 1: 0, 2, 0, 4 -> sqrt(20/4)
    torch.testing.assert_close(pooled_rmse(est, truth), torch.tensor([math.sqrt(2.5), math.sqrt(5.0)]).double())
    # run 0: sqrt((1+9)/2), sqrt(4/2); run 1: 0, sqrt(16/2)
    expected = torch.tensor([[math.sqrt(5.0), math.sqrt(2.0)], [0.0, math.sqrt(8.0)]]).double()
    torch.testing.assert_close(per_run_rmse(est, truth), expected)


def test_non_finite_estimates_stay_in_the_rmse():
    est = torch.zeros(2, 3, 1)
    est[1, 2, 0] = float("nan")
    assert torch.isnan(pooled_rmse(est, torch.zeros_like(est))).all()


def test_diverged_runs():
    runs = torch.tensor([[0.1, 0.2], [1.1, 0.2], [float("inf"), 0.1], [0.5, 0.5]])
    assert count_diverged(runs) == 1  # only the non-finite run without an oracle
    assert count_diverged(runs, torch.tensor([0.1, 0.1])) == 2  # 1.1 > 10 × 0.1 on state 0
    assert count_diverged(runs, torch.tensor([0.04, 0.04])) == 3  # and 0.5 > 0.4


def test_ratio_to_oracle():
    rows = {
        "PF-oracle": FilterResult(
            rmse=[0.01, 0.02], per_run_rmse=[[0.01, 0.02]], cost_ms=1, threads=1, throughput_per_s=1
        ),
        "UKF": FilterResult(rmse=[0.011, 0.03], per_run_rmse=[[0.011, 0.5]], cost_ms=1, threads=1, throughput_per_s=1),
    }
    _add_oracle_metrics(rows)
    assert rows["UKF"].ratio_to_oracle == pytest.approx([1.1, 1.5])
    assert rows["UKF"].diverged == 1 and rows["PF-oracle"].diverged == 0


def test_metrics_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="runs, steps, states"):
        pooled_rmse(torch.zeros(2, 3, 2), torch.zeros(2, 3, 1))


def test_experiment_tiny_profile_writes_a_complete_report(tmp_path):
    """The main job (tiny profile: tiny nets, a handful of updates) runs every filter and writes
    report.md, results.csv, results.json and every figure; a second run reuses everything."""
    cmd = [sys.executable, str(ROOT / "recipes/veh2dof/experiment.py"), "profile=tiny", f"output_root={tmp_path}"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    report = tmp_path / "report"
    for name in (
        "report.md",
        "results.csv",
        "results.json",
        "run0_states_errors.png",
        "per_run_rmse_box.png",
        "learning_curves.png",
        "window_study.png",
    ):
        assert (report / name).is_file(), name
    results = json.loads((report / "results.json").read_text())
    expected = {"EKF", "UKF", "PF", "PF-oracle", "SLF", "DAOF-v1", "DAOF-v2", "DAOF-v1 (N=1)"}
    assert set(results["filters"]) == expected
    for name, row in results["filters"].items():
        assert len(row["rmse"]) == 2 and all(math.isfinite(v) for v in row["rmse"]), name
        assert len(row["per_run_rmse"]) == results["runs"] == 3
        assert row["cost_ms"] > 0 and row["throughput_per_s"] > 0
    assert results["filters"]["PF-oracle"]["ratio_to_oracle"] == [1.0, 1.0]
    assert [r["window"] for r in results["window_study"]] == [1, 20]
    assert "| DAOF-v1 |" in (report / "report.md").read_text()

    second = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert second.returncode == 0, second.stderr[-3000:]
    assert second.stdout.count("finished earlier, reusing") == 4
    assert second.stdout.count("reused finished result") == 9


def test_study_cache_is_reused_only_for_the_same_filter_version(tmp_path):
    """A finished result is reused; a filter with another version (retrained weights) is evaluated again."""
    from daof.evaluate import run_study
    from daof.filters import EKF
    from envs import make_system

    system = make_system("linear")
    logs = []
    for version in ("w1", "w1", "w2"):
        run_study(
            system,
            {"EKF": EKF(system)},
            2,
            20,
            5,
            measure_cost=False,
            cache_dir=tmp_path,
            log=logs.append,
            versions={"EKF": version},
        )
    reused = ["reused finished result" in line for line in logs if line.startswith("[1/1] EKF:") and "RMSE" not in line]
    assert reused == [False, True, False]
