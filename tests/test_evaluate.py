"""The evaluator: metrics against hand-computed values, and Experiment I end to end (tiny profile),
through the one experiment entry (``daof.experiments``) and its config's refusals."""

import json
import math
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from daof.evaluate.metrics import count_diverged, paired_rmse_ratio, per_run_rmse, pooled_rmse
from daof.evaluate.study import FilterResult, _add_oracle_metrics
from daof.experiments.experiment import main, plan_experiment
from daof.experiments.runner import command_line
from daof.io import atomic_save

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = "recipes/veh2dof/experiment.py"


def experiment1(*args: str):
    """What ``python recipes/veh2dof/experiment.py args...`` runs, in process."""
    return main(list(args), experiment="veh2dof", program=SCRIPT)


def same_jobs(a, b) -> bool:
    """Two plans train the same filters with the same configs in the same directories."""
    jobs = [{n: (j.output_dir, j.total_frames, j.requested_config) for n, j in sp.jobs.items()} for sp in (a, b)]
    return jobs[0] == jobs[1]


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


def test_paired_rmse_ratio_by_hand():
    filt = torch.tensor([[1.0, 2.0], [3.0, 2.0], [1.0, 2.0]])
    ref = torch.tensor([[2.0, 2.0], [2.0, 2.0], [2.0, 1.0]])
    c = paired_rmse_ratio(filt, ref, draws=2000)
    # pooled MSE = mean of per-run MSEs: β sqrt((1 + 9 + 1) / 12), r sqrt(12 / 9)
    assert c["ratio"] == pytest.approx([math.sqrt(11 / 12), math.sqrt(12 / 9)])
    assert c["better_runs"] == [2, 0] and c["runs"] == 3
    for j in range(2):
        assert c["low"][j] <= c["ratio"][j] <= c["high"][j]
    assert c["low"][0] < 1 < c["high"][0]  # run 2 goes the other way: the interval spans 1
    assert c["low"][1] >= 1.0  # r is never better on any run: no resample gets below 1
    same = paired_rmse_ratio(ref, ref)
    assert same["ratio"] == same["low"] == same["high"] == [1.0, 1.0]
    with pytest.raises(ValueError, match="same shape"):
        paired_rmse_ratio(filt, ref[:2])
    with pytest.raises(ValueError, match="level"):
        paired_rmse_ratio(filt, ref, level=1.0)


