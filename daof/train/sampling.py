"""A replay-buffer sampler with a fixed weight per stored transition, and the weights DSAC-T runs give."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import Sampler

from daof.filters.learned import startup_feature

__all__ = ["ReplayPriority", "WeightedSampler"]


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


@dataclass(frozen=True)
class ReplayPriority:
    """The sampling weight of a transition: 1 + k_start·ρ_t² + k_est·Σ_i (x̂_{t−1,i} / s_i)².

    Both terms put more of the rare transitions into the updates: the start-up steps (ρ_t,
    ``buffer.startup_priority``) and large previous estimates, e.g. the 2-DOF vehicle's slides
    (``buffer.estimate_priority`` with ``buffer.estimate_priority_scale``: one scale per state,
    ``null`` leaves a state out). Both keys are inputs of the policy (ρ_t and x̂_{t−1} are in h_t),
    so at γ = 0 the weight changes which inputs the fit spends its capacity on, not the best
    estimate for an input: no importance correction is needed. A weight keyed on the true state
    would be biased: it pulls the estimate for an input towards the weighted states.
    """

    startup: float = 0.0
    estimate: float = 0.0
    inverse_scale: tuple[float, ...] = ()

    @classmethod
    def from_config(cls, buffer_cfg, state_dim: int) -> ReplayPriority:
        startup = float(buffer_cfg.get("startup_priority", 0.0))
        estimate = float(buffer_cfg.get("estimate_priority", 0.0))
        for name, k in (("startup_priority", startup), ("estimate_priority", estimate)):
            if not (math.isfinite(k) and k >= 0):
                raise ValueError(f"buffer.{name} must be finite and >= 0, got {k}")
        if estimate == 0:
            return cls(startup)
        scale = buffer_cfg.get("estimate_priority_scale")
        if scale is None or len(scale) != state_dim:
            raise ValueError(f"buffer.estimate_priority_scale needs one scale (or null) per state ({state_dim})")
        inverse = []
        for s in scale:
            if s is not None and not (math.isfinite(float(s)) and float(s) > 0):
                raise ValueError(f"buffer.estimate_priority_scale entries must be > 0 or null, got {list(scale)}")
            inverse.append(0.0 if s is None else 1.0 / float(s))
        if not any(inverse):
            raise ValueError("buffer.estimate_priority_scale leaves every state out")
        return cls(startup, estimate, tuple(inverse))

    @property
    def active(self) -> bool:
        return self.startup > 0 or self.estimate > 0

    def __call__(self, step: torch.Tensor, prev_estimate: torch.Tensor) -> torch.Tensor:
        """Weights [B] of transitions at measured steps ``step`` [B, 1] after estimates x̂_{t−1} [B, n]."""
        weight = torch.ones(prev_estimate.shape[:-1], dtype=prev_estimate.dtype, device=prev_estimate.device)
        if self.startup > 0:
            weight = weight + self.startup * startup_feature(step).squeeze(-1).to(weight.dtype) ** 2
        if self.estimate > 0:
            inverse = torch.tensor(self.inverse_scale, dtype=prev_estimate.dtype, device=prev_estimate.device)
            weight = weight + self.estimate * (prev_estimate * inverse).pow(2).sum(-1)
        return weight
