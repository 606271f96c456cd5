"""Files written atomically and read safely: plain data only, one clear error line for a bad file.

What is saved holds plain data only: tensors, dicts, lists, tuples, numbers, strings and None
(``to_plain`` converts numpy arrays and scalars, TensorDicts and OmegaConf containers on the way
to the file). So it is read with ``torch.load(weights_only=True)``, which refuses any other Python
object: a crafted ``.pt`` cannot run code when it is loaded (``safe_load``).
"""

from __future__ import annotations

import os
import pickle
import re
import tempfile
import warnings
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tensordict import TensorDictBase

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # numpy < 2
    from numpy.core.multiarray import _reconstruct

__all__ = ["atomic_save", "atomic_write_text", "safe_load", "to_plain", "writable_directory"]

#: what a checkpoint written before safe loading needs besides plain data: numpy's global
#: generator state, a uint32 array (with these, ``weights_only`` builds uint32 arrays and nothing else)
_LEGACY_NUMPY_GLOBALS = [_reconstruct, np.ndarray, np.dtype, np.dtypes.UInt32DType]
#: what ``weights_only`` loading rebuilds as it is
_ATOMS = (int, float, complex, bool, str, bytes, type(None), torch.Tensor, torch.Size, torch.dtype, torch.device)


def to_plain(obj, where: str = "checkpoint"):
    """``obj`` with everything ``torch.load(weights_only=True)`` refuses made plain data.

    numpy arrays -> tensors, numpy scalars -> Python numbers, TensorDicts -> nested dicts of
    tensors (``to_dict``), OmegaConf containers -> dicts and lists, other mappings and tuple
    subclasses -> dicts and tuples; dicts, lists and tuples are walked. A container in which
    nothing changes is returned as it is (a module's ``state_dict`` keeps its ``_metadata``). Any
    other object is a ``TypeError`` naming where it is: found when saving, not when resuming.
    """
    if isinstance(obj, np.generic):  # before the atoms: np.float64 is a float, yet pickles as numpy's
        return obj.item()
    if isinstance(obj, _ATOMS):
        return obj
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj.copy())
    if isinstance(obj, TensorDictBase):
        return to_plain(obj.to_dict(), where)
    if isinstance(obj, (DictConfig, ListConfig)):
        return OmegaConf.to_container(obj, resolve=True)
    if isinstance(obj, Mapping):
        items = {key: to_plain(value, f"{where}/{key}") for key, value in obj.items()}
        if type(obj) in (dict, OrderedDict) and all(items[key] is value for key, value in obj.items()):
            return obj
        return OrderedDict(items) if isinstance(obj, OrderedDict) else items
    if isinstance(obj, (list, tuple)):
        items = [to_plain(value, f"{where}/{i}") for i, value in enumerate(obj)]
        if type(obj) in (list, tuple) and all(a is b for a, b in zip(items, obj, strict=True)):
            return obj
        return items if isinstance(obj, list) else tuple(items)
    raise TypeError(f"{where} is a {type(obj).__module__}.{type(obj).__qualname__}, not plain data for a checkpoint")


def atomic_save(obj, path: str | Path) -> None:
    """``torch.save(to_plain(obj))`` to a temporary file, then rename.

    An interruption never leaves half a file, and a failed write no temporary file either.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        torch.save(to_plain(obj), tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to a temporary file, then rename: a reader sees the old file or the new one, never half."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def writable_directory(path: str | Path, what: str = "directory") -> Path:
    """Create ``path`` if needed and write a scratch file in it; one ``ValueError`` line if either fails.

    A read-only file system, a missing permission or a path through a file is found before any work.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as error:
        raise ValueError(f"cannot write the {what} {path}: {error.strerror or error}") from None
    return path


def safe_load(path: str | Path, map_location="cpu"):
    """``torch.load(path, weights_only=True)``: plain data only, or one ``ValueError`` line naming the file.

    A file that needs any other Python object (a crafted pickle, say) is refused without running
    it; so are truncated, empty and foreign files. A training checkpoint written before checkpoints
    were plain data (numpy's generator state as a numpy array) still loads.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no file at {path}")
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Detected pickle protocol")  # a foreign pickle: refused below
            try:
                return torch.load(path, map_location=map_location, weights_only=True)
            except pickle.UnpicklingError:
                if not _needs_only_legacy_numpy(path):
                    raise
            with torch.serialization.safe_globals(_LEGACY_NUMPY_GLOBALS):
                return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch and pickle raise many kinds for a bad file
        raise ValueError(f"{path} is not a readable checkpoint ({_reason(error)})") from None


def _needs_only_legacy_numpy(path: Path) -> bool:
    names = {f"{g.__module__}.{g.__qualname__}" for g in _LEGACY_NUMPY_GLOBALS}
    try:
        unsafe = set(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:  # not a zip checkpoint: nothing a legacy checkpoint would be
        return False
    return bool(unsafe) and unsafe <= names


def _reason(error: Exception) -> str:
    """One line on why ``torch.load`` failed."""
    text = str(error)
    refused = re.search(r"GLOBAL (\S+)", text) or re.search(r"but got <class '([^']+)'>", text)
    if refused:
        return f"it holds {refused.group(1)}, not plain data (refused without running it: weights_only=True)"
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1]
    line = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
    if isinstance(error, EOFError):
        line = line or "the file is empty or ends early"
    line = line.split(". ")[0].rstrip(".")
    detail = f"{type(error).__name__}: {line}" if line else type(error).__name__
    return f"not a readable torch file ({detail[:200]})"