def test_experiment_tiny_profile_writes_a_complete_report(local_ray, tmp_path, capsys):
    """The main job (tiny profile: tiny nets, a handful of updates) runs every filter and writes
    report.md, results.csv, results.json and every figure; a second run reuses everything; the
    command the report records plans the same run."""
    args = ["profile=tiny", f"output_root={tmp_path}"]
    report = tmp_path / "report"
    assert experiment1(*args) == [report / "report.md"]
    assert f"report: {report / 'report.md'}" in capsys.readouterr().out
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
    expected = {"EKF", "UKF", "PF", "PF-oracle", "SLF", "DAOF-v1", "DAOF-v2", "KalmanNet", "DAOF-v1 (N=1)"}
    expected |= {"DAOF-v1 (paper form)"}
    # the reference is checked: PF-oracle, and only if it fails its check the fallback PF-proposal
    check = results["reference_check"]
    tried = [c["name"] for c in check["candidates"]]
    assert tried[0] == "PF-oracle" and tried == ["PF-oracle", "PF-proposal"][: len(tried)]
    assert all(c["converged"] == all(v < 1.0 for v in c["change_percent"]) for c in check["candidates"])
    expected |= {"PF-proposal"} if "PF-proposal" in tried else set()
    assert set(results["filters"]) == expected
    converged = [c["name"] for c in check["candidates"] if c["converged"]]
    if converged:  # the first converged candidate, the last one tried
        assert results["reference"] == converged[0] == tried[-1] and check["how"] == "converged"
    else:  # never an unconverged candidate: the best filter
        assert check["how"] == "best" and results["reference"] == check["name"] not in tried
    for name, row in results["filters"].items():
        assert len(row["rmse"]) == 2 and all(math.isfinite(v) for v in row["rmse"]), name
        assert len(row["per_run_rmse"]) == results["runs"] == 3
        assert row["cost_ms"] > 0 and row["throughput_per_s"] > 0
    assert results["filters"][results["reference"]]["ratio_to_oracle"] == [1.0, 1.0]
    assert [r["window"] for r in results["window_study"]] == [1, 20]
    text = (report / "report.md").read_text()
    assert "| DAOF-v1 |" in text and "## Sliding-window study (DAOF-v1)" in text
    assert "## The paper's Table I, for context" in text and "Table II" not in text
    assert "- PF-oracle (400 particles), convergence check: with 800 particles (seed 3) its RMSE changes by" in text
    assert "- PF uses 200 particles." in text
    paired = results["paired_with"]
    assert paired["reference"] == "UKF" and set(paired["filters"]) == expected - {"UKF"}
    daof = paired["filters"]["DAOF-v1"]
    ukf, own = (torch.tensor(results["filters"][k]["rmse"]) for k in ("UKF", "DAOF-v1"))
    torch.testing.assert_close(torch.tensor(daof["ratio"], dtype=torch.float64), (own / ukf).double())
    assert "## Paired with the UKF" in text
    # the command in the report plans this run again
    command = shlex.split(results["command"])
    assert command[:2] == ["python", SCRIPT] and "profile=tiny" in command and "scenario=nominal" in command
    first, again = plan_experiment("veh2dof", args), plan_experiment("veh2dof", command[2:])
    assert same_jobs(first.scenarios["nominal"], again.scenarios["nominal"])

    # again, with the dropout study: trainings and the main study are reused, the gappy one is new
    gaps = ["dropout.enabled=true", "dropout.blackout=[yaw_rate,0.4,0.2]"]  # a blackout that fits 60 steps
    experiment1(*args, *gaps)
    out = capsys.readouterr().out
    assert out.count("finished earlier, reusing") == 12  # 6 trainings and their uncertainty heads
    # 10 filters, and every candidate the reference check tried, with its doubled run (a fallback is a row too)
    assert out.count("reused finished result") == 10 + 2 * len(tried) - 1
    gappy = json.loads((report / "dropout" / "results.json").read_text())
    assert set(gappy["filters"]) == expected and gappy["dropout"]["p"] == 0.1
    assert all(0.05 < m < 0.5 for m in gappy["dropout"]["missing_fraction"])
    for name, row in gappy["filters"].items():
        assert all(math.isfinite(v) for v in row["rmse"]), name
        assert row["rmse"] != results["filters"][name]["rmse"], name  # the gaps changed every filter's estimates
    assert "Sensor dropout" in (report / "dropout" / "report.md").read_text()
    assert "dropout.enabled=true" in shlex.split(gappy["command"])


def test_study_cache_is_reused_only_for_the_same_filter_version(tmp_path):
    """A finished result is reused; a filter with another version (retrained weights) is evaluated again."""
    from daof.envs import make_system

    from daof.evaluate import run_study
    from daof.filters import EKF

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


def test_classical_filters_are_cached_under_their_code_and_settings():
    """Two filters built alike share a fingerprint; another particle count or seed gets its own."""
    from daof.envs import make_system

    from daof.filters import UKF, ParticleFilter
    from daof.fingerprint import classical_fingerprint

    system = make_system("veh2dof")
    pf = classical_fingerprint(ParticleFilter(system, 100, seed=1), system)
    assert pf == classical_fingerprint(ParticleFilter(system, 100, seed=1), system)
    assert pf != classical_fingerprint(ParticleFilter(system, 200, seed=1), system)
    assert pf != classical_fingerprint(ParticleFilter(system, 100, seed=2), system)
    assert pf != classical_fingerprint(UKF(system), system)


# ----------------------------------------------------------------------------- scenarios side by side
def _small_study(system):
    from daof.evaluate import run_study
    from daof.experiments.config import compose_experiment, for_scenario
    from daof.experiments.experiment import classical_filters, reference_of

    # Experiment I's classical filters, with fewer particles
    particles = "profiles.tiny.particles={PF: 100, PF-oracle: 300, PF-joint: 300}"
    cfg = for_scenario(compose_experiment("veh2dof", ["profile=tiny", particles]), system.scenario)
    filters = classical_filters(cfg, cfg.profiles["tiny"], system)
    reference = reference_of(cfg, filters)
    return run_study(system, filters, 2, 30, 20261122, measure_cost=False, log=lambda _: None, reference=reference)


