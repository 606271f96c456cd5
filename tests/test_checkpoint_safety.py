"""Checkpoints are plain data read with ``weights_only=True``: a crafted file never runs, a bad one is one line."""

import pickle
import random
import re
import sys
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from daof.evaluate.study import _read_cache
from daof.train.checkpoint import atomic_save, capture_rng, load_checkpoint, restore_rng, safe_load, to_plain

sys.path.insert(0, str(Path(__file__).parent))
from test_training import tiny_cfg  # noqa: E402


class Payload:
    """Unpickling it creates ``marker``: what a crafted checkpoint would do instead."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def crafted(path: Path, marker: Path, zip_format: bool = True) -> Path:
    blob = {"training": {"frames": 0}, "key": {}, "result": {}, "estimates": Payload(marker)}
    if zip_format:
        torch.save(blob, path)
    else:
        path.write_bytes(pickle.dumps(blob))
    return path


@pytest.mark.parametrize("zip_format", [True, False], ids=["torch.save", "raw-pickle"])
def test_a_crafted_checkpoint_is_refused_without_running_it(tmp_path, zip_format):
    marker = tmp_path / "marker"
    path = crafted(tmp_path / "checkpoint.pt", marker, zip_format)
    # the control: unpickled the old way, the payload runs
    if zip_format:
        torch.load(path, weights_only=False)
    else:
        pickle.loads(path.read_bytes())
    assert marker.exists()
    marker.unlink()

    with pytest.raises(ValueError, match=re.escape(str(path))) as error:
        load_checkpoint(path)
    assert "\n" not in str(error.value)
    logged = []
    assert _read_cache(path, logged.append) is None  # the study's cache: computed again instead
    assert len(logged) == 1 and str(path) in logged[0]
    with pytest.raises(ValueError, match="io.open" if zip_format else re.escape(str(path))):
        safe_load(path)
    assert not marker.exists()


def test_bad_files_give_one_line_naming_the_file(tmp_path):
    good = tmp_path / "good.pt"
    atomic_save({"training": {"frames": 1}, "weights": torch.arange(1000.0)}, good)
    data = good.read_bytes()
    files = {
        "truncated.pt": data[: len(data) // 2],
        "empty.pt": b"",
        "random.pt": np.random.default_rng(0).bytes(4096),
        "text.pt": b"not a checkpoint\n",
    }
    for name, content in files.items():
        path = tmp_path / name
        path.write_bytes(content)
        for loader in (load_checkpoint, safe_load):
            with pytest.raises(ValueError) as error:
                loader(path)
            message = str(error.value)
            assert str(path) in message and "\n" not in message, message
            assert error.value.__suppress_context__  # no torch traceback chained before it
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="not a training checkpoint"):
        atomic_save({"weights": torch.ones(2)}, tmp_path / "other.pt")
        load_checkpoint(tmp_path / "other.pt")
    assert load_checkpoint(good)["training"] == {"frames": 1}


def test_a_failed_write_leaves_no_temporary_file_and_the_old_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    atomic_save({"training": {"frames": 1}}, path)

    def disk_full(obj, f):
        Path(f).write_bytes(b"half a file")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        atomic_save({"training": {"frames": 2}}, path)
    monkeypatch.undo()
    with pytest.raises(TypeError, match="checkpoint/training/when is a pathlib"):
        atomic_save({"training": {"when": Path("x")}}, path)  # not plain data: refused when saving
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    assert load_checkpoint(path)["training"] == {"frames": 1}


def test_to_plain_makes_what_weights_only_refuses_plain_data(tmp_path):
    module_state = torch.nn.Linear(2, 1).state_dict()
    blob = {
        "training": {"frames": np.int64(3), "score": np.float64(0.5)},
        "array": np.arange(4, dtype=np.uint32),
        "td": TensorDict({"a": torch.ones(2), "b": {"c": torch.zeros(2, 1)}}, batch_size=[2]),
        "cfg": OmegaConf.create({"x": 1, "y": [1, 2]}),
        "module": module_state,
        "tuple": (1, np.float32(2.0)),
    }
    plain = to_plain(blob)
    assert plain["module"] is module_state and hasattr(plain["module"], "_metadata")  # untouched
    assert plain["training"] == {"frames": 3, "score": 0.5} and type(plain["training"]["frames"]) is int
    assert plain["array"].dtype == torch.uint32 and plain["array"].tolist() == [0, 1, 2, 3]
    assert plain["tuple"] == (1, 2.0)
    assert plain["cfg"] == {"x": 1, "y": [1, 2]}
    assert set(plain["td"]) == {"a", "b"} and torch.equal(plain["td"]["b"]["c"], torch.zeros(2, 1))
    atomic_save(blob, tmp_path / "c.pt")
    loaded = torch.load(tmp_path / "c.pt", weights_only=True)
    assert isinstance(loaded["module"], OrderedDict) and torch.equal(loaded["module"]["weight"], module_state["weight"])


def test_rng_states_round_trip_through_a_safe_file(tmp_path):
    gen = torch.Generator().manual_seed(7)
    np.random.seed(1), random.seed(2), torch.manual_seed(3)
    np.random.normal()  # a cached Gaussian in numpy's state
    atomic_save({"training": {}, "rng": capture_rng({"env": gen})}, tmp_path / "c.pt")
    draws = (np.random.normal(size=3), random.random(), torch.rand(2), torch.rand(2, generator=gen))
    np.random.seed(0), random.seed(0), torch.manual_seed(0), gen.manual_seed(0)
    restore_rng(load_checkpoint(tmp_path / "c.pt")["rng"], {"env": gen})
    again = (np.random.normal(size=3), random.random(), torch.rand(2), torch.rand(2, generator=gen))
    assert np.array_equal(draws[0], again[0]) and draws[1] == again[1]
    assert torch.equal(draws[2], again[2]) and torch.equal(draws[3], again[3])


def test_a_checkpoint_from_before_plain_rng_states_still_resumes(tmp_path):
    """Old checkpoints hold numpy's state as a uint32 array: that (and only that) numpy array loads."""
    np.random.seed(5)
    legacy = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    torch.save({"training": {}, "rng": legacy}, tmp_path / "old.pt")
    expected = np.random.normal(size=2)
    np.random.seed(0)
    restore_rng(load_checkpoint(tmp_path / "old.pt")["rng"])
    assert np.array_equal(np.random.normal(size=2), expected)
    torch.save({"training": {}, "values": np.zeros(3)}, tmp_path / "float.pt")
    with pytest.raises(ValueError, match="Float64DType"):
        load_checkpoint(tmp_path / "float.pt")


def test_a_tiny_training_checkpoint_is_plain_data_and_resumes(tmp_path):
    from daof.train.supervised import SLFTrainer

    first, second = tmp_path / "first", tmp_path / "second"
    SLFTrainer(tiny_cfg("slf.yaml", first, **{"collector.total_frames": 400})).train()
    checkpoint = first / "checkpoint.pt"
    saved = torch.load(checkpoint, weights_only=True)  # nothing but plain data
    assert not any(p.suffix == ".tmp" for p in first.iterdir())
    trainer = SLFTrainer(tiny_cfg("slf.yaml", second, resume=str(checkpoint), **{"collector.total_frames": 800}))
    trainer.resume(checkpoint)
    restored = trainer.state_dict()
    assert restored["training"]["frames"] == 400
    for key in ("torch", "numpy", "python"):
        assert repr(restored["rng"][key]) == repr(saved["rng"][key])
    assert trainer.train()["frames"] == 800
    assert torch.load(second / "checkpoint.pt", weights_only=True)["training"]["frames"] == 800
