"""Training runs: a checkpoint restores every piece of state exactly, and the run finishes."""

import math
import re
from pathlib import Path

import pytest
import torch
from daof.envs.filtering_env import FEEDBACK_KEY
from daof.envs.gaps import training_dropout_mask
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict

from daof.filters.learned import load_filter
from daof.train.config import compose_config
from daof.train.dsac import MAX_EXPLORATION_STD, DSACTTrainer
from daof.train.supervised import SLFTrainer, gap_seed
from daof.train.validation import rmse_per_state

FILTERS = {"v1": "daof_v1", "v2": "daof_v2"}


def tiny_cfg(name: str, out: Path, **changes):
    """A training config as ``python -m daof.train`` composes it, made tiny.

    ``name`` "config.yaml" is DAOF (``version`` v1, the default, or v2: DAOF-v2, the paper's x̂ = π(h)),
    "slf.yaml" the SLF; ``system`` picks the system (default veh2dof).
    """
    version = changes.pop("version", "v1")
    filter_ = "slf" if name == "slf.yaml" else FILTERS[version]
    cfg = compose_config([f"filter={filter_}", f"system={changes.pop('system', 'veh2dof')}"])
    cfg.output_dir = str(out)
    cfg.logger.backend = "csv"
    cfg.network.num_cells = 16
    cfg.validation.runs, cfg.validation.steps, cfg.validation.every_frames = 2, 30, 200
    cfg.collector.env_batch = 4
    cfg.checkpoint.every_frames = 200
    if name == "config.yaml":
        cfg.collector.steps_per_batch = 25
        cfg.collector.warmup_frames = 100
        cfg.buffer.size = 1000
        cfg.optim.batch_size = 32
    else:
        cfg.collector.episode_steps = 50
    for key, value in changes.items():
        OmegaConf.update(cfg, key, value)
    return cfg


def flat_tensors(obj, prefix=""):
    """Every tensor in a nested checkpoint dict, by path."""
    out = {}
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
    elif isinstance(obj, TensorDict):
        out.update({f"{prefix}/{k}": v for k, v in obj.flatten_keys("/").items()})
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flat_tensors(v, f"{prefix}/{k}"))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out.update(flat_tensors(v, f"{prefix}/{i}"))
    return out


def assert_same_state(a: dict, b: dict):
    """Bit-identical (NaN == NaN: a replay storage's unfilled rows are uninitialised memory)."""
    ta, tb = flat_tensors(a), flat_tensors(b)
    assert ta.keys() == tb.keys()
    for key in ta:
        torch.testing.assert_close(ta[key], tb[key], rtol=0, atol=0, equal_nan=True, msg=key)


@pytest.mark.parametrize("version", ["v1"])
def test_dsac_resume_restores_everything_and_finishes(tmp_path, version):
    """Stop after a checkpoint, resume with a larger budget: networks, targets, optimisers, α, σ̄,
    counters, RNG and replay buffer come back exactly as saved, and the resumed run completes its
    budget. (That a resumed run is the uninterrupted one, for v1, v2 and a replayed env:
    tests/test_resume_continuity.py.)"""
    first = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, version=version, **{"collector.total_frames": 400}))
    first.train()
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert saved["training"]["frames"] == 400 and saved["training"]["updates"] > 0
    assert bool(saved["loss"]["sigma_bar_initialised"])

    second = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, version=version, **{"collector.total_frames": 800}))
    second.resume(tmp_path / "checkpoint.pt")
    restored = second.state_dict()
    for part in ("filter", "loss", "optim_critic", "optim_actor", "optim_alpha", "buffer", "rng"):
        assert_same_state(saved[part], restored[part])
    assert restored["training"]["frames"] == 400
    assert restored["training"]["updates"] == saved["training"]["updates"]
    assert len(second.buffer) == len(first.buffer)

    summary = second.train()
    assert summary["frames"] == 800
    assert summary["updates"] > saved["training"]["updates"]
    assert (tmp_path / "best.pt").is_file() and (tmp_path / "learning_curve.png").is_file()


def test_dsac_resume_deals_the_same_bank_episodes(tmp_path):
    """With a replayed env, the checkpoint holds the undealt bank episodes and a resume restores them."""

    def cfg(total_frames):
        c = tiny_cfg("config.yaml", tmp_path, version="v2", **{"collector.total_frames": total_frames})
        c.collector.episode_steps = 50
        with open_dict(c):
            c.overrides.replay = {"runs": 15, "steps": 50, "seed": 1}
        return c

    DSACTTrainer(cfg(400)).train()
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    deck = saved["episode_bank"]["deck"]
    assert 0 < len(deck) < 15 and len(set(deck.tolist())) == len(deck)  # a pass under way

    second = DSACTTrainer(cfg(800))
    second.resume(tmp_path / "checkpoint.pt")
    assert torch.equal(second.state_dict()["episode_bank"]["deck"], deck)


def test_resume_refuses_another_run(tmp_path):
    DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 200})).train()
    other = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "b", window=5, **{"collector.total_frames": 200}))
    with pytest.raises(ValueError, match="window=20, this run has 5"):
        other.resume(tmp_path / "checkpoint.pt")
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        other.resume(tmp_path / "nothing.pt")


