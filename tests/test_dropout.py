"""The study's sensor-dropout option (daof.evaluate.dropout) and ``run_study(..., dropout=...)``.

Pins down: the mask is reproducible from its seed and has the asked-for gap rate; the blackout
covers exactly the asked-for channel and seconds in every run; ``apply_dropout`` copies and only
blanks measurements; bad options fail clearly; a dropout study gives every classical filter finite
estimates, records what was missing, shows it in the report, and is cached apart from the
complete-data study.
"""

import json
import math

import pytest
import torch
from daof.envs.gaps import training_dropout_mask

from daof.evaluate import Dropout, apply_dropout, dropout_mask, run_study
from daof.evaluate.report import write_report
from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter


def test_mask_is_reproducible_from_its_seed_with_the_asked_for_rate():
    shape = (20, 500, 2)
    mask = dropout_mask(shape, 0.1, seed=3)
    assert mask.shape == shape and mask.dtype == torch.bool
    assert torch.equal(mask, dropout_mask(shape, 0.1, seed=3))
    assert not torch.equal(mask, dropout_mask(shape, 0.1, seed=4))
    n = mask.numel()
    assert abs(mask.float().mean().item() - 0.1) < 5 * math.sqrt(0.1 * 0.9 / n)  # binomial, 5 σ
    assert not dropout_mask(shape, 0.0).any() and dropout_mask(shape, 1.0).all()


def test_training_gaps_spread_their_rate_and_black_out_one_channel_in_half_the_runs():
    """Per-run gap rates ~ U[0, p_max] (mean p_max / 2); blackouts are one channel, one contiguous
    stretch of at most blackout_s seconds, in about half the runs; same generator state, same mask."""
    shape, dt = (4000, 200, 3), 0.02
    gaps = training_dropout_mask(shape, 0.2, 0.0, dt, torch.Generator().manual_seed(0))
    rates = gaps.float().mean((1, 2))
    assert abs(rates.mean().item() - 0.1) < 0.005 and rates.max() < 0.25 and rates.min() < 0.01
    assert not training_dropout_mask(shape, 0.0, 0.0, dt, torch.Generator().manual_seed(0)).any()
    lost = training_dropout_mask(shape, 0.0, 1.0, dt, torch.Generator().manual_seed(1))
    assert torch.equal(lost, training_dropout_mask(shape, 0.0, 1.0, dt, torch.Generator().manual_seed(1)))
    per_run = lost.any(1)  # [runs, channels]
    assert per_run.sum(-1).max() == 1  # one channel at most
    assert abs(per_run.any(-1).float().mean().item() - 0.5) < 0.05
    steps = lost.any(-1)  # [runs, steps]
    assert steps.sum(-1).max() <= round(1.0 / dt)
    edges = (steps[:, 1:] != steps[:, :-1]).sum(-1) + steps[:, 0] + steps[:, -1]
    assert edges.max() <= 2  # one contiguous stretch
    with pytest.raises(ValueError, match="training dropout"):
        training_dropout_mask(shape, 1.5, 0.0, dt, torch.Generator())