def test_scenario_report_puts_the_scenarios_side_by_side(tmp_path):
    """One table of RMSE per state per filter per scenario (best in bold), the winner of each scenario,
    every scenario's table with its ratio label, links to the per-scenario reports, CSV and JSON."""
    from daof.envs import make_system

    from daof.evaluate.report import write_scenario_report

    studies = {sc: _small_study(make_system("veh2dof", sc)) for sc in ("nominal", "mismatch", "outliers")}
    reports = {sc: tmp_path / sc / "report" / "report.md" for sc in studies}
    path = write_scenario_report(studies, tmp_path / "report", title="side by side", profile="tiny", reports=reports)
    text = path.read_text()
    head = "| filter | nominal: beta [rad] | nominal: yaw_rate [rad/s] | mismatch: beta [rad] | mismatch: yaw_rate"
    assert head in text
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    assert results["scenarios"] == ["nominal", "mismatch", "outliers"]
    for sc, study in studies.items():
        names = list(study.results)
        rmse = torch.tensor([study.results[n].rmse for n in names])
        best = [names[i] for i in rmse.argmin(0).tolist()]
        assert results["winners"][sc]["per_state"] == dict(zip(["beta", "yaw_rate"], best))
        score = (rmse / rmse.min(0).values).mean(1)
        assert results["winners"][sc]["overall"] == names[int(score.argmin())]
        practical = [i for i, n in enumerate(names) if n not in {"PF-oracle", study.reference}]
        assert results["winners"][sc]["overall_without_oracle"] == names[min(practical, key=lambda i: score[i])]
        assert results["studies"][sc]["filters"]["UKF"]["rmse"] == study.results["UKF"].rmse
        # the winner's cell is bold in the summary table
        j = 2 * list(studies).index(sc)
        row = next(line for line in text.splitlines() if line.startswith(f"| {best[0]} | "))
        assert row.split(" | ")[1 + j] == f"**{study.results[best[0]].rmse[0]:.4g}**"
    assert f"| mismatch | {results['winners']['mismatch']['per_state']['beta']} |" in text
    assert "## Scenario `nominal` ([full report](../nominal/report/report.md))" in text
    assert "ratio to PF-oracle (beta / yaw_rate)" in text  # nominal: the near-optimal reference
    assert "ratio to PF-joint (beta / yaw_rate)" in text  # mismatch: the scenario's Bayes filter
    assert "Ratios are per state, relative to PF-joint" in text
    assert "ratio to PF-oracle (nominal model) (beta / yaw_rate)" in text  # outliers: only a nominal-model PF
    assert "the PF-oracle is the near-optimal reference only on `nominal`" in text
    assert results["studies"]["mismatch"]["reference"] == "PF-joint"
    assert results["winners"]["mismatch"]["overall_without_oracle"] not in {"PF-oracle", "PF-joint"}
    lines = (tmp_path / "report" / "results.csv").read_text().splitlines()
    assert lines[0].startswith("scenario,filter,rmse_beta,rmse_yaw_rate,ratio_beta") and len(lines) == 1 + 13
    assert "| PF-joint | – | – | " in text  # run on mismatch only: a dash where it was not run
    assert (tmp_path / "report" / "rmse_by_scenario.png").is_file()


def test_a_non_finite_filter_never_wins_a_scenario():
    from types import SimpleNamespace

    from daof.evaluate.report import scenario_winners

    def row(rmse):
        return FilterResult(rmse=rmse, per_run_rmse=[rmse], cost_ms=None, threads=1, throughput_per_s=1)

    study = SimpleNamespace(
        system=SimpleNamespace(state_names=("a", "b")),
        results={
            "bad": row([float("nan"), 0.001]),
            "PF-oracle": row([0.9, 1.5]),
            "A": row([1.0, 2.0]),
            "B": row([2.0, 1.2]),
        },
    )
    w = scenario_winners(study)
    assert w["per_state"] == {"a": "PF-oracle", "b": "B"}  # "bad" has the lowest b, but failed on a
    # mean of RMSE / best per state: PF-oracle (1 + 1.5/1.2)/2 < A (1/0.9 + 2/1.2)/2 < B (2/0.9 + 1)/2
    assert w["overall"] == "PF-oracle" and w["overall_without_oracle"] == "A"
    assert w["score"]["bad"] is None