def test_an_old_v2_action_override_or_checkpoint_is_read_as_the_removed_option(tmp_path):
    """``network.v2_action`` was removed on 2026-12-07 with DAOF-v2's increment form: its surviving value
    ``estimate`` is ignored (an override of it, a checkpoint or run_config.json that names it: every run
    before the removal names it, whatever its kind), ``increment`` refuses to resume in one line."""
    import json

    from daof.train.base import comparable_config

    assert compose_config(["filter=daof_v2", "network.v2_action=estimate"]) == compose_config(["filter=daof_v2"])
    assert compose_config(["filter=daof_v2", "~network.v2_action"]) == compose_config(["filter=daof_v2"])
    cfg = tiny_cfg("config.yaml", tmp_path, version="v2", **{"collector.total_frames": 200})
    DSACTTrainer(cfg).train()
    blob = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    run_config = json.loads((tmp_path / "run_config.json").read_text())
    assert "v2_action" not in run_config["network"]
    now = OmegaConf.to_container(cfg, resolve=True)
    for kind in ("DAOF-v1", "DAOF-v2", "SLF"):  # run_config.json before the removal: an experiment reuses it
        old = {**now, "kind": kind, "network": {**now["network"], "v2_action": "estimate"}}
        assert comparable_config(old) == comparable_config({**now, "kind": kind})
    increment = {**now, "network": {**now["network"], "v2_action": "increment"}}
    assert comparable_config(increment) != comparable_config(now)  # another filter: not reused
    # a key added since (network.reference_gain, 2026-12-08): a run written before it is the default's run
    before = {**now, "network": {k: v for k, v in now["network"].items() if k != "reference_gain"}}
    assert "reference_gain" in now["network"] and comparable_config(before) == comparable_config(now)
    paper_form = {**now, "network": {**now["network"], "reference_gain": False}}
    assert comparable_config(paper_form) != comparable_config(before)
    for value in ("estimate", "increment"):
        path = tmp_path / f"{value}.pt"
        network = {**blob["config"]["network"], "v2_action": value}
        torch.save({**blob, "config": {**blob["config"], "network": network}}, path)
        later = {"collector.total_frames": 400}
        resumed = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / value, version="v2", **later))
        if value == "estimate":
            resumed.resume(path)
            assert resumed.frames == 200
            resumed._release_directory()
            continue
        with pytest.raises(ValueError) as error:
            resumed.resume(path)
        message = str(error.value)
        assert "\n" not in message and message.startswith(f"checkpoint {path} cannot be resumed: "), message
        assert "network.v2_action='increment' was removed on 2026-12-07" in message
        assert "docs/log/2026-12-07-daof-v2-increment-form-removed.md" in message


def test_slf_learns_and_resumes(tmp_path):
    """A few SLF batches already beat the raw yaw-rate measurement; resume continues the run.

    On complete data: through the default's random gaps this tiny budget is not enough to learn."""
    plain = {"network.num_cells": 32, "network.missing_mask": False, "dropout.p_max": 0.0, "dropout.blackout_s": 0.0}
    cfg = tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 1000, **plain})
    SLFTrainer(cfg).train()
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    cfg = tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 4000, **plain})
    trainer = SLFTrainer(cfg)
    trainer.resume(tmp_path / "checkpoint.pt")
    assert_same_state(saved["optim"], trainer.state_dict()["optim"])
    summary = trainer.train()
    assert summary["frames"] == 4000
    # raw yaw-rate measurement error is about 0.14 rad/s (Laplace b = 0.1): clearly below it
    assert summary["best"]["record"]["rmse_yaw_rate"] < 0.85 * 0.14


def test_slf_trains_through_random_gaps_with_a_missing_mask(tmp_path):
    """``dropout`` blanks entries of each batch (the same ones on a rerun) and ``network.missing_mask``
    flags them; the run finishes and its filter keeps the mask."""
    changes = {
        "collector.total_frames": 400,
        "network.missing_mask": True,
        "dropout.p_max": 0.3,
        "dropout.blackout_s": 0.5,
    }
    trainer = SLFTrainer(tiny_cfg("slf.yaml", tmp_path / "a", **changes))
    windows, _ = trainer._dataset()
    flags = windows.view(windows.shape[0], trainer.cfg.window, -1)[..., -trainer.system.measurement_dim :]
    assert 0 < flags.mean() < 0.3 and set(flags.unique().tolist()) == {0.0, 1.0}
    again, _ = SLFTrainer(tiny_cfg("slf.yaml", tmp_path / "b", **changes))._dataset()
    assert torch.equal(windows, again)
    assert trainer.train()["frames"] == 400
    assert torch.load(tmp_path / "a" / "best.pt", weights_only=False)["config"]["missing_mask"] is True


def test_slf_training_gaps_are_drawn_independently_of_the_simulation_noise(tmp_path):
    """The gaps of a batch come from ``gap_seed(simulation seed)``, never from the simulation's own seed
    (the same seed would tie the gap pattern to the noise draws)."""
    changes = {"network.missing_mask": True, "dropout.p_max": 0.3, "dropout.blackout_s": 0.5}
    trainer = SLFTrainer(tiny_cfg("slf.yaml", tmp_path, **changes))
    seed = trainer.batch_seed()
    windows, _ = trainer._dataset()
    c, dim = trainer.cfg.collector, trainer.system.measurement_dim
    runs, steps = int(c.env_batch), int(c.episode_steps)
    flags = windows.view(runs, steps, trainer.cfg.window, -1)[:, :, -1, -dim:].bool()  # each window's newest frame
    assert gap_seed(seed) != seed and gap_seed(seed) == gap_seed(seed)

    def mask(s):
        return training_dropout_mask((runs, steps, dim), 0.3, 0.5, trainer.system.dt, torch.Generator().manual_seed(s))

    assert torch.equal(flags, mask(gap_seed(seed)))
    assert not torch.equal(flags, mask(seed))


