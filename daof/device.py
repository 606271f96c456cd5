"""The one place a run's device is decided: ``resolve_device("cpu" | "cuda" | "cuda:1" | "auto")``."""

from __future__ import annotations

import torch

__all__ = ["resolve_device"]


def resolve_device(name: str | torch.device = "cpu") -> torch.device:
    """The ``torch.device`` of a config's ``device``; ``auto`` is the first GPU if there is one, else the CPU.

    A CUDA device that is not there is refused in one ``ValueError`` line, before any work.
    """
    if str(name) == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"device={name!r} is not a device; use cpu, cuda, cuda:<k> or auto") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"device={name!r} asked, but torch {torch.__version__} sees no CUDA GPU; use device=cpu")
        if (device.index or 0) >= count:
            raise ValueError(f"device={name!r} asked, but torch sees {count} CUDA GPU(s)")
        return torch.device("cuda", device.index or 0)
    if device.type != "cpu":
        raise ValueError(f"device={name!r} is not supported; use cpu, cuda, cuda:<k> or auto")
    return device