def test_each_scenario_trains_on_its_own_data_in_its_own_directory(tmp_path):
    plan = plan_experiment("veh2dof", ["profile=tiny", f"root={tmp_path}", "scenarios=[nominal,mismatch,outliers]"])
    assert list(plan.scenarios) == ["nominal", "mismatch", "outliers"]
    dirs = set()
    for sc, sp in plan.scenarios.items():
        assert Path(sp.cfg.output_root) == tmp_path / sc and Path(sp.cfg.report_dir) == tmp_path / sc / "report"
        paper = "DAOF-v1 (paper form)"
        assert list(sp.jobs) == ["SLF", "DAOF-v2", "DAOF-v1", "DAOF-v1 (N=1)", paper, "KalmanNet"]
        assert sp.windows == {"SLF": 20, "DAOF-v2": 20, "DAOF-v1": 20, "DAOF-v1 (N=1)": 1, paper: 20, "KalmanNet": 20}
        for name, job in sp.jobs.items():
            assert f"scenario={sc}" in job.overrides and job.name == f"{name} [{sc}]"
            assert f"window={sp.windows[name]}" in job.overrides
            assert job.requested_config["scenario"] == sc
            dirs.add(job.output_dir)
    assert len(dirs) == 18 and Path(plan.cfg.combined_report_dir) == tmp_path / "report"
    # the default is one scenario, in the directory the README names
    single = plan_experiment("veh2dof", [])
    assert list(single.scenarios) == ["nominal"] and single.cfg.report_dir == "runs/experiment1/quick/nominal/report"
    # several scenarios cannot share one output_root
    with pytest.raises(SystemExit, match="would share the output directory .* set root=DIR"):
        experiment1("profile=tiny", f"output_root={tmp_path}", "scenarios=[nominal,mismatch]")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("scenarios=[nominal,icy]", "unknown scenario 'icy' for veh2dof; valid: ['nominal', 'mismatch', 'outliers']"),
        ("profile=huge", "unknown profile 'huge'; valid: ['tiny', 'quick', 'paper']"),
    ],
)
def test_experiment1_bad_scenario_or_profile_exits_with_one_line(tmp_path, override, message):
    with pytest.raises(SystemExit) as error:
        experiment1(override, f"root={tmp_path}")
    assert str(error.value) == message
    assert not list(tmp_path.iterdir()), "nothing trains on a bad input"


@pytest.mark.slow
def test_experiment1_scenarios_side_by_side_end_to_end(local_ray, tmp_path, capsys):
    """Two scenarios at the tiny profile (one window): per-scenario reports and the combined one."""
    experiment1("profile=tiny", f"root={tmp_path}", "scenarios=[nominal,mismatch]", "profiles.tiny.windows=[20]")
    for sc in ("nominal", "mismatch"):
        results = json.loads((tmp_path / sc / "report" / "results.json").read_text())
        assert results["scenario"] == sc and set(results["filters"]) >= {"EKF", "PF-oracle", "SLF", "DAOF-v1"}
        assert ("PF-joint" in results["filters"]) == (sc == "mismatch")
        assert results["reference"] == ("PF-joint" if sc == "mismatch" else "PF-oracle")
    combined = json.loads((tmp_path / "report" / "results.json").read_text())
    assert combined["scenarios"] == ["nominal", "mismatch"] and set(combined["winners"]) == {"nominal", "mismatch"}
    assert f"combined report: {tmp_path / 'report' / 'report.md'}" in capsys.readouterr().out