def test_filter_and_system_groups_give_each_row_its_settings(tmp_path):
    """filter=... picks a kind's defaults; a system's tuning file changes only what that system needs."""
    v1, v2 = (tiny_cfg("config.yaml", tmp_path, version=v) for v in ("v1", "v2"))
    settings = ("reward.baseline", "network.critic_form", "collector.episode_steps", "network.window_init")
    assert [OmegaConf.select(v1, key) for key in settings] == ["zero_action", "quadratic", 500, "newest"]
    assert [OmegaConf.select(v2, key) for key in settings] == ["none", "reward_quadratic", 100, "uniform"]
    assert (v1.kind, v2.kind) == ("DAOF-v1", "DAOF-v2") and v2.loss.alpha_init == pytest.approx(math.e)
    # every system trains DAOF-v2 in the paper's form (its only one) with the reward-spread critic; veh14dof
    # changes its budget
    for s in ("veh2dof", "linear", "veh14dof"):
        cfg = compose_config(["filter=daof_v2", f"system={s}"])
        assert "v2_action" not in cfg.network
        settings = (cfg.network.critic_form, cfg.network.critic_scale, cfg.loss.gamma)
        assert settings == ("reward_quadratic", "reward", 0.0)
    e2 = compose_config(["filter=daof_v2", "system=veh14dof"])
    assert (e2.collector.episode_steps, e2.optim.utd, e2.include_controls) == (500, 0.125, False)
    assert compose_config(["filter=slf", "system=veh14dof"]).optim.epochs_per_batch == 8


@pytest.mark.parametrize(
    "override, message",
    [
        ("windw=5", "unknown config key 'windw'; did you mean 'window'?"),
        ("+windw=5", "unknown config key 'windw'"),
        ("window=abc", "could not be converted to Integer"),
        ("window=0", "window must be >= 1"),
        ("system=foo", "unknown system 'foo'; valid: linear, veh14dof, veh2dof"),
        ("filter=daof_v3", "unknown filter 'daof_v3'"),
        ("scenario=foo", "unknown scenario 'foo' for veh2dof"),
        ("overrides.no_such=1", "unknown parameter"),
        ("optim.utd=-1", "optim.utd must be > 0"),
        ("collector.total_frames=0", "collector.total_frames must be >= 1"),
        ("collector.total_frames=8000", "trains nothing"),
        ("network.critic_form=cubic", "network.critic_form='cubic' is not valid"),
        ("dropout.p_max=0.2", "DAOF trains on complete data"),
        ("optim.lr_final=0", "optim.lr_final must be in"),
        (
            "network.v2_action=increment",
            "network.v2_action='increment' was removed on 2026-12-07 with DAOF-v2's increment form "
            "(docs/log/2026-12-07-daof-v2-increment-form-removed.md)",
        ),
        ("+network.v2_action=jump", "network.v2_action='jump' was removed on 2026-12-07"),
    ],
)
def test_a_bad_config_is_refused_in_one_line_before_any_work(override, message):
    with pytest.raises(ValueError, match=re.escape(message)) as error:
        compose_config([override])
    assert "\n" not in str(error.value)


def test_target_entropy_is_sized_from_the_error_scale(tmp_path):
    """auto: the entropy of Gaussian noise of k error scales per state, in the actor's action units."""
    for version in ("v1", "v2"):
        trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / version, version=version))
        raw = 0.4 * trainer.system.error_scale / trainer.filter.action_scale  # v1 acts in units of its bound
        cap = MAX_EXPLORATION_STD * (trainer.filter.high - trainer.filter.low) / 2
        # v2's noise (its estimate's units) is below the cap; v1's residual bound (0.5 · √P⁺) is tighter than
        # 0.4 error scales
        assert (raw < cap).all() if version == "v2" else (raw > cap).all()
        expected = float(torch.log(torch.minimum(raw, cap) * math.sqrt(2 * math.pi * math.e)).sum())
        assert trainer.loss.target_entropy == pytest.approx(expected)
    # noise wider than the action range cannot be reached: each std is capped, in action units
    wide = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "wide", **{"loss.exploration_std": 10.0}))
    capped = math.log(MAX_EXPLORATION_STD * math.sqrt(2 * math.pi * math.e))
    assert wide.loss.target_entropy == pytest.approx(2 * capped)
    assert wide.loss.target_entropy < 2 * math.log(2.0)
    cfg = tiny_cfg("config.yaml", tmp_path / "fixed", **{"loss.target_entropy": -3.0})
    assert DSACTTrainer(cfg).loss.target_entropy == pytest.approx(-3.0)
    with pytest.raises(ValueError, match="exploration_std must be > 0"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "bad", **{"loss.exploration_std": 0.0}))
    with pytest.raises(ValueError, match=r"target_entropy=1.5 is unreachable"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "high", **{"loss.target_entropy": 1.5}))


def test_startup_schedules_of_a_dsac_run(tmp_path):
    """reward.weights=kalman: W_t rises from below W to W (non-decreasing) and the env uses it; v1's
    bound b_t = k·√diag P⁺_t and innovation scale come from the same UKF; constant weights switch the
    weights off and keep the bound."""
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "k", version="v1"))
    system = trainer.system
    w = 1.0 / (system.state_dim * system.error_scale**2)
    schedule = trainer.reward_weights
    assert schedule.shape == (trainer.filter.correction_scale.shape[0], system.state_dim)
    assert (schedule[0] < 0.9 * w).all() and (schedule.diff(dim=0) >= 0).all()
    torch.testing.assert_close(schedule[-1], w)
    assert trainer.base_env.reward_weights is schedule
    assert (trainer.filter.correction_scale[0] > trainer.filter.correction_scale[-1]).any()
    assert (trainer.filter.policy.innovation_scale[0] > trainer.filter.policy.innovation_scale[-1]).all()
    plain = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "c", version="v1", **{"reward.weights": "constant"}))
    assert plain.reward_weights is None
    torch.testing.assert_close(plain.filter.correction_scale, trainer.filter.correction_scale)


