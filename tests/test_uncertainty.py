"""Uncertainty out of the filters: the error std beside each estimate (``run_with_std``), the learned
filters' uncertainty head, the calibration metrics (NEES, ±2σ coverage) and the study's fields."""

import json
import math

import pytest
import torch

from daof.evaluate import run_study
from daof.evaluate.metrics import GAUSSIAN_COVERAGE, calibration
from daof.evaluate.report import write_report
from daof.filters import EKF, UKF, Filter, KalmanFilter, ParticleFilter, StationaryKalmanFilter
from daof.filters.learned import load_filter, make_filter
from daof.filters.learned.uncertainty import file_digest, head_path, load_head
from daof.train.uncertainty import HeadSettings, fit_head, gaussian_nll, main


def _gaussian_errors(runs=200, steps=500, sigma=(0.5, 3.0), seed=0):
    g = torch.Generator().manual_seed(seed)
    std = torch.tensor(sigma).expand(runs, steps, len(sigma))
    truth = torch.randn(runs, steps, len(sigma), generator=g)
    return truth + std * torch.randn(runs, steps, len(sigma), generator=g), truth, std


def test_calibration_of_gaussian_errors_with_the_right_sigma():
    estimates, truth, std = _gaussian_errors()
    c = calibration(estimates, truth, std)
    assert c["nees"] == pytest.approx([1.0, 1.0], abs=0.02)
    assert c["coverage"] == pytest.approx([GAUSSIAN_COVERAGE] * 2, abs=0.003)
    assert c["excluded"] == [0, 0]


@pytest.mark.parametrize("factor", [0.5, 2.0])
def test_calibration_detects_a_sigma_wrong_by_two(factor):
    """σ claimed half the truth: NEES 4, coverage P(|z| ≤ 1) = 68 %; twice: NEES 1/4, coverage P(|z| ≤ 4)."""
    estimates, truth, std = _gaussian_errors()
    c = calibration(estimates, truth, std * factor)
    expected_cover = math.erf(2 * factor / math.sqrt(2))
    assert c["nees"] == pytest.approx([1 / factor**2] * 2, rel=0.03)
    assert c["coverage"] == pytest.approx([expected_cover] * 2, abs=0.004)


def test_calibration_counts_non_finite_and_zero_sigma_without_crashing():
    estimates, truth, std = _gaussian_errors(runs=4, steps=50)
    std = std.clone()
    std[0, 0, 0], std[0, 1, 0], std[0, 2, 0], std[1, 0, 1] = 0.0, math.nan, math.inf, -1.0
    estimates = estimates.clone()
    estimates[2, :, 1] = math.nan  # a diverged run's estimates
    c = calibration(estimates, truth, std)
    assert c["excluded"] == [3, 1 + 50]
    assert all(math.isfinite(v) for v in c["nees"] + c["coverage"])
    assert calibration(estimates, truth, torch.zeros_like(std))["excluded"] == [200, 200]
    assert math.isnan(calibration(estimates, truth, torch.zeros_like(std))["nees"][0])
    with pytest.raises(ValueError, match="std and estimates must both be"):
        calibration(estimates, truth, std[..., :1])


@pytest.mark.parametrize("cls", [KalmanFilter, StationaryKalmanFilter])
def test_the_kalman_filter_is_calibrated_on_the_linear_system(lin, cls):
    """Its covariance is the exact error covariance: NEES ≈ 1 and 95.45 % coverage over 200 runs (the stationary
    filter's too: its std is the Joseph-form covariance of its fixed gain, wide in the start-up)."""
    data = lin.simulate(200, 200, 11)
    kf = cls(lin)
    estimates, std = kf.run_with_std(data)
    assert kf.std_source == "covariance" and std.shape == estimates.shape
    assert torch.equal(estimates, kf.run(data))  # the same estimates; run pays nothing for the std
    c = calibration(estimates, data["state"], std)
    assert c["nees"] == pytest.approx([1.0, 1.0], abs=0.08)
    assert c["coverage"] == pytest.approx([GAUSSIAN_COVERAGE] * 2, abs=0.01)
    # the wrong std (2x) on the same errors is caught
    assert all(v > 3 for v in calibration(estimates, data["state"], std / 2)["nees"])