def test_the_scripts_exit_with_one_line_and_no_traceback(tmp_path, monkeypatch):
    """A bad profile: the shared entry as a user runs it (a subprocess: one line on stderr, no
    traceback), and the README's recipe script, which hands the same ``main`` its arguments, in process."""
    cmd = [sys.executable, "-m", "daof.experiments", "experiment=linear", "profile=huge", f"root={tmp_path}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode != 0
    assert done.stderr.strip().splitlines() == ["unknown profile 'huge'; valid: ['tiny', 'quick', 'paper']"]
    assert "Traceback" not in done.stdout + done.stderr
    monkeypatch.setattr(sys, "argv", [SCRIPT, "profile=huge", f"root={tmp_path}"])
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(ROOT / SCRIPT), run_name="__main__")
    assert str(stop.value) == "unknown profile 'huge'; valid: ['tiny', 'quick', 'paper']"
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- the experiment config's refusals
@pytest.mark.parametrize(
    ("experiment", "overrides", "message"),
    [
        ("veh3dof", [], "unknown experiment 'veh3dof'; valid: linear, veh14dof, veh2dof"),
        ("veh2dof", ["windw=4"], "unknown experiment key 'windw'; did you mean 'window'?"),
        ("veh2dof", ["profiles.tiny.run=3"], "unknown experiment key 'profiles.tiny.run'; did you mean 'runs'?"),
        ("veh2dof", ["dropout.enable=true"], "unknown experiment key 'dropout.enable'; did you mean 'enabled'?"),
        ("veh2dof", ["learned.SLF.filtr=slf"], "unknown experiment key 'learned.SLF.filtr'; did you mean 'filter'?"),
        ("veh2dof", ["seed"], "override 'seed' is not key=value"),
        ("veh2dof", ["window=abc"], "window=abc.*could not be converted to Integer"),
        ("veh2dof", ["profiles.tiny.runs=lots"], "profiles.tiny.runs=lots.*could not be converted to Integer"),
        ("veh2dof", ["profile=tiny", "profiles.tiny.runs=0"], "profiles.tiny.runs must be >= 1, got 0"),
        ("veh2dof", ["profile=tiny", "profiles.tiny.steps=-5"], "profiles.tiny.steps must be >= 1, got -5"),
        ("veh2dof", ["window=0"], "window must be >= 1, got 0"),
        ("veh2dof", ["parallel_jobs=0"], "parallel_jobs must be >= 1, got 0"),
        ("veh2dof", ["ray.address=auto", "parallel_jobs=2"], "parallel_jobs sizes a local Ray; the cluster at"),
        ("veh2dof", ["ray.adress=auto"], "unknown experiment key 'ray.adress'; did you mean 'address'?"),
        ("veh2dof", ["ray.address=ray://head:10001"], "ray.address=ray://head:10001: Ray Client cannot run the tr"),
        ("veh2dof", ["profile=tiny", "profiles.tiny.windows=[1,0]"], "profiles.tiny.windows must be >= 1, got 0"),
        ("veh2dof", ["profile=tiny", "profiles.tiny.windows=[5,5]"], "names a window more than once"),
        ("veh2dof", ["scenarios=[]"], "scenarios must be one or more scenario names of veh2dof, got \\[\\]"),
        ("veh2dof", ["scenarios=[nominal,nominal]"], "scenarios \\['nominal', 'nominal'\\] name a scenario more"),
        ("linear", ["scenario=mismatch"], "unknown scenario 'mismatch' for linear; valid: \\['nominal'\\]"),
        ("veh2dof", ["learned.SLF.filter=ukf"], "learned.SLF.filter='ukf' is not valid; valid: \\['daof_v1'"),
        ("veh2dof", ["+profiles.tiny.frames.SFL=10", "profile=tiny"], "profiles.tiny.frames \\['SFL'\\] is not"),
        ("veh2dof", ["profile=tiny", "profiles.tiny.frames.SLF=0"], "profiles.tiny.frames.SLF must be >= 1, got 0"),
        ("veh2dof", ["profile=tiny", "~profiles.tiny.particles.PF"], "profiles.tiny.particles has no particle count"),
        ("veh2dof", ["classical.EKF.filter=EnKF"], "classical.EKF.filter='EnKF' is not valid"),
        ("veh2dof", ["classical.PF-joint.scenarios=[icy]"], "classical.PF-joint.scenarios \\['icy'\\] is not"),
        ("veh2dof", ["reference=[KF]"], "reference \\['KF'\\] is not an exact or particle filter of classical"),
        ("veh2dof", ["reference=[UKF]"], "reference \\['UKF'\\] is not an exact or particle filter of classical"),
        ("veh2dof", ["classical.UKF.exact=true"], "classical.UKF.exact: only \\['KalmanFilter'\\] can be exact"),
        ("veh2dof", ["classical.PF.fallback=true"], "classical.PF.fallback: only a reference candidate runs as"),
        ("veh2dof", ["convergence_check.limit_percent=0"], "convergence_check.limit_percent must be > 0, got 0.0"),
        ("veh2dof", ["report.paired_with=KF"], "report.paired_with \\['KF'\\] is not a filter of the study"),
        ("veh2dof", ["report.paper_table=III"], "report.paper_table \\['III'\\] is not a paper table"),
        ("veh2dof", ["convergence_check.filter=UKF"], "convergence_check.filter"),
        ("veh2dof", ["dropout.p=1.5"], "dropout.p must be in \\[0, 1\\], got 1.5"),
        ("veh2dof", ["profile=tiny", "dropout.enabled=true"], "dropout: blackout \\[4.0, 5.0\\) s does not fit in 60"),
        ("veh2dof", ["dropout.enabled=true", "dropout.blackout=[wheel,1,1]"], "dropout: blackout channel 'wheel'"),
        ("veh2dof", ['notes=["{nope}"]'], "uses unknown field\\(s\\) \\['nope'\\]"),
        ("veh2dof", ["profile=tiny", 'profiles.tiny.overrides.SLF=["optim.lrr=1"]'], "SLF: unknown config key"),
        ("linear", ["requirements.DAOF-v1.tolerance=0"], "requirements.DAOF-v1.tolerance must be > 0, got 0.0"),
        ("linear", ["reference=[]"], "requirements.DAOF-v1 is relative to the study's reference, but reference is"),
        ("veh14dof", ["+profiles.quick.system.hh=1"], "unknown parameter\\(s\\) \\['hh'\\] for veh14dof"),
        ("veh2dof", ["~learned.SLF"], "profiles.quick.frames \\['SLF'\\] is not learned rows"),
    ],
)
def test_the_experiment_config_refuses_bad_input_in_one_line(tmp_path, experiment, overrides, message):
    """Unknown experiments and keys (with the nearest key), wrong types and impossible values: one
    line each, from planning alone (``main`` exits with it before any work; nothing is written)."""
    with pytest.raises(ValueError) as error:
        plan_experiment(experiment, [f"root={tmp_path}", *overrides])
    text = str(error.value)
    assert "\n" not in text and text.strip(), text
    assert re.search(message, text), text
    assert not list(tmp_path.iterdir())