def test_learning_rates_follow_a_cosine_to_the_final_fraction(tmp_path):
    """optim.lr_final: lr at frame 0, lr · final at the budget, the cosine's midpoint halfway; 1 keeps lr."""
    cfg = tiny_cfg("config.yaml", tmp_path / "lr", **{"optim.lr_final": 0.1, "collector.total_frames": 1000})
    trainer = DSACTTrainer(cfg)
    lr = float(cfg.optim.lr_actor)
    for frames, factor in ((0, 1.0), (500, 0.55), (1000, 0.1), (4000, 0.1)):
        trainer.frames = frames
        assert trainer.set_learning_rates() == pytest.approx(factor)
        assert trainer.optim_actor.param_groups[0]["lr"] == pytest.approx(lr * factor)
        assert trainer.optim_critic.param_groups[0]["lr"] == pytest.approx(float(cfg.optim.lr_critic) * factor)
    constant = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "c", **{"optim.lr_final": 1.0}))
    constant.frames = 700
    assert constant.set_learning_rates() == pytest.approx(1.0)


def test_slf_learning_rate_follows_the_same_cosine(tmp_path):
    """The SLF's ``optim.lr_final``: its Adam lr after the last batch is lr times the cosine at the budget."""
    cfg = tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 1000, "optim.lr_final": 0.2})
    trainer = SLFTrainer(cfg)
    trainer.train()
    # the lr of the last batch is set at the frames seen before it, one (equal-sized) batch earlier
    last_batch = trainer.frames - trainer.frames // trainer.batches
    expected = 0.2 + 0.8 * 0.5 * (1 + math.cos(math.pi * last_batch / 1000))
    assert trainer.optim.param_groups[0]["lr"] == pytest.approx(float(cfg.optim.lr) * expected)
    assert expected < 0.5


def test_the_untrained_network_is_never_the_best_checkpoint(tmp_path):
    """The validation before the first update is on the curve but cannot become best.pt, even when
    training makes things worse (it did for DAOF-v2 in a quick profile, which then reported the
    untrained filter)."""
    cfg = tiny_cfg(
        "config.yaml", tmp_path, version="v2", **{"collector.total_frames": 400, "collector.warmup_frames": 200}
    )
    trainer = DSACTTrainer(cfg)
    validate = trainer.validate

    def untrained_scores_best():  # as if every update made the filter worse
        record = validate()
        record["score"] = 0.0 if trainer.updates == 0 else 1.0 + record["updates"]
        return record

    trainer.validate = untrained_scores_best
    summary = trainer.train()
    assert trainer.history[0]["updates"] == 0
    assert summary["best"]["record"]["updates"] > 0
    assert torch.load(tmp_path / "best.pt", weights_only=False)["extra"]["updates"] > 0


def test_validation_actor_target_validates_and_saves_the_polyak_averaged_actor(tmp_path):
    """``validation.actor=target``: the weights validated and written to best.pt / final.pt are
    DSAC-T's target actor; the online actor the loss trains is left as it was."""
    cfg = tiny_cfg(
        "config.yaml", tmp_path, version="v2", **{"collector.total_frames": 400, "validation.actor": "target"}
    )
    trainer = DSACTTrainer(cfg)
    trainer.train()
    online = {k: v.clone() for k, v in trainer.filter.state_dict().items()}
    saved = load_filter(tmp_path / "final.pt", trainer.system)
    with trainer.deployed_weights():
        target = {k: v.clone() for k, v in trainer.filter.state_dict().items()}
    assert_same_state(trainer.filter.state_dict(), online)  # swapped back out
    assert_same_state(saved.state_dict(), target)
    assert any(not torch.equal(online[k], target[k]) for k in online)  # τ < 1: the two differ after updates
    record = trainer.validate()
    rmse = rmse_per_state(saved.run(trainer.val_data), trainer.val_data["state"])
    torch.testing.assert_close(torch.tensor([record[f"rmse_{n}"] for n in trainer.system.state_names]), rmse)


def test_an_unknown_validation_actor_is_refused(tmp_path):
    with pytest.raises(ValueError, match="validation.actor"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **{"validation.actor": "best"}))


def test_a_critic_per_state_learns_on_the_reward_terms(tmp_path):
    """``loss.critic_per_state``: the critics output a value distribution per state, trained on
    the env's ``reward_per_state``, whose terms sum to the scalar reward."""
    cfg = tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 300, "loss.critic_per_state": True})
    trainer = DSACTTrainer(cfg)
    assert trainer.loss.tensor_keys.reward == "reward_per_state"
    trainer.train()
    batch = trainer.buffer.sample()
    torch.testing.assert_close(batch["next", "reward_per_state"].sum(-1, keepdim=True), batch["next", "reward"])
    assert trainer.loss.sigma_bar.shape == (2, trainer.system.state_dim)
    assert bool((trainer.loss.sigma_bar > 0).all()) and trainer.updates > 0