def test_classical_filters_give_their_std_beside_run_s_estimates(veh):
    data = veh.simulate(3, 40, 2)
    for filt in (EKF(veh), UKF(veh), ParticleFilter(veh, 300, seed=1)):
        estimates, std = filt.run_with_std(data)
        assert torch.equal(estimates, filt.run(data)), filt.name
        assert std.shape == estimates.shape and bool((std > 0).all()), filt.name
    assert ParticleFilter(veh).std_source == "particle spread"


def test_a_filter_without_std_returns_none(lin):
    class Prior(Filter):
        name = "prior"

        def _run(self, y, u_prev, u):
            return self.system.prior.mean.expand(*y.shape[:2], -1).clone()

    data = lin.simulate(2, 10, 0)
    estimates, std = Prior(lin).run_with_std(data)
    assert std is None and estimates.shape == (2, 10, 2)
    assert make_filter("SLF", system="linear", num_cells=16).run_with_std(data)[1] is None  # no head fitted


def _tiny(kind, system="linear"):
    torch.manual_seed(0)  # the untrained filter's weights
    f = make_filter(kind, system=system, window=4, num_cells=16)
    f.fit_normalizer(runs=4, steps=50)
    return f.eval().requires_grad_(False)


@pytest.mark.parametrize("kind", ["SLF", "DAOF-v1", "DAOF-v2", "KalmanNet"])
def test_a_tiny_learned_filters_head_trains_and_gives_positive_std(kind, tmp_path):
    f = _tiny(kind)
    settings = HeadSettings(runs=32, steps=100, epochs=10, batch_size=128, lr=1e-2, num_cells=16)
    head, record = fit_head(f, settings, seed=5, log=lambda *_: None)
    # the head learnt what a constant σ per state does not hold (the start-up's wide errors): by 0.21-1.3 nats
    assert min(record["held_out_nll"]) < record["held_out_nll_constant"] - 0.1
    assert fit_head(f, settings, seed=5, log=lambda *_: None)[1]["held_out_nll"] == record["held_out_nll"]
    f.attach_uncertainty(head)
    data = f.system.simulate(3, 30, 1)
    estimates, std = f.run_with_std(data)
    assert f.std_source == "uncertainty head"
    assert std.shape == (3, 30, f.system.state_dim) and bool(torch.isfinite(std).all() and (std > 0).all())
    assert torch.equal(estimates, f.run(data))  # the head never changes the estimates
    assert not any(k.startswith("_uncertainty") for k in f.state_dict())  # the checkpoint stays the filter


def test_the_head_loads_with_its_checkpoint_and_only_with_it(tmp_path):
    from daof.filters.learned.uncertainty import file_digest, save_head

    f = _tiny("SLF")
    head, record = fit_head(f, HeadSettings(runs=8, steps=40, epochs=2, num_cells=16), seed=5, log=lambda *_: None)
    f.save(tmp_path / "best.pt")
    save_head(head, head_path(tmp_path / "best.pt"), file_digest(tmp_path / "best.pt"), record)
    loaded = load_filter(tmp_path / "best.pt")
    data = f.system.simulate(2, 20, 3)
    f.attach_uncertainty(head)
    assert torch.equal(loaded.run_with_std(data)[1], f.run_with_std(data)[1])
    assert load_head(head_path(tmp_path / "best.pt")).extra["seed"] == 5
    f.save(tmp_path / "best.pt", extra={"another": "version"})  # the filter changes: its head is stale
    with pytest.warns(UserWarning, match="fitted to another filter checkpoint"):
        stale = load_filter(tmp_path / "best.pt")
    assert stale.uncertainty is None and stale.std_source is None
    with pytest.raises(ValueError, match="this filter has"):
        _tiny("SLF", system="veh2dof").attach_uncertainty(head)


def test_gaussian_nll_is_lowest_at_the_true_variance():
    errors = torch.randn(20000, 1, generator=torch.Generator().manual_seed(0)) * 3.0
    nll = [gaussian_nll(torch.full_like(errors, math.log(v)), errors).item() for v in (4.0, 9.0, 16.0)]
    assert nll[1] < nll[0] and nll[1] < nll[2]