def test_what_the_command_line_cannot_break_is_checked_too():
    """Impossible experiments a YAML file could describe: classical filters on a system without a
    model, or no filter at all."""
    from daof.experiments.config import ClassicalFilter, check_experiment, compose_experiment, for_scenario

    cfg = for_scenario(compose_experiment("veh14dof"), "nominal")
    cfg.classical["EKF"] = ClassicalFilter(filter="EKF")
    with pytest.raises(ValueError, match="^veh14dof has no model for filters: the classical filters \\['EKF'\\]"):
        check_experiment(cfg)
    cfg.classical.clear()
    cfg.learned.clear()
    cfg.profiles["quick"].frames.clear()
    cfg.profiles["quick"].overrides.clear()
    with pytest.raises(ValueError, match="^the experiment has no filters"):
        check_experiment(cfg)


def test_the_entry_wants_one_experiment():
    valid = "linear, veh14dof, veh2dof or a path to a YAML file"
    with pytest.raises(SystemExit, match=f"^give one experiment=NAME; valid: {valid}$"):
        main([])
    with pytest.raises(SystemExit, match="^recipes/veh2dof/experiment.py runs experiment=veh2dof; leave out"):
        experiment1("experiment=linear")


def test_every_experiment_and_profile_plans():
    """Each shipped experiment, at each profile, composes, passes its checks and plans its trainings."""
    for name, rows in (
        ("veh2dof", {"SLF", "DAOF-v2", "DAOF-v1", "KalmanNet"}),
        ("linear", {"DAOF-v1", "DAOF-v2", "KalmanNet"}),
        ("veh14dof", {"SLF", "DAOF-v2"}),
    ):
        for profile in ("tiny", "quick", "paper"):
            plan = plan_experiment(name, [f"profile={profile}"])
            (sp,) = plan.scenarios.values()
            assert rows <= set(sp.jobs), (name, profile)
            command = f"python -m daof.experiments experiment={name} profile={profile}"
            assert plan.command(f"profile={profile}") == command


# ----------------------------------------------------------------------------- bad inputs, one line each
def test_stale_or_missing_checkpoints_exit_with_one_line(tmp_path):
    """A checkpoint of another system, scenario or window in a job's directory, or none at all."""
    from daof.envs import make_system

    from daof.experiments.jobs import TrainingJob
    from daof.experiments.runner import load_trained
    from daof.filters.learned import FilterConfig, LearnedFilter

    LearnedFilter(FilterConfig(kind="DAOF-v2", system="veh2dof", window=4, num_cells=8)).save(
        tmp_path / "v" / "best.pt"
    )
    job = TrainingJob("DAOF-v2", tmp_path / "v", 100)
    system = make_system("veh2dof")
    assert load_trained({"DAOF-v2": job}, system, {"system": "veh2dof", "window": 4})["DAOF-v2"].config.window == 4
    cases = [
        ({"window": 20}, "has window=4, expected 20"),
        ({"system": "linear"}, "has system='veh2dof', expected 'linear'"),
        ({"scenario": "mismatch"}, "has scenario='nominal', expected 'mismatch'"),
    ]
    for expect, match in cases:
        with pytest.raises(
            SystemExit, match=f"^DAOF-v2: checkpoint .*best.pt {match} \\(train it again: delete .*v\\)$"
        ) as error:
            load_trained({"DAOF-v2": job}, system, lambda name, e=expect: e)
        assert "\n" not in str(error.value)
    missing = TrainingJob("SLF", tmp_path / "none", 100)
    with pytest.raises(SystemExit, match="^SLF: no filter checkpoint at .*none/best.pt"):
        load_trained({"SLF": missing}, system, {"system": "veh2dof"})