@pytest.mark.parametrize("per_state", [False, True])
def test_a_quadratic_critic_is_a_concave_quadratic_in_the_action_and_trains(tmp_path, per_state):
    """``network.critic_form=quadratic``: μ_k = V_k(h) − Σ_{i∈k} p_i(h)(a_i − m_i(h))², p > 0.

    Checked through the loss's own critic call: μ along each action axis is a parabola opening
    down (second differences equal and negative), the per-state terms each depend on their own
    action only (third differences vanish), and a short run updates it."""
    cfg = tiny_cfg(
        "config.yaml",
        tmp_path,
        **{"collector.total_frames": 300, "loss.critic_per_state": per_state, "network.critic_form": "quadratic"},
    )
    trainer = DSACTTrainer(cfg)
    trainer.train()
    assert trainer.updates > 0
    batch = trainer.buffer.sample()[:8]
    key, n = trainer.filter.action_key, trainer.system.state_dim
    for i in range(n):
        mus = []
        for a_i in (-0.5, 0.0, 0.5, 1.0):
            td = batch.clone()
            td[key][..., i] = a_i  # DAOF-v1's action is the unit update: the critic reads it as is
            mu, sigma = trainer.loss._critic_mu_sigma(td, trainer.loss.qvalue_network_params)
            mus.append(mu)
        second = mus[0] - 2 * mus[1] + mus[2]  # = −2·0.25·p_i for the terms holding action i
        moved = second.abs() > 1e-6
        assert (second[moved] < 0).all()
        held = torch.arange(second.shape[-1]) == i if per_state else torch.ones(1, dtype=torch.bool)
        assert moved[..., held].all() and not moved[..., ~held].any()
        third = mus[3] - 3 * mus[2] + 3 * mus[1] - mus[0]  # 0 for a quadratic, not for an MLP's μ
        torch.testing.assert_close(third, torch.zeros_like(third), atol=1e-5, rtol=0)


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_a_reward_quadratic_critic_has_the_rewards_own_curvature_and_trains(tmp_path, version):
    """``network.critic_form=reward_quadratic``: μ = V(h) − Σ_i W_t,i w_t,i² (a_i − m_i(h))² with the
    reward's weights W_t and the action's state-unit width w_t (DAOF-v1: its bound b_t at step t;
    DAOF-v2: the estimate's half-range), so the second difference along each action axis is
    the reward's own, for every window and step."""
    cfg = tiny_cfg(
        "config.yaml",
        tmp_path,
        version=version,
        **{"collector.total_frames": 300, "network.critic_form": "reward_quadratic"},
    )
    cfg.loss.gamma = 0.0
    trainer = DSACTTrainer(cfg)
    trainer.train()
    assert trainer.updates > 0
    f, env = trainer.filter, trainer.base_env
    batch = trainer.buffer.sample()[:16]
    key, n = f.action_key, trainer.system.state_dim
    step = batch.get("step", None)
    width = (f.high - f.low) / 2 * (f.bound_at(step) if f.acts_by_update else 1.0)
    w = env.reward_weights
    if w.ndim == 2:  # W_t of the step being estimated
        w = w[step.squeeze(-1).clamp(1, len(w)) - 1]
    mid, half = (f.high + f.low) / 2, (f.high - f.low) / 2
    for i in range(n):
        mus = []
        for a_i in (-0.5, 0.0, 0.5):
            td = batch.clone()
            td[key][..., i] = (mid + a_i * half)[i]
            mu = trainer.loss._critic_mu_sigma(td, trainer.loss.qvalue_network_params)[0]
            # a critic per state (DAOF-v2's default) holds each reward term apart: their sum is the reward's
            mus.append(mu.sum(-1) if cfg.loss.critic_per_state else mu.squeeze(-1))
        second = mus[0] - 2 * mus[1] + mus[2]
        torch.testing.assert_close(second, -0.5 * (w * width.pow(2))[..., i].expand_as(second), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_actor_samples_share_one_critic_pass_per_window(tmp_path, version):
    """``loss.actor_samples`` = M: the critics get M actions beside an expanded view of each window;
    a quadratic critic then runs its MLP once per window, with the values it gives on copies."""
    changes = {"collector.total_frames": 300, "network.critic_form": "reward_quadratic", "loss.actor_samples": 4}
    cfg = tiny_cfg("config.yaml", tmp_path, version=version, **changes)
    cfg.loss.gamma = 0.0
    trainer = DSACTTrainer(cfg)
    trainer.train()
    assert trainer.updates > 0 and trainer.loss.actor_samples == 4
    f, loss = trainer.filter, trainer.loss
    batch = trainer.buffer.sample()[:8].select(*loss.qvalue_network.in_keys, strict=False)
    td = batch.unsqueeze(-1).expand(8, 4)
    td.set(f.action_key, f.low + (f.high - f.low) * torch.rand(8, 4, trainer.system.state_dim))
    seen = []
    hook = loss.qvalue_network.module.mlp.register_forward_pre_hook(lambda _, args: seen.append(args[0].shape[:-1]))
    try:
        shared = loss._critic_mu_sigma(td, loss.qvalue_network_params)
        copied = loss._critic_mu_sigma(td.apply(lambda x: x.contiguous()), loss.qvalue_network_params)
    finally:
        hook.remove()
    assert seen == [torch.Size([8, 1]), torch.Size([8, 4])]
    for a, b in zip(shared, copied):
        torch.testing.assert_close(a, b)


def test_a_reward_scaled_critic_spreads_as_its_quadratic_reward_and_trains(tmp_path):
    """``network.critic_scale=reward``: σ_i² = s_i² + 2√2·p_i·s_i·(a_i − m_i)², the spread of the reward
    term −p_i(a_i − a*_i)² when a*_i | h is Gaussian around m_i, with s_i = softplus(raw_i) at a = m;
    refused without a critic per state, and a short run at a small ε keeps σ finite and positive."""
    changes = {"collector.total_frames": 300, "network.critic_form": "reward_quadratic", "loss.critic_per_state": True}
    changes |= {"network.critic_scale": "reward", "loss.epsilon": 1e-10, "version": "v2"}
    cfg = tiny_cfg("config.yaml", tmp_path / "a", **changes)
    cfg.loss.gamma = 0.0
    trainer = DSACTTrainer(cfg)
    trainer.train()
    assert trainer.updates > 0 and trainer.loss.epsilon == 1e-10
    f, loss = trainer.filter, trainer.loss
    critic = loss.qvalue_network.module
    batch = trainer.buffer.sample()[:8]
    with loss.qvalue_network_params[0].to_module(loss.qvalue_network):
        _, raw, best, curvature = critic.heads(batch["history"], batch.get("step", None))
    mid, half = f.squash_affine()
    spread = torch.nn.functional.softplus(raw)
    for offset in (0.0, 0.3, -0.7):
        td = batch.clone()
        td[f.action_key] = mid + (best + offset) * half
        _, sigma = loss._critic_mu_sigma(td, loss.qvalue_network_params)
        expected = (spread.pow(2) + 8**0.5 * spread * curvature * offset**2).sqrt()
        torch.testing.assert_close(sigma[0], expected, rtol=1e-4, atol=1e-7)
    assert bool(torch.isfinite(loss.sigma_bar).all()) and bool((loss.sigma_bar > 0).all())
    cfg = tiny_cfg("config.yaml", tmp_path / "b", **(changes | {"loss.critic_per_state": False}))
    cfg.loss.gamma = 0.0
    with pytest.raises(ValueError, match="needs a quadratic critic form with a critic per state"):
        DSACTTrainer(cfg)


def test_a_reward_quadratic_critic_needs_gamma_zero(tmp_path):
    cfg = tiny_cfg("config.yaml", tmp_path, **{"network.critic_form": "reward_quadratic", "loss.gamma": 0.5})
    with pytest.raises(ValueError, match="exact only with loss.gamma=0"):
        DSACTTrainer(cfg)


def test_mean_feedback_needs_gamma_zero_and_trains(tmp_path):
    """``collector.feedback=mean`` is refused with γ > 0 and, at γ = 0, trains with clean windows in the buffer."""
    # a critic that allows γ > 0, so the feedback check is the one that speaks
    mlp_critic = {"network.critic_form": "mlp", "network.critic_scale": "window", "loss.critic_per_state": False}
    changes = {"collector.feedback": "mean", "loss.gamma": 0.5, "version": "v2", **mlp_critic}
    cfg = tiny_cfg("config.yaml", tmp_path / "a", **changes)
    with pytest.raises(ValueError, match="feedback=mean keeps each action's value only with loss.gamma=0"):
        DSACTTrainer(cfg)
    changes = {"collector.feedback": "mean", "loss.gamma": 0.0, "version": "v2", "collector.total_frames": 300}
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "b", **changes))
    summary = trainer.train()
    assert summary["updates"] > 0 and math.isfinite(summary["best"]["score"])
    stored = trainer.buffer[:]
    assert FEEDBACK_KEY not in stored.keys()
    # the next window's newest x̂ is the squashed loc of the step, not the sampled action it was scored on
    newest = stored["next", "history"][:, -trainer.filter.frame_dim :][:, : trainer.system.state_dim]
    torch.testing.assert_close(newest, stored["next", "prev_estimate"])
    assert not torch.allclose(newest, stored["action"])


