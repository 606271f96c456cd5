"""A replay-buffer sampler with a fixed weight per stored transition."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import Sampler

__all__ = ["WeightedSampler"]


class WeightedSampler(Sampler):
    """Draws stored transitions with replacement, with probability ∝ a weight set when each is written.

    The weight comes with the data under the buffer's ``priority_key`` (TorchRL's buffers pass it to
    ``update_priority`` on ``extend``); nothing updates it afterwards. TorchRL's
    ``PrioritizedSampler`` does the same with a sum tree, but that needs torchrl's C++ extension,
    which is not built for the torch this project pins. Sampling is one ``torch.multinomial`` over
    the filled slots (the global RNG, so a checkpoint's RNG state covers it).
    """

    def __init__(self, capacity: int):
        self.weights = torch.ones(int(capacity))

    def update_priority(self, index, priority, *, storage=None) -> None:
        priority = torch.as_tensor(priority, dtype=self.weights.dtype).reshape(-1)
        if not (torch.isfinite(priority).all() and (priority > 0).all()):
            raise ValueError("sampling weights must be finite and > 0")
        self.weights[torch.as_tensor(index).reshape(-1)] = priority

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        filled = len(storage)
        if filled == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        index = torch.multinomial(self.weights[:filled], batch_size, replacement=True, generator=self._rng)
        return index, {}

    def _empty(self) -> None:
        self.weights.fill_(1.0)

    def state_dict(self) -> dict[str, Any]:
        return {"weights": self.weights.clone()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.weights.copy_(state_dict["weights"])

    def dumps(self, path) -> None:
        torch.save(self.state_dict(), Path(path) / "weighted_sampler.pt")

    def loads(self, path) -> None:
        self.load_state_dict(torch.load(Path(path) / "weighted_sampler.pt"))