def test_blackout_covers_the_channel_for_its_seconds_in_every_run():
    dt, steps = 0.02, 500
    mask = dropout_mask(
        (4, steps, 2), 0.0, ("yaw_rate", 4.0, 1.0), dt=dt, channel_names=("lateral_acceleration", "yaw_rate")
    )
    assert not mask[..., 0].any()
    # data index k is time (k + 1)·dt: 4.00 s is k = 199, the last step before 5.00 s is k = 248
    expected = torch.zeros(steps, dtype=torch.bool)
    expected[199:249] = True
    assert expected.sum() == 50  # 1 s at 0.02 s
    assert (mask[..., 1] == expected).all()
    # by index as well, on top of random gaps that stay where they were
    gaps = dropout_mask((4, steps, 2), 0.2, seed=1)
    both = dropout_mask((4, steps, 2), 0.2, (1, 4.0, 1.0), seed=1, dt=dt)
    assert torch.equal(both, gaps | mask)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"p": 1.5}, "probability"),
        ({"p": -0.1}, "probability"),
        ({"blackout": ("yaw_rate", 4.0, 1.0)}, "dt"),
        ({"blackout": ("steering", 4.0, 1.0), "dt": 0.02, "channel_names": ("a", "yaw_rate")}, "'steering'"),
        ({"blackout": (2, 4.0, 1.0), "dt": 0.02}, "out of range"),
        ({"blackout": (1, 9.5, 1.0), "dt": 0.02}, "does not fit"),
        ({"blackout": (1, 4.0, 0.0), "dt": 0.02}, "duration_s > 0"),
    ],
)
def test_bad_dropout_options_raise(kwargs, match):
    kwargs = {"p": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        dropout_mask((2, 500, 2), **kwargs)


def test_apply_dropout_copies_and_only_blanks_measurements(veh):
    data = veh.simulate(3, 300, seed=1)
    before = data.clone()
    out = Dropout(p=0.2, blackout=("yaw_rate", 2.0, 1.0), seed=5).apply(data, veh)
    assert torch.equal(data["measurement"], before["measurement"])  # the input is untouched
    for key in ("state", "control", "prev_control"):
        assert torch.equal(out[key], data[key])
    missing = torch.isnan(out["measurement"])
    expected = dropout_mask(
        (3, 300, 2), 0.2, ("yaw_rate", 2.0, 1.0), seed=5, dt=veh.dt, channel_names=("a", "yaw_rate")
    )
    assert torch.equal(missing, expected)
    assert torch.equal(out["measurement"][~missing], data["measurement"][~missing])
    again = apply_dropout(data, 0.2, ("yaw_rate", 2.0, 1.0), 5, dt=veh.dt, channel_names=veh.measurement_names)
    assert torch.equal(torch.isnan(again["measurement"]), missing)


def test_dropout_study_gives_every_classical_filter_finite_estimates_and_a_report(veh, tmp_path):
    dropout = Dropout(p=0.2, blackout=("yaw_rate", 2.0, 1.0), seed=1)
    filters = {"EKF": EKF(veh), "UKF": UKF(veh), "PF": ParticleFilter(veh, 300, seed=1)}
    study = run_study(veh, filters, runs=3, steps=300, seed=77, measure_cost=False, log=lambda _: None, dropout=dropout)
    missing = study.dropout["missing_fraction"]
    assert missing[0] == pytest.approx(0.2, abs=0.05) and missing[1] > missing[0]  # the blackout adds 1/6
    assert torch.isnan(study.data["measurement"][:, 99:149, 1]).all()
    prior_std = veh.prior.covariance.diagonal().sqrt().tolist()
    for name, estimate in study.estimates.items():
        assert torch.isfinite(estimate).all(), name
        assert study.results[name].diverged == 0
        assert all(e < s for e, s in zip(study.results[name].rmse, prior_std)), (name, study.results[name].rmse)
    assert study.to_json()["dropout"] == study.dropout
    report = write_report(study, tmp_path, title="dropout", profile="test")
    text = report.read_text()
    assert "**Sensor dropout**" in text and "`yaw_rate` blacked out from 2 s for 1 s" in text
    assert json.loads((tmp_path / "results.json").read_text())["dropout"]["p"] == 0.2


def test_dropout_results_are_cached_apart_from_complete_data(lin, tmp_path):
    filters = {"KF": KalmanFilter(lin)}
    logs = []
    kwargs = {"runs": 2, "steps": 100, "seed": 5, "measure_cost": False, "cache_dir": tmp_path, "log": logs.append}
    complete = run_study(lin, filters, **kwargs)
    gappy = run_study(lin, filters, **kwargs, dropout=Dropout(p=0.3, blackout=None))
    assert not any("reused" in line for line in logs)  # the dropout study did not pick up the complete one
    assert complete.dropout is None and "dropout" not in complete.to_json()
    assert not torch.equal(gappy.estimates["KF"], complete.estimates["KF"])
    assert len(list(tmp_path.glob("KF*.pt"))) == 2
    logs.clear()
    again = run_study(lin, filters, **kwargs, dropout=Dropout(p=0.3, blackout=None))
    other = run_study(lin, filters, **kwargs, dropout=Dropout(p=0.3, blackout=None, seed=1))
    assert sum("reused" in line for line in logs) == 1  # the same dropout is reused, another seed is not
    assert torch.equal(again.estimates["KF"], gappy.estimates["KF"])
    assert not torch.equal(other.estimates["KF"], gappy.estimates["KF"])