def test_a_run_of_another_config_is_set_aside_not_reused(tmp_path):
    """A finished run is reused only if its run_config.json is the config the job asks for now
    (apart from its budget and where it lives: a moved results root is still reused)."""
    from daof.experiments.jobs import TrainingJob
    from daof.train.base import RUN_CONFIG

    job = TrainingJob("SLF", tmp_path / "slf", 100, ["filter=slf", "window=4"])
    job.output_dir.mkdir()
    (job.output_dir / "summary.json").write_text(json.dumps({"frames": 100}))
    atomic_save({"state_dict": {}}, job.output_dir / "best.pt")  # readable: a truncated one is test_reliability's
    assert not job.finished()  # no record of its config: not trusted
    (job.output_dir / RUN_CONFIG).write_text(json.dumps(job.requested_config))
    assert job.finished() and job.set_aside_if_stale() is None
    assert TrainingJob("SLF", job.output_dir, 50, ["filter=slf", "window=4"]).finished()  # the budget may differ
    moved = tmp_path / "moved"
    shutil.copytree(job.output_dir, moved)
    assert TrainingJob("SLF", moved, 100, ["filter=slf", "window=4"]).finished()  # so may the directory
    changed = TrainingJob("SLF", job.output_dir, 100, ["filter=slf", "window=4", "optim.lr=1e-3"])
    assert not changed.finished()
    assert changed.set_aside_if_stale() == tmp_path / "slf.stale-1"
    assert (tmp_path / "slf.stale-1" / RUN_CONFIG).is_file() and not job.output_dir.exists()


def test_a_failed_training_exits_with_one_line(local_ray, tmp_path):
    from daof.experiments.jobs import TrainingJob
    from daof.experiments.runner import train

    # a job whose config is refused fails before anything is launched, with the reason
    job = TrainingJob("SLF", tmp_path / "slf", 100, ["filter=slf", "windw=4"])
    with pytest.raises(SystemExit) as error:
        train([job], parallel=1, log=lambda _: None)
    assert str(error.value).startswith("SLF: unknown config key 'windw'; did you mean 'window'?")
    # a training that crashes: one line naming it, and the log it points to holds the cause
    script = tmp_path / "crashing.py"
    script.write_text("import sys\nprint('out of memory')\nsys.exit(3)\n")
    job = TrainingJob("SLF", tmp_path / "slf", 100, ["filter=slf"], launcher=[sys.executable, str(script)])
    with pytest.raises(SystemExit) as error:
        train([job], parallel=1, log=lambda _: None)
    assert str(error.value) == "training failed for ['SLF']; rerun the same command to resume"
    assert "out of memory" in (tmp_path / "slf" / "train.log").read_text()


def test_the_config_a_job_asks_for_is_pinned_when_it_starts(local_ray, tmp_path, monkeypatch):
    """A training that finishes after its configuration files were edited is done; a rerun sets it aside."""
    import daof.experiments.jobs as jobs
    from daof.experiments.runner import train
    from daof.train.base import RUN_CONFIG

    script = tmp_path / "train.py"
    script.write_text(
        "import json, sys, pathlib\n"
        "out = pathlib.Path([a for a in sys.argv if a.startswith('output_dir=')][0].split('=', 1)[1])\n"
        f"(out / {RUN_CONFIG!r}).write_text(pathlib.Path({str(tmp_path / 'pinned.json')!r}).read_text())\n"
        "(out / 'summary.json').write_text(json.dumps({'frames': 100}))\n"
        "import torch; torch.save({}, out / 'best.pt')\n"
    )
    job = jobs.TrainingJob("SLF", tmp_path / "slf", 100, ["filter=slf"], launcher=[sys.executable, str(script)])
    (tmp_path / "pinned.json").write_text(json.dumps(job.requested_config))
    edited = OmegaConf.create({**job.requested_config, "window": 7})
    monkeypatch.setattr(jobs, "compose_config", lambda overrides: edited)  # the files change during the run
    lines = []
    train([job], parallel=1, log=lines.append)
    assert any("SLF: done" in line for line in lines), lines
    again = jobs.TrainingJob("SLF", tmp_path / "slf", 100, ["filter=slf"])
    assert not again.finished()  # the configuration now asks for another run


