"""``GappySystem``: env episodes with random sensor gaps, to train closed-loop filters through them.

A wrapper ``StochasticSystem`` that ``FilteringEnv`` runs unchanged. Each episode drawn by
``reset_episode`` gets its own gap pattern (``training_dropout_mask``: a
per-episode gap rate p ~ U[0, p_max], and in half the episodes one channel lost for up to
``blackout_s`` seconds). ``advance`` observes what a deployed filter would read: a missing channel
holds its last present value, and ``missing`` (0/1 per channel) says which ones are stale, the
flags a filter with ``FilterConfig.missing_mask`` reads in its window. The first measurement of an
episode is never missing, so there is always a value to hold.

``simulate`` is the base system's, complete: validation sets and the input normaliser stay on
complete data. Everything else (names, prior, bounds, ``f``/``g``) is the base system's.
"""

from __future__ import annotations

import torch
from daof.envs.system import StochasticSystem, SystemWrapper
from tensordict import TensorDict

__all__ = ["GappySystem", "MISSING_KEY", "training_dropout_mask"]

#: observation key of the 0/1 missing flags, one per measurement channel
MISSING_KEY = "missing"


def training_dropout_mask(
    shape: tuple[int, int, int], p_max: float, blackout_s: float, dt: float, generator: torch.Generator
) -> torch.Tensor:
    """Bool mask ``[runs, steps, channels]`` of random sensor gaps to train a filter on.

    Not the study's pattern, a spread around it: each run misses every entry with its own
    probability p ~ U[0, p_max], and half the runs also lose one random channel for U[0, blackout_s]
    seconds from a random step (clipped at the run's end).
    """
    runs, steps, dim = shape
    if not 0.0 <= p_max <= 1.0 or blackout_s < 0:
        raise ValueError(f"training dropout needs 0 <= p_max <= 1 and blackout_s >= 0, got {p_max}, {blackout_s}")
    dev = generator.device  # the mask lives where the generator draws (an env's device)
    p = torch.rand(runs, 1, 1, generator=generator, device=dev) * p_max
    mask = torch.rand(runs, steps, dim, generator=generator, device=dev) < p
    if blackout_s > 0:
        lost = torch.rand(runs, generator=generator, device=dev) < 0.5
        channel = torch.randint(dim, (runs,), generator=generator, device=dev)
        start = torch.randint(steps, (runs, 1), generator=generator, device=dev)
        length = (torch.rand(runs, 1, generator=generator, device=dev) * blackout_s / dt).round().long()
        k = torch.arange(steps, device=dev).view(1, -1)
        window = lost.view(-1, 1) & (k >= start) & (k < start + length)  # [runs, steps]
        mask |= window.unsqueeze(-1) & (torch.arange(dim, device=dev).view(1, 1, -1) == channel.view(-1, 1, 1))
    return mask


class GappySystem(SystemWrapper):
    """``base`` with random measurement gaps in every episode of up to ``steps`` measured steps."""

    reports_missing = True

    def __init__(self, base: StochasticSystem, p_max: float, blackout_s: float, steps: int):
        if steps < 1:
            raise ValueError(f"GappySystem needs episodes of steps >= 1, got {steps}")
        super().__init__(base)
        self.p_max, self.blackout_s, self.steps = float(p_max), float(blackout_s), int(steps)
        self._gaps(1, torch.Generator().manual_seed(0))  # bad options fail here, with the mask's error

    def _gaps(self, runs: int, generator: torch.Generator) -> torch.Tensor:
        shape = (runs, self.steps, self.measurement_dim)
        gaps = training_dropout_mask(shape, self.p_max, self.blackout_s, self.dt, generator)
        gaps[:, 0] = False  # the first measurement is always there
        return gaps

    def reset_episode(self, runs: int, generator: torch.Generator, device="cpu") -> TensorDict:
        sim = self.base.reset_episode(runs, generator, device)
        sim["gaps"] = self._gaps(runs, generator).to(device)
        sim["held"] = torch.zeros(runs, self.measurement_dim, device=device)
        return sim

    def advance(self, sim: TensorDict, generator: torch.Generator) -> tuple[TensorDict, TensorDict]:
        base_sim = sim.exclude("gaps", "held")
        new_sim, obs = self.base.advance(base_sim, generator)
        t = new_sim["t"]  # measured steps so far: 1 for the first measurement
        index = (t - 1).clamp(0, self.steps - 1)
        missing = sim["gaps"][torch.arange(len(t), device=t.device), index] & (t <= self.steps).unsqueeze(-1)
        y = torch.where(missing, sim["held"], obs["measurement"])
        new_sim["gaps"], new_sim["held"] = sim["gaps"], y
        obs["measurement"], obs[MISSING_KEY] = y, missing.to(y.dtype)
        return new_sim, obs

    def simulate(self, runs: int, steps: int, seed: int, device="cpu") -> TensorDict:
        """The base system's complete data (validation and normalisation sets have no gaps)."""
        return self.base.simulate(runs, steps, seed, device)

    def describe(self) -> dict:
        info = self.base.describe()
        info["training_gaps"] = {"p_max": self.p_max, "blackout_s": self.blackout_s, "steps": self.steps}
        return info
