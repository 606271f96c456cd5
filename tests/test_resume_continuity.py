"""A run stopped at a checkpoint and resumed is the uninterrupted run, bit for bit; same seed, same run."""

import sys
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict

from daof.train.dsac import DSACTTrainer
from daof.train.supervised import SLFTrainer

sys.path.insert(0, str(Path(__file__).parent))
from test_training import assert_same_state, tiny_cfg  # noqa: E402

TOTAL, STOP = 400, 200


class Interrupted(Exception):
    """Stands for the process being killed right after a checkpoint was written."""


def trained(trainer_cls, cfg) -> dict:
    trainer = trainer_cls(cfg)
    trainer.train()
    return trainer.state_dict()


def stopped_and_resumed(trainer_cls, cfg, monkeypatch) -> dict:
    save = trainer_cls.save_checkpoint

    def save_then_stop(self):
        path = save(self)
        if self.frames == STOP:
            raise Interrupted
        return path

    first = trainer_cls(cfg)
    with monkeypatch.context() as patch:
        patch.setattr(trainer_cls, "save_checkpoint", save_then_stop)
        with pytest.raises(Interrupted):
            first.train()
    first._release_directory()  # what the killed process's exit does
    second = trainer_cls(cfg)
    second.resume(cfg.output_dir + "/checkpoint.pt")
    second.train()
    return second.state_dict()


def comparable(state: dict) -> dict:
    """Everything a training run learns and keeps (not its wall clock, logger or best-file metadata).

    The replay storage's rows beyond its length are uninitialised memory: only the written rows count.
    """
    keys = ("filter", "loss", "optim_critic", "optim_actor", "optim_alpha", "optim", "rng")
    out = {k: state[k] for k in keys if k in state}
    if "buffer" in state:
        storage = state["buffer"]["_storage"]
        out["replay"] = {k: v[: storage["_len"]] for k, v in storage["_storage"].items()}
        out["replay_len"] = torch.tensor(storage["_len"])
    return out


def dsac_cfg(out: Path, case: str):
    """v1, v2, or v2 on a replayed env (episodes of 50 steps dealt from a bank of 15)."""
    cfg = tiny_cfg("config.yaml", out, version=case[:2], **{"collector.total_frames": TOTAL})
    if case.endswith("replay"):
        cfg.collector.episode_steps = 50
        with open_dict(cfg):
            cfg.overrides.replay = {"runs": 15, "steps": 50, "seed": 1}
    return cfg


@pytest.mark.parametrize("case", ["v1", "v2", "v2-replay"])
def test_dsac_resumed_run_is_the_uninterrupted_run(tmp_path, monkeypatch, case):
    """Stopped at 200 of 400 frames (episodes in flight) and resumed: identical weights, targets,
    optimisers, replay buffer and generators at the end."""
    whole = trained(DSACTTrainer, dsac_cfg(tmp_path / "whole", case))
    resumed = stopped_and_resumed(DSACTTrainer, dsac_cfg(tmp_path / "resumed", case), monkeypatch)
    assert whole["training"]["frames"] == resumed["training"]["frames"] == TOTAL
    assert whole["training"]["updates"] == resumed["training"]["updates"]
    assert_same_state(comparable(whole), comparable(resumed))
    assert [h["score"] for h in whole["training"]["history"]] == [h["score"] for h in resumed["training"]["history"]]


def test_slf_resumed_run_is_the_uninterrupted_run(tmp_path, monkeypatch):
    changes = {"collector.total_frames": TOTAL}
    whole = trained(SLFTrainer, tiny_cfg("slf.yaml", tmp_path / "whole", **changes))
    resumed = stopped_and_resumed(SLFTrainer, tiny_cfg("slf.yaml", tmp_path / "resumed", **changes), monkeypatch)
    assert_same_state(comparable(whole), comparable(resumed))


def test_same_seed_same_weights(tmp_path):
    """Two trainings of one config and seed end with identical weights, which training moved."""
    changes = {"collector.total_frames": STOP}
    first = DSACTTrainer(tiny_cfg("config.yaml", tmp_path / "a", **changes))
    initial = {k: v.clone() for k, v in first.filter.state_dict().items()}
    first.train()
    a = first.state_dict()
    b = trained(DSACTTrainer, tiny_cfg("config.yaml", tmp_path / "b", **changes))
    assert_same_state(comparable(a), comparable(b))
    assert a["training"]["updates"] > 0
    assert any(not torch.equal(initial[k], a["filter"][k]) for k in initial)
