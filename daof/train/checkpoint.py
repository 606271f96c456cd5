"""Training checkpoints that resume: every piece of state in one file (``daof.io``: written
atomically, plain data only, read with ``weights_only=True``), and the RNG states they keep."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from daof.io import atomic_save, safe_load, to_plain

__all__ = ["RUN_CONFIG", "atomic_save", "capture_rng", "load_checkpoint", "restore_rng", "safe_load", "to_plain"]

#: file every trainer writes into its output directory: the resolved config it runs with
RUN_CONFIG = "run_config.json"


def capture_rng(extra_generators: dict[str, torch.Generator] | None = None) -> dict:
    """States of the global torch, numpy and Python generators plus any named generators, as plain data.

    numpy's (``np.random.get_state()``) keeps its name and counters, its 624 uint32 words become an
    int64 tensor; Python's is a tuple of ints already.
    """
    name, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": (name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached_gaussian)),
        "python": random.getstate(),
    }
    for gen_name, gen in (extra_generators or {}).items():
        state[f"gen:{gen_name}"] = gen.get_state()
    return state


def restore_rng(state: dict, extra_generators: dict[str, torch.Generator] | None = None) -> None:
    """Inverse of ``capture_rng`` (also of the numpy-array form of checkpoints written before it)."""
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached_gaussian = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached_gaussian))
    version, words, gauss = state["python"]
    random.setstate((version, tuple(words), gauss))
    for gen_name, gen in (extra_generators or {}).items():
        gen.set_state(state[f"gen:{gen_name}"])


def load_checkpoint(path: str | Path) -> dict:
    """Load a training checkpoint (``safe_load``), with one clear error if it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    blob = safe_load(path)
    if not isinstance(blob, dict) or "training" not in blob:
        raise ValueError(f"{path} is not a training checkpoint of this project")
    return blob