def test_an_unknown_critic_form_is_refused(tmp_path):
    cfg = tiny_cfg("config.yaml", tmp_path, **{"network.critic_form": "cubic"})
    with pytest.raises(ValueError, match="critic form must be one of"):
        DSACTTrainer(cfg)


RESIDUAL = {
    "network.critic_form": "quadratic",
    "reward.baseline": "zero_action",
}


def test_a_residual_run_starts_at_the_reference_filter_and_its_critic_prefers_nothing_yet(tmp_path):
    """reference_gain: the actor's residual starts at 0 (the deterministic filter is the mean-gain update)
    with the entropy target's exploration std; a quadratic critic's m(h) starts at 0 too."""
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **RESIDUAL))
    f = trainer.filter
    data = trainer.system.simulate(2, 30, seed=3)
    with torch.no_grad():
        loc, scale = f.policy(*[trainer.env.reset()[k] for k in f.policy_in_keys])
        torch.testing.assert_close(loc, torch.zeros_like(loc))
        torch.testing.assert_close(scale, trainer.exploration_std().expand_as(scale))
        # in the loss's two critics and their targets, not only in the module they were built from
        n = trainer.system.state_dim
        for params in (trainer.loss.qvalue_network_params, trainer.loss.target_qvalue_network_params):
            last = params["module", "mlp", "6"]
            assert (last["weight"][:, 2 : 2 + n] == 0).all() and (last["bias"][:, 2 : 2 + n] == 0).all()
            assert not torch.equal(last["weight"][0], last["weight"][1])  # two critics, not one twice
    fixed = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "fixed", **RESIDUAL, **{"loss.target_entropy": -3.0}))
    with torch.no_grad():  # a fixed entropy target: the residual starts at 0 too, with that entropy
        loc, scale = fixed.filter.policy(*[fixed.env.reset()[k] for k in fixed.filter.policy_in_keys])
    torch.testing.assert_close(loc, torch.zeros_like(loc))
    torch.testing.assert_close(scale, torch.full_like(scale, math.exp(-1.5) / math.sqrt(2 * math.pi * math.e)))
    steps = torch.arange(1, 31).clamp(max=f.correction_scale.shape[0]) - 1
    estimates, prev = f.run(data), f.system.prior.mean.expand(2, -1)
    for t in range(30):  # x̂_t = x̂⁻_t + K̄_t ν_t: the filter is the reference alone
        prediction = f.system.f(prev, data["prev_control"][:, t])
        nu = data["measurement"][:, t] - f.system.g(prediction, data["control"][:, t])
        expected = (prediction + (f.reference_gain[steps[t]] @ nu.unsqueeze(-1)).squeeze(-1)).clamp(
            f.state_low, f.state_high
        )
        torch.testing.assert_close(estimates[:, t], expected, atol=1e-6, rtol=1e-5)
        prev = estimates[:, t]