def test_the_command_fits_a_head_beside_a_run_s_checkpoint(tmp_path, capsys):
    f = _tiny("DAOF-v2")
    f.save(tmp_path / "best.pt")
    (tmp_path / "run_config.json").write_text(json.dumps({"system": "linear", "seeds": {"train": 3}}))
    main([str(tmp_path), "--runs", "8", "--steps", "40", "--epochs", "2", "--num-cells", "16"])
    out = capsys.readouterr().out
    assert "held-out runs (1): NEES" in out and "±2σ coverage" in out
    head = load_head(tmp_path / "best.uncertainty.pt")
    assert head.extra["seed"] == 424_242_003  # HEAD_SEED + the run's training seed
    assert load_filter(tmp_path / "best.pt").std_source == "uncertainty head"
    with pytest.raises(SystemExit, match="validation or evaluation seed"):
        main([str(tmp_path), "--runs", "8", "--steps", "40", "--seed", "20261122"])


def test_the_study_writes_the_calibration_fields_and_figure(lin, tmp_path):
    class Prior(Filter):
        name = "prior"

        def _run(self, y, u_prev, u):
            return self.system.prior.mean.expand(*y.shape[:2], -1).clone()

    slf = _tiny("SLF")
    head, _ = fit_head(slf, HeadSettings(runs=8, steps=40, epochs=2, num_cells=16), seed=5, log=lambda *_: None)
    slf.attach_uncertainty(head)
    filters = {"KF": KalmanFilter(lin), "SLF": slf, "prior": Prior(lin)}
    study = run_study(lin, filters, runs=6, steps=40, seed=1, measure_cost=False, log=lambda *_: None, reference="KF")
    kf = study.results["KF"]
    assert kf.std_source == "covariance" and len(kf.nees) == 2 and len(kf.coverage_2sigma) == 2
    assert kf.std_excluded == [0, 0] and all(0.0 <= v <= 1.0 for v in kf.coverage_2sigma)
    assert study.results["SLF"].std_source == "uncertainty head"
    assert study.results["prior"].nees is None and study.results["prior"].std_source is None
    write_report(study, tmp_path, title="calibration", profile="tiny")
    results = json.loads((tmp_path / "results.json").read_text())["filters"]
    assert results["KF"]["nees"] == pytest.approx(kf.nees) and results["prior"]["coverage_2sigma"] is None
    text = (tmp_path / "report.md").read_text()
    section = text.split("## Calibration of the error std", 1)[1].split("\n## ", 1)[0]
    assert "| KF | covariance |" in section and "| SLF | uncertainty head |" in section and "| prior |" not in section
    assert (tmp_path / "calibration.png").is_file() and "![calibration](calibration.png)" in text
    header = (tmp_path / "results.csv").read_text().splitlines()[0]
    assert header.endswith("nees_position,nees_velocity,coverage_2sigma_position,coverage_2sigma_velocity")
    quiet = {"measure_cost": False, "log": lambda *_: None}
    without = run_study(lin, filters, runs=6, steps=40, seed=1, calibrate=False, **quiet)
    assert all(r.nees is None for r in without.results.values())


def test_an_experiment_fits_a_head_once_per_checkpoint(tmp_path, monkeypatch):
    from daof.experiments import jobs
    from daof.experiments.jobs import HeadJob, TrainingJob, run_jobs

    monkeypatch.setattr(jobs, "_ray_installed", lambda: False)  # its own process, one at a time (Ray: tiny profile)
    f = _tiny("SLF")
    f.save(tmp_path / "best.pt")
    (tmp_path / "run_config.json").write_text(json.dumps({"system": "linear", "seeds": {"train": 2}}))
    job = HeadJob(TrainingJob("SLF", tmp_path, 100), HeadSettings(runs=8, steps=40, epochs=2, num_cells=16))
    messages = []
    started = "uncertainty head: fitting, log " + str(tmp_path / "uncertainty.log")
    fits = lambda: sum(m.endswith(started) for m in messages)  # noqa: E731
    path = head_path(tmp_path / "best.pt")
    assert not job.finished()
    run_jobs([job], log=messages.append)
    first = path.read_bytes()
    assert fits() == 1 and job.finished() and load_head(path).extra["seed"] == 424_242_002
    assert "held-out runs (1): NEES" in (tmp_path / "uncertainty.log").read_text()
    run_jobs([job], log=messages.append)
    assert fits() == 1 and path.read_bytes() == first  # kept: fitted to this best.pt
    f.save(tmp_path / "best.pt", extra={"retrained": True})  # a new best.pt: its head is fitted again
    assert not job.finished()
    run_jobs([job], log=messages.append)
    assert fits() == 2 and load_head(path, file_digest(tmp_path / "best.pt")) is not None