@pytest.mark.parametrize("kind", ["DAOF-v1", "DAOF-v2", "SLF"])
def test_learned_filters_reject_bad_input_with_one_line(kind, veh):
    """NaN / inf controls, inf measurements, wrong shapes and dtypes: one ValueError line naming the
    filter and the entry, raised before any network runs (the classical filters: test_missing_measurements)."""
    from test_missing_measurements import bad_inputs

    from daof.filters.learned import FilterConfig, LearnedFilter

    f = LearnedFilter(FilterConfig(kind=kind, system="veh2dof", window=4, num_cells=8), veh)
    for case, (data, key) in bad_inputs(veh.simulate(2, 6, seed=0)).items():
        with pytest.raises(ValueError) as error:
            f.run(data)
        message = str(error.value)
        assert message.startswith(f"{kind}: ") and key in message and "\n" not in message, (case, message)


def test_learning_curves_come_from_the_whole_run_not_only_up_to_the_best_checkpoint(tmp_path):
    """best.pt holds the validation history only up to the best; the curve is read from final.pt beside it."""
    from daof.experiments.runner import learning_curves
    from daof.filters.learned import FilterConfig, LearnedFilter, load_filter

    f = LearnedFilter(FilterConfig(kind="DAOF-v1", system="veh2dof", window=2, num_cells=8))
    history = [{"frames": k * 100, "rmse_beta": 1.0 / (k + 1), "rmse_yaw_rate": 2.0} for k in range(4)]
    f.save(tmp_path / "best.pt", extra={"history": history[:2]})
    only_best = load_filter(tmp_path / "best.pt")
    assert learning_curves({"DAOF-v1": only_best}) == {"DAOF-v1": history[:2]}
    f.save(tmp_path / "final.pt", extra={"history": history})
    assert learning_curves({"DAOF-v1": load_filter(tmp_path / "best.pt")}) == {"DAOF-v1": history}


def test_learning_curve_references_are_the_validation_set_numbers_of_the_run(tmp_path):
    """The lines beside the curves come from the run's summary.json (its validation set), not the study's data."""
    import json

    from daof.experiments.runner import validation_references
    from daof.filters.learned import FilterConfig, LearnedFilter, load_filter

    f = LearnedFilter(FilterConfig(kind="DAOF-v1", system="veh2dof", window=2, num_cells=8))
    f.save(tmp_path / "slf" / "best.pt")
    f.save(tmp_path / "v1" / "best.pt")
    filters = {name: load_filter(tmp_path / name / "best.pt") for name in ("slf", "v1")}
    assert validation_references(filters) == {}  # no summary yet: no lines rather than wrong ones
    (tmp_path / "v1" / "summary.json").write_text(json.dumps({"validation_references": {"UKF": [0.0105, 0.0258]}}))
    assert validation_references(filters) == {"UKF": [0.0105, 0.0258]}
    assert validation_references(filters, ["slf"]) == {}


def test_a_reports_command_line_keeps_every_override_given():
    """The command written into a report reproduces it: pinned arguments first, then every other
    override given (quoted for a shell), a dropped key left out."""
    given = ["profile=paper", "profiles.paper.frames.DAOF-v1=3200000", "scenarios=[a,b]", "+x=1"]
    assert command_line("s.py", "profile=paper", "scenario=a", given=given, drop=["scenarios"]) == (
        "python s.py profile=paper scenario=a profiles.paper.frames.DAOF-v1=3200000 +x=1"
    )
    assert command_line("s.py", "profile=paper", given=given) == (
        "python s.py profile=paper profiles.paper.frames.DAOF-v1=3200000 'scenarios=[a,b]' +x=1"
    )
    assert command_line("s.py", "profile=quick") == "python s.py profile=quick"


def test_the_study_cache_is_keyed_on_the_systems_parameters(tmp_path):
    """A study of μ = 0.5 never reuses the cached results of μ = 0.9 (same filter, runs, steps, seed)."""
    from daof.envs import make_system

    from daof.evaluate.study import run_study
    from daof.filters import EKF

    def study(mu):
        system = make_system("veh2dof", mu=mu)
        filters = {"EKF": EKF(system)}
        return run_study(system, filters, 3, 40, 5, measure_cost=False, cache_dir=tmp_path, log=lambda _: None)

    nominal, low = study(0.9), study(0.5)
    assert nominal.results["EKF"].rmse != low.results["EKF"].rmse
    assert study(0.5).results["EKF"].rmse == low.results["EKF"].rmse  # the same system is reused
