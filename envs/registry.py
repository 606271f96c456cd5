"""``make_system``: systems by name, with scenario and parameter overrides checked up front."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from daof.envs.system import StochasticSystem

__all__ = ["make_system", "register_system", "SYSTEMS"]

#: name -> (system class, parameter dataclass); filled by register_system
SYSTEMS: dict[str, tuple[Callable[..., StochasticSystem], type]] = {}


def register_system(name: str, cls, params_cls) -> None:
    """Make ``cls(scenario=..., params=params_cls(...))`` available as ``make_system(name)``."""
    SYSTEMS[name] = (cls, params_cls)


def make_system(name: str, scenario: str = "nominal", replay=None, **overrides) -> StochasticSystem:
    """Build a system by name (``veh2dof``, ``veh14dof``, ``linear``).

    ``overrides`` replace fields of the system's parameter dataclass; an unknown name, scenario
    or field is a ``ValueError`` that lists what is valid. ``replay`` (a mapping of
    ``RecordedSystem``'s ``runs``, ``steps``, ``seed``, ``cache_dir``) wraps the system so that env
    episodes replay a recorded bank and ``simulate`` is memoised (``daof.envs.recorded``).
    """
    if name not in SYSTEMS:
        raise ValueError(f"unknown system {name!r}; known systems: {sorted(SYSTEMS)}")
    cls, params_cls = SYSTEMS[name]
    if scenario not in cls.scenarios:
        raise ValueError(f"unknown scenario {scenario!r} for {name}; valid: {list(cls.scenarios)}")
    valid = {f.name for f in dataclasses.fields(params_cls)}
    unknown = sorted(set(overrides) - valid)
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown} for {name}; valid: {sorted(valid)}")
    system = cls(scenario=scenario, params=params_cls(**overrides))
    if replay:
        from daof.envs.recorded import RecordedSystem

        system = RecordedSystem.from_mapping(system, replay)
    return system