def test_the_zero_action_baseline_takes_the_reward_of_the_zero_update_off(tmp_path):
    """reward.baseline=zero_action: r' = r(a) − r(0) per stored transition, with r(0) the reward of
    x̂(0) = x̂⁻ + K̄ν at the step's weights; it needs γ = 0 and a filter that acts by updates."""
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "b", **{**RESIDUAL, "collector.total_frames": 300}))
    trainer.train()
    batch = trainer.buffer.storage.get(torch.arange(len(trainer.buffer)))
    f, weights = trainer.filter, trainer.base_env.reward_weights
    rows = batch["step"][..., 0].clamp(max=len(weights)) - 1
    prediction = f.system.f(batch["prev_estimate"], batch["prev_control"])
    nu = batch["measurement"] - f.system.g(prediction, batch["control"])
    zero = (prediction + (f.reference_gain[rows] @ nu.unsqueeze(-1)).squeeze(-1)).clamp(f.state_low, f.state_high)
    scored = (prediction + (f.reference_gain[rows] @ nu.unsqueeze(-1)).squeeze(-1)) + f.correction_scale[rows] * batch[
        "correction"
    ]
    scored = scored.clamp(f.state_low, f.state_high)
    x, w = batch["true_state"], weights[rows]
    expected = -((x - scored).pow(2) * w).sum(-1, keepdim=True) + ((x - zero).pow(2) * w).sum(-1, keepdim=True)
    torch.testing.assert_close(batch["next", "reward"], expected, atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match="gamma=0"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "g", **{**RESIDUAL, "loss.gamma": 0.5}))
    with pytest.raises(ValueError, match="reward.baseline must be one of"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "u", **{"reward.baseline": "average"}))
    with pytest.raises(ValueError, match="acts by updates"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "v2", version="v2", **{"reward.baseline": "zero_action"}))


def test_critic_init_resampled_is_torchrls_copy_which_loses_the_structured_init(tmp_path):
    """network.critic_init=resampled (the runs before 115f8b2): TorchRL expands one critic and
    re-samples its copies in [min, max], so the quadratic critic's m(h) rows are not 0."""
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **RESIDUAL, **{"network.critic_init": "resampled"}))
    n = trainer.system.state_dim
    assert trainer.loss.qvalue_network_params["module", "mlp", "6", "weight"][:, 2 : 2 + n].abs().amax() > 0
    with pytest.raises(ValueError, match="critic_init"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "bad", **{"network.critic_init": "copied"}))


def test_window_init_newest_starts_every_network_on_the_newest_frame(tmp_path):
    """network.window_init=newest: the first layers of the actor and both critics have zero weights on
    the N − 1 older frames, so changing them does not change any output at the start."""
    trainer = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **RESIDUAL, **{"network.window_init": "newest"}))
    f = trainer.filter
    older = (f.config.window - 1) * f.frame_dim
    critics_first = trainer.loss.qvalue_network_params["module", "mlp", "0", "weight"]
    for weight in (f.policy.mlp[0].weight.unsqueeze(0), critics_first):
        assert (weight[..., :older] == 0).all() and (weight[..., older:] != 0).all()
    td = trainer.env.reset()
    window, step = td[f.input_key], td["step"]
    moved = window.clone()
    moved[..., :older] += torch.randn_like(window[..., :older])
    action = torch.zeros(*td.batch_size, trainer.system.state_dim)
    critic = trainer.critic.module
    with torch.no_grad():
        first = f.policy.mlp[0]
        torch.testing.assert_close(first(f.policy.features(window, step)), first(f.policy.features(moved, step)))
        torch.testing.assert_close(critic(window, action, step), critic(moved, action, step))
        assert not torch.equal(critic(window, action, step), critic(window, action + 0.5, step))
    with pytest.raises(ValueError, match="window_init"):
        DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "bad", **{"network.window_init": "oldest"}))


@pytest.mark.parametrize("name, version", [("config.yaml", "v1"), ("config.yaml", "v2"), ("slf.yaml", None)])
def test_load_filter_reads_a_training_checkpoint(tmp_path, name, version):
    """``load_filter`` takes a run's checkpoint.pt as well as its best.pt and final.pt: the filter of
    the run's config with the checkpoint's weights."""
    changes = {"version": version} if version else {}
    trainer = (SLFTrainer if version is None else DSACTTrainer)(tiny_cfg(name, tmp_path, **changes))
    loaded = load_filter(trainer.save_checkpoint())
    assert type(loaded) is type(trainer.filter) and loaded.config == trainer.filter.config
    data = trainer.val_data
    torch.testing.assert_close(loaded.run(data), trainer.filter.eval().run(data), rtol=0, atol=0)


