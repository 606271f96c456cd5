"""Short digests that key caches: of files, of a classical filter's code and settings, of a data set.

A cache keyed by them is never stale: a retrained checkpoint, an edited filter or system module, other
settings or other data give another key.
"""

from __future__ import annotations

import hashlib
import inspect
from pathlib import Path

import torch
from tensordict import TensorDictBase

from daof.filters.base import Filter

__all__ = ["checkpoint_fingerprint", "classical_fingerprint", "data_fingerprint"]


def checkpoint_fingerprint(paths) -> str:
    """A short digest of the given files' bytes: a study cache keyed by it is never stale after retraining."""
    digest = hashlib.sha1()
    for path in sorted(Path(p) for p in paths):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:10]


def classical_fingerprint(filt, system) -> str:
    """A short digest of the modules of a classical filter, of ``Filter`` and of its system, and of its settings."""
    sources = {inspect.getsourcefile(type(filt)), inspect.getsourcefile(type(system)), inspect.getsourcefile(Filter)}
    settings = sorted((k, v) for k, v in vars(filt).items() if isinstance(v, (bool, int, float, str)))
    return checkpoint_fingerprint(sources) + hashlib.sha1(repr(settings).encode()).hexdigest()[:6]


def data_fingerprint(data: TensorDictBase) -> str:
    """A short digest of a simulated data set's tensors (their keys, shapes and bytes)."""
    digest = hashlib.sha1()
    for key in sorted(data.keys(include_nested=True, leaves_only=True), key=str):
        value = data.get(key).detach().cpu().contiguous()
        digest.update(f"{key}{tuple(value.shape)}{value.dtype}".encode())
        digest.update(value.view(-1).view(torch.uint8).numpy().tobytes())  # its bytes, whatever the dtype
    return digest.hexdigest()[:12]
