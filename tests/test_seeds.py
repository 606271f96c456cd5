"""Training seeds as a sweep: every learned row trains on each seed, and the report gives the
spread over seeds, the paired comparison per seed and how many seeds beat the reference."""

import json

import pytest

from daof.experiments.experiment import main, plan_experiment


def test_every_learned_row_trains_once_per_seed(tmp_path):
    plan = plan_experiment("veh2dof", ["profile=tiny", f"root={tmp_path}", "training_seeds=[1,2]"])
    jobs = next(iter(plan.scenarios.values())).jobs
    assert {"DAOF-v1 (seed 1)", "DAOF-v1 (seed 2)", "SLF (seed 2)"} <= set(jobs)
    assert jobs["DAOF-v1 (seed 2)"].output_dir.name == "daof-v1-N20-s2"
    assert "seed=2" in jobs["DAOF-v1 (seed 2)"].overrides
    assert not any("seed 2" in name and "(N=" in name for name in jobs)  # the window study: first seed only
    with pytest.raises(ValueError, match="training_seeds must be distinct integers"):
        plan_experiment("veh2dof", ["profile=tiny", f"root={tmp_path}", "training_seeds=[1,1]"])


def test_the_report_gives_the_spread_over_seeds(tmp_path, lin):
    """Two "seeds" of a row (here the EKF and UKF, which agree on a linear system) against the KF."""
    from daof.evaluate import run_study
    from daof.evaluate.report import Layout, ReportSpec, SeedSpread, write_report
    from daof.filters import EKF, UKF, KalmanFilter

    filters = {"KF": KalmanFilter(lin), "row (seed 1)": EKF(lin), "row (seed 2)": UKF(lin)}
    study = run_study(lin, filters, runs=4, steps=30, seed=5, measure_cost=False, log=lambda *_: None, reference="KF")
    spec = ReportSpec(
        layout=Layout(paired_with="KF"), seeds=SeedSpread({"row": {1: "row (seed 1)", 2: "row (seed 2)"}})
    )
    write_report(study, tmp_path, title="seeds", profile="tiny", spec=spec)
    spread = json.loads((tmp_path / "results.json").read_text())["seeds"]["row"]
    rmse = [study.results[f"row (seed {s})"].rmse for s in (1, 2)]
    assert spread["rmse_mean"] == pytest.approx([(a + b) / 2 for a, b in zip(*rmse)])
    assert spread["rmse_std"] == pytest.approx([abs(a - b) / 2**0.5 for a, b in zip(*rmse)])
    ratios = [study.results[f"row (seed {s})"].ratio_to_oracle for s in (1, 2)]
    assert spread["ratio_mean"] == pytest.approx([(a + b) / 2 for a, b in zip(*ratios)])
    better = sum(all(r < 1 for r in spread["paired"][str(s)]["ratio"]) for s in (1, 2))
    assert spread["seeds_better"] == better
    text = (tmp_path / "report.md").read_text()
    assert "## Over training seeds" in text and "| row | 1, 2 |" in text
    assert f"**{better} of 2 seeds beat the KF on every state.**" in text


@pytest.mark.slow
def test_an_experiment_over_two_seeds(local_ray, tmp_path):
    """End to end (the linear check at the tiny profile, two seeds; ~2 min)."""
    main(["profile=tiny", f"output_root={tmp_path}", "training_seeds=[1,2]"], experiment="linear", program="x")
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    assert {"DAOF-v1 (seed 1)", "DAOF-v1 (seed 2)", "DAOF-v2 (seed 2)"} <= set(results["filters"])
    assert [r["requirement"].split(" RMSE")[0] for r in results["requirements"]] == [
        "DAOF-v1 (seed 1)",
        "DAOF-v1 (seed 2)",
    ]
    assert "## Over training seeds" in (tmp_path / "report" / "report.md").read_text()
