"""Training checkpoints that resume: every piece of state in one file, written atomically."""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

__all__ = ["RUN_CONFIG", "capture_rng", "restore_rng", "atomic_save", "load_checkpoint"]

#: file every trainer writes into its output directory: the resolved config it runs with
RUN_CONFIG = "run_config.json"


def capture_rng(extra_generators: dict[str, torch.Generator] | None = None) -> dict:
    """States of the global torch, numpy and Python generators plus any named generators."""
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    for name, gen in (extra_generators or {}).items():
        state[f"gen:{name}"] = gen.get_state()
    return state


def restore_rng(state: dict, extra_generators: dict[str, torch.Generator] | None = None) -> None:
    """Inverse of ``capture_rng``."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    for name, gen in (extra_generators or {}).items():
        gen.set_state(state[f"gen:{name}"])


def atomic_save(obj, path: str | Path) -> None:
    """``torch.save`` to a temporary file, then rename: an interruption never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict:
    """Load a training checkpoint, with one clear error if it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    blob = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(blob, dict) or "training" not in blob:
        raise ValueError(f"{path} is not a training checkpoint of this project")
    return blob