def test_a_run_directory_is_locked_while_a_trainer_owns_it(tmp_path):
    """A second trainer in a directory a live training holds is refused in one line; the lock goes with the run."""
    from daof.train.lock import RunDirectoryBusy, lock_run_directory

    held = lock_run_directory(tmp_path)
    trainer = SLFTrainer(tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 100}))
    with pytest.raises(RunDirectoryBusy, match=f"run directory {tmp_path} is in use by another training"):
        trainer.train()
    held.close()
    assert trainer.train()["frames"] >= 100
    lock_run_directory(tmp_path).close()  # released when the run finished


def test_a_fresh_run_moves_another_runs_files_aside(tmp_path):
    """A directory never mixes two runs: the old run's files go to previous-1 before the new one writes."""
    SLFTrainer(tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 100})).train()
    first = (tmp_path / "best.pt").read_bytes()
    SLFTrainer(tiny_cfg("slf.yaml", tmp_path, window=4, **{"collector.total_frames": 100})).train()
    assert (tmp_path / "previous-1" / "best.pt").read_bytes() == first
    assert load_filter(tmp_path / "best.pt").config.window == 4


def test_resume_rewrites_best_pt_from_the_checkpoint_and_refuses_another_seed(tmp_path):
    """best.pt written after the last checkpoint belongs to a discarded stretch: a resume restores the checkpoint's."""
    cfg = tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 400, "checkpoint.every_frames": 100000})
    trainer = DSACTTrainer(cfg)
    trainer.train()  # its checkpoint is the final one; fake a later, discarded best.pt
    recorded = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["best_filter"]["extra"]["frames"]
    (tmp_path / "best.pt").write_bytes(b"a best.pt of a discarded stretch")
    again = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 400}))
    again.resume(tmp_path / "checkpoint.pt")
    assert load_filter(tmp_path / "best.pt").extra["frames"] == recorded
    again._release_directory()
    other = DSACTTrainer(tiny_cfg("config.yaml", tmp_path, seed=2, **{"collector.total_frames": 400}))
    with pytest.raises(ValueError, match="checkpoint .* is for seed=1, this run has 2"):
        other.resume(tmp_path / "checkpoint.pt")


@pytest.mark.parametrize(
    "changes",
    [
        {"network.critic_form": "quadratic"},
        {"network.critic_form": "reward_quadratic", "loss.actor_samples": 4},
        {"network.critic_form": "reward_quadratic", "loss.critic_per_state": True, "network.critic_scale": "reward"},
    ],
)
def test_a_split_critic_gives_the_whole_critics_values_and_the_actor_loss_its_gradients(tmp_path, changes):
    """A quadratic critic runs as its action-free part, then the action; the actor loss reuses the critic
    loss's action-free part. Both give what the whole critic module (vmapped) and a fresh critic pass give."""
    cfg = tiny_cfg("config.yaml", tmp_path, **{"collector.total_frames": 300, **changes})
    cfg.loss.gamma = 0.0
    trainer = DSACTTrainer(cfg)
    trainer.train()
    loss, batch = trainer.loss, trainer.buffer.sample()
    assert loss._critic_split
    params = loss.qvalue_network_params
    whole = loss._vmap_qnetworkN0(batch.select(*loss.qvalue_network.in_keys, strict=False), params)
    whole = whole["state_action_value"].unflatten(-1, (-1, 2))
    mu, sigma = loss._critic_mu_sigma(batch, params)
    torch.testing.assert_close(mu, whole[..., 0], rtol=0, atol=1e-6)
    torch.testing.assert_close(sigma, torch.nn.functional.softplus(whole[..., 1]), rtol=0, atol=1e-6)
    actor = [p for p in loss.actor_network_params.flatten_keys().values() if p.requires_grad]
    results = []
    for reuse in (True, False):
        torch.manual_seed(5)  # the same actions drawn (γ = 0: the critic loss draws nothing)
        if reuse:
            value = loss(batch)["loss_actor"]
        else:
            loss.qvalue_loss(batch)
            value = loss.actor_loss(batch)[0]
        results.append((value.detach(), torch.autograd.grad(value, actor)))
    (a, grads_a), (b, grads_b) = results
    torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    for ga, gb in zip(grads_a, grads_b):
        torch.testing.assert_close(ga, gb, rtol=1e-5, atol=1e-6)
    assert any(g.abs().max() > 0 for g in grads_a)
    critics = [p for p in loss.qvalue_network_params.flatten_keys().values() if p.requires_grad]
    torch.manual_seed(5)
    leaked = torch.autograd.grad(loss(batch)["loss_actor"], critics, allow_unused=True)
    assert all(g is None or not g.any() for g in leaked)  # the reused part is detached


def test_the_ukf_validation_reference_is_computed_once_per_validation_set(tmp_path, monkeypatch):
    """Runs side by side share the UKF's validation RMSE (a file beside them); another set computes its own."""
    import daof.train.base as base

    runs = []
    real_run = base.UKF.run
    monkeypatch.setattr(base.UKF, "run", lambda self, data: runs.append(1) or real_run(self, data))
    trainer = SLFTrainer(tiny_cfg("slf.yaml", tmp_path / "a"))
    first = trainer.reference_rmse()
    expected = rmse_per_state(real_run(base.UKF(trainer.system), trainer.val_data), trainer.val_data["state"])
    torch.testing.assert_close(torch.tensor(first["UKF"]), expected)
    assert len(runs) == 1 and len(list((tmp_path / base.REFERENCE_CACHE).glob("ukf-*.json"))) == 1
    assert SLFTrainer(tiny_cfg("slf.yaml", tmp_path / "b")).reference_rmse() == first and len(runs) == 1
    other = SLFTrainer(tiny_cfg("slf.yaml", tmp_path / "c", **{"seeds.validation": 9101})).reference_rmse()
    assert other != first and len(runs) == 2
