"""KalmanNet: the recursion, its TensorDict module, missing measurements, the checkpoint and its training."""

import pytest
import torch
from tensordict import TensorDict

from daof.filters import StationaryKalmanFilter
from daof.filters.learned import KalmanNet, load_filter, make_filter
from daof.filters.learned.kalmannet import STATE_KEYS
from daof.train.config import compose_config
from daof.train.kalmannet import KalmanNetTrainer


def kalmannet(system, seed=0):
    torch.manual_seed(seed)
    filt = make_filter("KalmanNet", system=system)
    filt.fit_normalizer(runs=4, steps=100)
    return filt.eval()


def force_gain(filt, gain):
    """Replace the gain network's output by a fixed gain K (state units per measurement unit)."""
    scaled = gain.float() / filt.state_scale[:, None] * filt.measurement_scale[None, :]
    filt.gain_net.forward = lambda f1, f2, f3, f4, *hidden: (scaled.expand(f1.shape[0], *scaled.shape), *hidden)


def test_with_the_steady_state_gain_it_is_the_stationary_kalman_filter(lin):
    filt = kalmannet(lin)
    reference = StationaryKalmanFilter(lin)
    force_gain(filt, reference.gain)
    data = lin.simulate(6, 300, 11)
    assert torch.allclose(filt.run(data), reference.run(data), atol=1e-5)
    force_gain(filt, 0.5 * reference.gain)  # another gain: the check can fail
    assert (filt.run(data) - reference.run(data)).abs().max() > 1e-2


def test_streaming_through_the_tensordict_module_equals_run(veh):
    filt = kalmannet(veh)
    data = veh.simulate(3, 40, 5)
    module = filt.filter_module()
    state = filt.initial_state(3)
    td = TensorDict({("kalmannet", k): v for k, v in zip(STATE_KEYS, state)}, batch_size=[3])
    out = []
    with torch.no_grad():
        for t in range(40):
            for key in ("measurement", "prev_control", "control"):
                td[key] = data[key][:, t]
            td = module(td)
            out.append(td["action"])
            td = td.exclude("kalmannet").update({"kalmannet": td["next", "kalmannet"]}).exclude("next")
    assert torch.equal(torch.stack(out, 1), filt.run(data))
    assert torch.equal(filt.run_streaming(data), filt.run(data))


def test_a_missing_measurement_skips_the_update(lin):
    filt = kalmannet(lin)
    data = lin.simulate(4, 30, 3)
    gappy = data.clone()
    gappy["measurement"][:, 10:13] = float("nan")
    full, gapped = filt.run(data), filt.run(gappy)
    assert torch.equal(full[:, :10], gapped[:, :10])
    assert torch.isfinite(gapped).all()
    # a step without measurement only predicts: x̂_t = f(x̂_{t−1}, u_{t−1})
    for t in (10, 11, 12):
        assert torch.allclose(gapped[:, t], lin.f(gapped[:, t - 1], data["prev_control"][:, t]), atol=1e-6)
    assert (full[:, 11] - gapped[:, 11]).abs().max() > 1e-4


def test_checkpoint_round_trip_is_plain_data(lin, tmp_path):
    filt = kalmannet(lin, seed=3)
    filt.save(tmp_path / "k.pt", extra={"note": 1})
    blob = torch.load(tmp_path / "k.pt", weights_only=True)
    assert blob["config"]["kind"] == "KalmanNet" and "state_scale" in blob["state_dict"]
    back = load_filter(tmp_path / "k.pt")
    assert isinstance(back, KalmanNet)
    assert torch.equal(back.state_scale, filt.state_scale)
    data = lin.simulate(2, 50, 8)
    assert torch.equal(back.run(data), filt.run(data))


def test_veh14dof_is_refused_in_one_line():
    with pytest.raises(ValueError, match="KalmanNet predicts with the model f, g; 'veh14dof' has none"):
        make_filter("KalmanNet", system="veh14dof")


def test_a_tiny_training_lowers_the_validation_loss_and_loads(tmp_path):
    cfg = compose_config(["filter=kalmannet", "system=linear", f"output_dir={tmp_path}", "collector.env_batch=16",
                          "collector.episode_steps=50", "collector.total_frames=4000", "optim.batch_size=16",
                          "optim.bptt_steps=25", "optim.epochs_per_batch=4", "validation.runs=8", "validation.steps=60",
                          "validation.every_frames=800", "checkpoint.every_frames=4000"])  # fmt: skip
    trainer = KalmanNetTrainer(cfg)
    untrained = trainer.validate()["score"]
    summary = trainer.train()
    assert summary["updates"] == 5 * 4 * 2  # batches · epochs · segments of bptt_steps
    assert summary["best"]["score"] < 0.8 * untrained
    filt = load_filter(tmp_path / "best.pt", expect={"kind": "KalmanNet"})
    assert filt.run(filt.system.simulate(2, 20, 1)).shape == (2, 20, 2)
