"""Sweeping a config key through the experiment machinery, with one summary table."""

import pytest

from daof.experiments.experiment import plan_experiment
from daof.experiments.sweep import main, summary_table, value_overrides


def test_a_training_key_wins_over_every_row_and_profile_override(tmp_path):
    plan = plan_experiment("veh2dof", value_overrides("network.num_cells", "8", ["profile=tiny", f"root={tmp_path}"]))
    jobs = next(iter(plan.scenarios.values())).jobs
    assert all(job.requested_config["network"]["num_cells"] == 8 for job in jobs.values())  # tiny sets 16


def test_an_experiment_key_is_an_experiment_override(tmp_path):
    overrides = value_overrides("window", "5", ["profile=tiny", f"root={tmp_path}"])
    plan = plan_experiment("veh2dof", overrides)
    assert overrides[-1] == "window=5" and next(iter(plan.scenarios.values())).windows["DAOF-v1"] == 5


def test_the_summary_has_a_row_per_filter_and_value():
    results = {
        v: {"states": ["a", "b"], "reference": "KF", "filters": {"KF": {"rmse": [1.0, 2.0], "ratio_to_oracle": [1, 1]},
            "DAOF": {"rmse": [1.5 * k, 2.0], "ratio_to_oracle": [1.5 * k, 1.0]}}}
        for k, v in enumerate(["8", "16"], 1)
    }  # fmt: skip
    lines = summary_table("network.num_cells", results)
    assert lines[0] == "| filter | network.num_cells | RMSE a | RMSE b | a / KF | b / KF |"
    assert lines[2:] == [
        "| KF | 8 | 1 | 2 | 1.000 | 1.000 |",
        "| KF | 16 | 1 | 2 | 1.000 | 1.000 |",
        "| DAOF | 8 | 1.5 | 2 | 1.500 | 1.000 |",
        "| DAOF | 16 | 3 | 2 | 3.000 | 1.000 |",
    ]


def test_a_bad_sweep_is_one_line(tmp_path):
    with pytest.raises(SystemExit, match="give one experiment=NAME"):
        main(["--key", "window", "--values", "5", "--", "profile=tiny"])
    with pytest.raises(SystemExit, match="window must be >= 1"):
        main(["--key", "window", "--values", "0", "--", "experiment=veh2dof", "profile=tiny", f"root={tmp_path}"])


@pytest.mark.slow
def test_a_sweep_end_to_end(local_ray, tmp_path):
    """Two widths of the linear check at the tiny profile (~3 min)."""
    summary = main(["--key", "network.num_cells", "--values", "8", "16", "--", "experiment=linear", "profile=tiny",
                    f"root={tmp_path}"])  # fmt: skip
    text = summary.read_text()
    assert "| DAOF-v1 | 8 |" in text and "| DAOF-v1 | 16 |" in text
