"""``device``: one place resolves it, an absent GPU is refused in one line before any work, and a
training's device reaches its env, replay buffer, networks, loss, optimisers and validation data."""

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase

import daof.train.dsac as dsac
from daof.device import resolve_device
from daof.experiments.experiment import plan_experiment
from daof.train.config import compose_config
from daof.train.dsac import DSACTTrainer
from daof.train.supervised import SLFTrainer

NO_GPU = not torch.cuda.is_available()
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(NO_GPU, reason="no CUDA GPU"))]


def tiny(filter_: str, out: Path, device: str):
    cfg = compose_config([f"filter={filter_}", "system=veh2dof", f"device={device}", "logger.backend="])
    cfg.output_dir = str(out)
    cfg.network.num_cells = 16
    cfg.validation.runs, cfg.validation.steps, cfg.validation.every_frames = 2, 30, 200
    cfg.collector.env_batch, cfg.collector.total_frames, cfg.checkpoint.every_frames = 4, 300, 10_000
    cfg.collector.steps_per_batch, cfg.collector.warmup_frames, cfg.collector.episode_steps = 25, 100, 50
    cfg.buffer.size, cfg.optim.batch_size = 1000, 32
    return cfg


def devices_of(*objects) -> dict[str, torch.device]:
    """Path -> device of every tensor in modules, optimisers, tensordicts and plain containers."""
    out = {}

    def walk(obj, path):
        if isinstance(obj, torch.Tensor):
            out[path] = obj.device
        elif isinstance(obj, torch.nn.Module):
            for name, t in obj.state_dict(keep_vars=True).items():
                walk(t, f"{path}.{name}")
        elif isinstance(obj, torch.optim.Optimizer):
            for k, state in enumerate(obj.state.values()):
                walk(state, f"{path}.state{k}")
        elif isinstance(obj, TensorDictBase):
            for name, t in obj.items(True, True):
                walk(t, f"{path}.{name}")
        elif isinstance(obj, dict):
            for name, t in obj.items():
                walk(t, f"{path}.{name}")

    for i, obj in enumerate(objects):
        walk(obj, f"[{i}]")
    return out


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="not a device"):
        resolve_device("gpu0")
    with pytest.raises(ValueError, match="not supported"):
        resolve_device("meta")
    with pytest.raises(ValueError, match="sees"):
        resolve_device(f"cuda:{torch.cuda.device_count() + 3}")


@pytest.mark.skipif(not NO_GPU, reason="a CUDA GPU is there")
def test_an_absent_gpu_is_refused_in_one_line_before_any_work(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="sees no CUDA GPU") as error:
        compose_config(["filter=daof_v1", "device=cuda", f"output_dir={out}"])
    assert "\n" not in str(error.value)
    assert not out.exists()
    with pytest.raises(ValueError, match="sees no CUDA GPU"):
        plan_experiment("veh2dof", ["profile=tiny", "device=cuda", f"root={tmp_path}/exp"])
    cfg = compose_config(["filter=daof_v1"])
    cfg.device, cfg.output_dir = "cuda", str(out)  # a config made without compose_config: the trainer refuses it
    with pytest.raises(ValueError, match="sees no CUDA GPU"):
        DSACTTrainer(cfg)
    assert not out.exists()


@pytest.mark.parametrize("device", DEVICES)
def test_a_dsac_training_keeps_every_tensor_on_its_device(tmp_path, monkeypatch, device):
    given = {}

    class Env(dsac.FilteringEnv):
        def __init__(self, *args, **kwargs):
            given["env"] = kwargs.get("device")
            super().__init__(*args, **kwargs)

    class Storage(dsac.LazyTensorStorage):
        def __init__(self, *args, **kwargs):
            given["storage"] = kwargs.get("device")
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(dsac, "FilteringEnv", Env)
    monkeypatch.setattr(dsac, "LazyTensorStorage", Storage)
    trainer = DSACTTrainer(tiny("daof_v1", tmp_path, device))
    trainer.train()
    want = resolve_device(device)
    assert given == {"env": want, "storage": want}  # passed on, not left to a default
    assert trainer.updates > 0
    placed = devices_of(
        trainer.loss,
        trainer.filter,
        trainer.optim_actor,
        trainer.optim_critic,
        trainer.optim_alpha,
        trainer.buffer.storage._storage,
        trainer.val_data,
        {k: v for k, v in vars(trainer.system).items() if isinstance(v, torch.Tensor)},
        {"reward_weights": trainer.base_env.reward_weights},
    )
    assert any(".state" in path for path in placed) and any("[5]" in path for path in placed)
    assert {path: d for path, d in placed.items() if d != want} == {}


@pytest.mark.parametrize("device", DEVICES)
def test_an_slf_training_simulates_and_fits_on_its_device(tmp_path, device):
    trainer = SLFTrainer(tiny("slf", tmp_path, device))
    simulate, asked = trainer.system.simulate, []

    def spy(*args, **kwargs):
        asked.append(kwargs.get("device"))
        return simulate(*args, **kwargs)

    trainer.system.simulate = spy
    trainer.train()
    want = resolve_device(device)
    assert asked and set(asked) == {want}
    placed = devices_of(trainer.filter, trainer.optim, trainer.val_data)
    assert {path: d for path, d in placed.items() if d != want} == {}
    assert OmegaConf.select(trainer.cfg, "device") == device
