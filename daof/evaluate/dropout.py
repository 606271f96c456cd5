"""Sensor dropout for the study (issue 6, item 3): measurement entries set to NaN.

Every channel is missing independently with probability ``p`` per step, and one channel is blacked
out for a stretch of time in every run (the issue's scenario: the yaw-rate channel for 1 s). The
mask comes from its own seeded generator and depends only on the data's shape, the options and the
seed, never on the data's values, so the same options give the same gaps on any system. NaN is how
every filter in ``daof.filters`` recognises a missing channel (docs/missing_data.md). The gaps
that learned filters are trained through are ``daof.envs.gaps.training_dropout_mask``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from daof.envs.checks import as_seed
from daof.envs.system import StochasticSystem

__all__ = ["Dropout", "apply_dropout", "dropout_mask"]

#: (channel index or name, start [s], duration [s])
Blackout = tuple[int | str, float, float]


def _channel_index(channel: int | str, dim: int, names) -> int:
    if isinstance(channel, str):
        if names is None or channel not in names:
            raise ValueError(f"blackout channel {channel!r} is not a measurement channel (channels: {names})")
        return list(names).index(channel)
    if not 0 <= int(channel) < dim:
        raise ValueError(f"blackout channel {channel} is out of range for {dim} measurement channels")
    return int(channel)


def dropout_mask(
    shape: tuple[int, int, int],
    p: float,
    blackout: Blackout | None = None,
    seed: int = 0,
    *,
    dt: float | None = None,
    channel_names=None,
) -> torch.Tensor:
    """Bool mask ``[runs, steps, channels]``, True where the measurement is missing.

    Random gaps: each entry independently with probability ``p``. Blackout ``(channel, start_s,
    duration_s)``: that channel in every run at the steps whose time t·Δτ (t = 1..T, the
    ``daof.envs.system`` convention: data index k is t = k + 1) lies in [start_s, start_s + duration_s);
    it must fit inside the data.
    """
    runs, steps, dim = shape
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"dropout probability p must be in [0, 1], got {p}")
    generator = torch.Generator().manual_seed(as_seed(seed, "dropout seed"))
    mask = torch.rand(runs, steps, dim, generator=generator) < p
    if blackout is not None:
        channel, start_s, duration_s = blackout
        if dt is None or dt <= 0:
            raise ValueError(f"a blackout in seconds needs the step dt > 0, got {dt}")
        if start_s < 0 or duration_s <= 0:
            raise ValueError(f"blackout needs start_s >= 0 and duration_s > 0, got {start_s}, {duration_s}")
        if start_s + duration_s > steps * dt + dt / 2:
            raise ValueError(
                f"blackout [{start_s}, {start_s + duration_s}) s does not fit in {steps} steps of {dt} s "
                f"({steps * dt:g} s)"
            )
        index = _channel_index(channel, dim, channel_names)
        time = torch.arange(1, steps + 1, dtype=torch.float64) * dt
        # half-step tolerance so that a boundary on the step grid is not lost to rounding
        window = (time > start_s - dt / 2) & (time < start_s + duration_s - dt / 2)
        mask[:, window, index] = True
    return mask


def apply_dropout(
    data: TensorDictBase,
    p: float,
    blackout: Blackout | None = None,
    seed: int = 0,
    *,
    dt: float | None = None,
    channel_names=None,
) -> TensorDictBase:
    """A copy of study ``data`` whose ``measurement`` is NaN where ``dropout_mask`` says missing.

    Everything else (true state, controls) is unchanged; entries that were already NaN stay NaN.
    """
    y = data["measurement"]
    if y.ndim != 3:
        raise ValueError(f"data['measurement'] must be [runs, steps, channels], got {tuple(y.shape)}")
    mask = dropout_mask(tuple(y.shape), p, blackout, seed, dt=dt, channel_names=channel_names).to(y.device)
    out = data.clone()
    out.set("measurement", y.masked_fill(mask, math.nan))
    return out


@dataclass(frozen=True)
class Dropout:
    """The study's ``dropout`` option: random gaps with probability ``p`` plus one blackout.

    The default is the issue's scenario on veh2dof: 10 % gaps per channel and step, and the yaw-rate
    channel lost for 1 s from t = 4 s. ``blackout=None`` keeps the random gaps only.
    """

    p: float = 0.1
    blackout: Blackout | None = ("yaw_rate", 4.0, 1.0)
    seed: int = 0

    def __post_init__(self):
        as_seed(self.seed, "dropout seed")

    def apply(self, data: TensorDictBase, system: StochasticSystem) -> TensorDictBase:
        """``apply_dropout`` with the system's step and channel names."""
        return apply_dropout(
            data, self.p, self.blackout, self.seed, dt=system.dt, channel_names=system.measurement_names
        )

    def describe(self) -> dict:
        """Plain data that identifies the gaps (the study's cache key and results.json)."""
        blackout = None
        if self.blackout is not None:
            channel, start_s, duration_s = self.blackout
            blackout = {"channel": channel, "start_s": float(start_s), "duration_s": float(duration_s)}
        return {"p": float(self.p), "blackout": blackout, "seed": as_seed(self.seed, "dropout seed")}
