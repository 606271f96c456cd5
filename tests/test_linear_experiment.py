"""The optimality check (experiment=linear, recipes/linear/experiment.py): DAOF against the Kalman filter.

End to end at the tiny profile (the trainings as subprocesses, the study and report in process),
and its bad inputs: an unknown scenario or profile ends the run with one clear line before any training.
"""

import csv
import json
import math
import shlex

import pytest

from daof.experiments.experiment import main, plan_experiment

SCRIPT = "recipes/linear/experiment.py"


def linear(*args: str):
    """What ``python recipes/linear/experiment.py args...`` runs, in process."""
    return main(list(args), experiment="linear", program=SCRIPT)


def test_linear_experiment_tiny_profile_reports_ratios_to_the_kalman_filter(tmp_path, capsys):
    args = ["profile=tiny", f"output_root={tmp_path}"]
    linear(*args)
    out = capsys.readouterr().out
    report = tmp_path / "report"
    for name in ("report.md", "results.csv", "results.json", "run0_states_errors.png", "learning_curves.png"):
        assert (report / name).is_file(), name
    results = json.loads((report / "results.json").read_text())
    assert results["system"] == "linear" and results["runs"] == 3 and results["steps"] == 60
    assert results["reference"] == "KF"
    # exact by the config (the KF of a linear-Gaussian system), so nothing is doubled, and the report says so
    assert results["reference_check"]["how"] == "exact" and [
        c["name"] for c in results["reference_check"]["candidates"]
    ] == ["KF"]
    assert (
        "- Reference: KF, exact (the Kalman filter of a linear-Gaussian system is the posterior mean)"
        in (report / "report.md").read_text()
    )
    rows = results["filters"]
    assert list(rows) == ["KF", "KF-stationary", "PF", "SLF", "DAOF-v1", "DAOF-v2", "KalmanNet"]
    for name, row in rows.items():
        assert len(row["rmse"]) == 2 and all(math.isfinite(v) for v in row["rmse"]), name
        # the ratio column is this filter's RMSE over the KF's, per state
        expected = [a / b for a, b in zip(row["rmse"], rows["KF"]["rmse"])]
        assert row["ratio_to_oracle"] == pytest.approx(expected, rel=1e-12), name
        assert row["cost_ms"] > 0
    assert rows["KF"]["ratio_to_oracle"] == [1.0, 1.0]
    # the experiment fits every trained filter's uncertainty head: every row reports its calibration
    for name, row in rows.items():
        assert row["std_source"] == ("uncertainty head" if name in results["training"] else row["std_source"]), name
        assert row["std_source"] is not None and len(row["nees"]) == 2 and len(row["coverage_2sigma"]) == 2, name
    assert (tmp_path / "daof-v2-N20-s1" / "best.uncertainty.pt").is_file()
    # the requirement is decided from the measured ratios and stated in the report
    check, kalmannet = results["requirements"]
    met = all(r <= 1.05 for r in rows["DAOF-v1"]["ratio_to_oracle"])
    assert check["requirement"] == "DAOF-v1 RMSE ≤ 1.05× KF per state" and check["met"] is met
    assert kalmannet["met"] is all(r <= 1.05 for r in rows["KalmanNet"]["ratio_to_oracle"])
    text = (report / "report.md").read_text()
    assert "ratio to KF (position / velocity)" in text
    assert f"DAOF-v1 RMSE ≤ 1.05× KF per state: **{'met' if met else 'not met'}**." in text
    ratio = rows["DAOF-v1"]["ratio_to_oracle"]
    assert f"DAOF-v1 / KF over all steps: position {ratio[0]:.3f}, velocity {ratio[1]:.3f}" in text
    assert "; after the first 50 steps: position " in text  # settled_step: the ratios after the start-up
    assert "Ratio to KF per state over the steps after the first 50 (the start-up excluded): KF-stationary " in text
    assert "PF: bootstrap particle filter with 200 particles" in text and "Table I" not in text
    with (report / "results.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert [r["filter"] for r in table] == list(rows) and float(table[0]["ratio_position"]) == 1.0
    # the trainings: python -m daof.train system=linear filter=daof_v1|daof_v2 with the profile's overrides
    assert set(results["training"]) == {"SLF", "DAOF-v1", "DAOF-v2", "KalmanNet"}
    assert results["training"]["DAOF-v1"]["frames"] >= 1200
    # DAOF-v2 in the paper's form with the reward-spread critic, its default (daof/conf/filter/daof_v2.yaml)
    v2_config = json.loads((tmp_path / "daof-v2-N20-s1" / "run_config.json").read_text())
    assert (v2_config["kind"], v2_config["network"]["critic_scale"]) == ("DAOF-v2", "reward")
    assert f"report: {report / 'report.md'}" in out
    assert "DAOF-v1 RMSE ≤ 1.05× KF per state: " in out
    # the command in the report plans this run again
    command = shlex.split(results["command"])
    assert command[:3] == ["python", SCRIPT, "profile=tiny"] and f"output_root={tmp_path}" in command
    first, again = (plan_experiment("linear", a).scenarios["nominal"] for a in (args, command[2:]))
    assert {n: j.requested_config for n, j in first.jobs.items()} == {
        n: j.requested_config for n, j in again.jobs.items()
    }
    # a second run reuses every training, every uncertainty head and every study result
    linear(*args)
    out = capsys.readouterr().out
    assert out.count("head: finished earlier, reusing") == 4 and out.count("finished earlier, reusing") == 8
    assert out.count("reused finished result") == 7


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("scenario=mismatch", "unknown scenario 'mismatch' for linear; valid: ['nominal']"),
        ("profile=huge", "unknown profile 'huge'; valid: ['tiny', 'quick', 'paper']"),
    ],
)
def test_bad_scenario_or_profile_exits_with_one_line(tmp_path, override, message):
    with pytest.raises(SystemExit) as error:
        linear(override, f"output_root={tmp_path}")
    assert str(error.value) == message
    assert not list(tmp_path.iterdir()), "nothing trains on a bad input"
