"""Learned filters as TensorDict modules: DAOF-v1, DAOF-v2 and the supervised SLF, one class each.

* ``DAOFv2``: x̂_t = π(h_t^N)                          (model-free; its increment form was removed on
  2026-12-07: docs/log/2026-12-07-daof-v2-increment-form-removed.md)
* ``DAOFv1``: x̂_t = f(x̂_{t−1}, u_{t−1}) + K̄_t ν_t + b_t ⊙ π(h_t^N)  (model predictor + the update
  of a UKF's mean gain K̄_t at step t + a learned residual, π ∈ [−1, 1]ⁿ, bounded by b_t =
  correction_sigmas · that UKF's √diag P⁺_t)
* ``SLF``:    x̂_t = φ(y_{t−N+1..t}, u_{t−N+1..t})     (open loop, trained by regression)
* ``KalmanNet``: x̂_t = f(x̂_{t−1}, u_{t−1}) + K_t ν_t, K_t from a recurrent network (Revach et al. 2022;
  trained by MSE over sequences, ``daof.train.kalmannet``)

All share ``LearnedFilter`` (``base``): the network (window normaliser -> MLP -> (loc, log σ)), the
window's ``layout``, ``run(data)`` (filters simulated data exactly as the env does),
``filter_module(env=None)`` (the deterministic filter, what a user runs; with ``env`` it first
checks the env's window is the filter's) and ``save``; ``load_filter`` reads a saved filter or a
training checkpoint back. ``make_filter(kind, config, system)`` (or ``LearnedFilter(config,
system)``) builds the class a config asks for. DSAC-T's views of the network (the stochastic actor,
the collector's policy) are in ``daof.train.policies``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from daof.envs.system import StochasticSystem
from daof.filters.learned.base import KINDS, LearnedFilter, UpdateFilter, filter_class, plain_data
from daof.filters.learned.checkpoint import load_filter
from daof.filters.learned.config import MISSING_FILLS, RETIRED_OPTIONS, FilterConfig, retire_options
from daof.filters.learned.daof_v1 import DAOFv1
from daof.filters.learned.daof_v2 import DAOFv2
from daof.filters.learned.kalmannet import KalmanNet
from daof.filters.learned.network import SCHEDULE_STEPS, PolicyNet, hold_last_value, schedule_row, startup_feature
from daof.filters.learned.slf import SLF

__all__ = [
    "KINDS",
    "MISSING_FILLS",
    "RETIRED_OPTIONS",
    "SCHEDULE_STEPS",
    "DAOFv1",
    "DAOFv2",
    "FilterConfig",
    "KalmanNet",
    "LearnedFilter",
    "PolicyNet",
    "SLF",
    "UpdateFilter",
    "filter_class",
    "hold_last_value",
    "load_filter",
    "make_filter",
    "plain_data",
    "schedule_row",
    "sliding_windows",
    "startup_feature",
]


def make_filter(
    kind: str,
    config: FilterConfig | Mapping | None = None,
    system: StochasticSystem | None = None,
    **fields,
) -> LearnedFilter:
    """A learned filter of ``kind`` ("DAOF-v1", "DAOF-v2", "SLF").

    ``config``: a ``FilterConfig`` of that kind, or a mapping of its fields (``kind`` aside);
    ``fields`` set or replace fields. ``system``: the system object to filter (the config's
    ``system`` and ``scenario`` fields default to its name and scenario), or just its name; by
    default the config's, built by name and scenario. ``make_filter("SLF", system="veh2dof", window=5)``.
    A retired option (``RETIRED_OPTIONS``) is read as a stored config's is (``retire_options``): its
    surviving value is ignored, any other refused in one line (``v2_action="increment"``).
    """
    if isinstance(system, str):
        system, fields = None, {"system": system, **fields}
    elif system is not None and not isinstance(config, FilterConfig):
        fields = {"system": system.name, "scenario": system.scenario, **fields}
    if isinstance(config, FilterConfig):
        if config.kind != kind:
            raise ValueError(f"make_filter({kind!r}) got a {config.kind} config")
        fields = retire_options(kind, fields)
        config = dataclasses.replace(config, **fields) if fields else config
    else:
        config = FilterConfig.from_dict({**dict(config or {}), **fields, "kind": kind})
    return filter_class(config)(config, system)


def sliding_windows(frames, window: int):
    """[runs, steps, F] frames -> [runs, steps, N·F] windows padded with the first frame (the SLF's).

    Kept for code written before ``FrameLayout``: ``filter.layout.sliding_windows(frames)`` is the same.
    """
    from daof.envs.history import sliding_windows as windows

    return windows(frames, window)
