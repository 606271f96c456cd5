"""``make_system``: systems by name or import path, with scenario and parameter overrides checked up front.

A system is named one of three ways:

* a registered name (``register_system``): ``veh2dof``, ``linear``, ``veh14dof``;
* an import path ``package.module:Class`` to a ``StochasticSystem`` subclass of the user's own code;
* the name of an entry point in the ``daof.systems`` group of an installed distribution
  (``[project.entry-points."daof.systems"] mine = "my_pkg.my_module:MySystem"``).

A class from an import path or an entry point is built as ``cls(scenario=..., params=cls.params_class(**overrides))``
when it names a parameter dataclass in ``params_class``, else as ``cls(scenario=...)`` (or ``cls()`` when its
constructor takes no scenario), refusing parameter overrides. Its instance's ``name`` is set to what it was
built from, so checkpoints and reports record the string that rebuilds it (docs/custom_system.md).
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import inspect
import sys
from collections.abc import Callable
from pathlib import Path

from daof.envs.system import StochasticSystem

__all__ = [
    "ENTRY_POINT_GROUP",
    "SYSTEMS",
    "import_root",
    "is_import_path",
    "make_system",
    "register_system",
    "system_class",
    "system_entry_point",
]

#: name -> (system class, parameter dataclass); filled by register_system
SYSTEMS: dict[str, tuple[Callable[..., StochasticSystem], type]] = {}
#: the entry point group installed distributions name their systems in
ENTRY_POINT_GROUP = "daof.systems"


def register_system(name: str, cls, params_cls) -> None:
    """Make ``cls(scenario=..., params=params_cls(...))`` available as ``make_system(name)``."""
    SYSTEMS[name] = (cls, params_cls)


def is_import_path(name: str) -> bool:
    """Whether ``name`` is written as an import path (``module:Class``) rather than a registered name."""
    return ":" in name


def _import_class(path: str) -> type:
    """The class an import path ``package.module:Class`` names; a bad path is one ``ValueError`` line."""
    module_name, _, attr = path.partition(":")
    if not module_name or not attr or ":" in attr:
        raise ValueError(f"system {path!r} is not an import path 'package.module:Class'")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        own = error.name is not None and (module_name + ".").startswith(error.name + ".")
        where = "" if own else f" while importing {module_name!r}"
        hint = "is its folder on sys.path?"
        raise ValueError(f"system {path!r}: no module named {error.name!r}{where} ({hint})") from None
    except Exception as error:  # the user's module raised on import
        first = (str(error).strip().splitlines() or [""])[0]
        why = f"{type(error).__name__}: {first}"
        raise ValueError(f"system {path!r}: importing {module_name!r} failed: {why}") from None
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"system {path!r}: module {module_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    return obj


def system_entry_point(name: str):
    """The ``daof.systems`` entry point called ``name``, or None."""
    return next(iter(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP, name=name)), None)


def system_class(name: str) -> tuple[type, type | None]:
    """(system class, parameter dataclass or None) for a registered name, an import path or an entry point."""
    if name in SYSTEMS:
        return SYSTEMS[name]
    if is_import_path(name):
        cls = _import_class(name)
    else:
        entry = system_entry_point(name)
        if entry is None:
            raise ValueError(
                f"unknown system {name!r}; known systems: {sorted(SYSTEMS)}, "
                f"an import path 'package.module:Class' or a {ENTRY_POINT_GROUP!r} entry point"
            )
        try:
            cls = entry.load()
        except Exception as error:
            first = (str(error).strip().splitlines() or [""])[0]
            raise ValueError(f"system {name!r}: loading entry point {entry.value!r} failed: {first}") from None
    if not (isinstance(cls, type) and issubclass(cls, StochasticSystem)):
        raise ValueError(f"system {name!r} is not a StochasticSystem subclass (got {type(cls).__name__} {cls!r})")
    registered = [p for c, p in SYSTEMS.values() if c is cls]  # a registered class by its path: the same params
    params_cls = getattr(cls, "params_class", None) or (registered[0] if registered else None)
    if params_cls is not None and not (isinstance(params_cls, type) and dataclasses.is_dataclass(params_cls)):
        raise ValueError(f"system {name!r}: params_class must be a dataclass, got {params_cls!r}")
    return cls, params_cls


def _build(cls: type, params_cls: type | None, name: str, scenario: str, overrides: dict) -> StochasticSystem:
    if params_cls is not None:
        return cls(scenario=scenario, params=params_cls(**overrides))
    if overrides:
        raise ValueError(f"system {name} takes no parameter overrides (its class has no params_class), got {overrides}")
    takes_scenario = "scenario" in inspect.signature(cls).parameters
    return cls(scenario=scenario) if takes_scenario else cls()


def make_system(name: str, scenario: str = "nominal", replay=None, **overrides) -> StochasticSystem:
    """Build a system by registered name (``veh2dof``, ``veh14dof``, ``linear``), import path or entry point.

    ``overrides`` replace fields of the system's parameter dataclass; an unknown name, scenario
    or field is a ``ValueError`` that lists what is valid. ``replay`` (a mapping of
    ``RecordedSystem``'s ``runs``, ``steps``, ``seed``, ``cache_dir``) wraps the system so that env
    episodes replay a recorded bank and ``simulate`` is memoised (``daof.envs.recorded``).
    """
    cls, params_cls = system_class(name)
    if scenario not in cls.scenarios:
        raise ValueError(f"unknown scenario {scenario!r} for {name}; valid: {list(cls.scenarios)}")
    if params_cls is not None:
        valid = {f.name for f in dataclasses.fields(params_cls)}
        unknown = sorted(set(overrides) - valid)
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown} for {name}; valid: {sorted(valid)}")
    system = _build(cls, params_cls, name, scenario, overrides)
    if name not in SYSTEMS:
        system.name = name  # the string that rebuilds it: what checkpoints, caches and reports record
    if replay:
        from daof.envs.recorded import RecordedSystem

        system = RecordedSystem.from_mapping(system, replay)
    return system


def import_root(name: str) -> Path | None:
    """The folder a fresh interpreter needs on ``sys.path`` to import the system ``name`` (None: nothing to add).

    For an import path, the folder holding its top-level package (or module), found from the module's
    file; training subprocesses get it on ``PYTHONPATH`` (``daof.experiments.jobs``).
    """
    if not is_import_path(name) or name in SYSTEMS:
        return None
    system_class(name)  # imports the module (or says in one line why not)
    module_name = name.partition(":")[0]
    if module_name == "__main__":
        raise ValueError(f"system {name!r} is defined in the script being run: a fresh process cannot import it; "
                         "move the class into a module")  # fmt: skip
    file = getattr(sys.modules[module_name], "__file__", None)
    if file is None:
        return None
    path = Path(file).resolve()
    if path.name == "__init__.py":
        path = path.parent
    return path.parents[len(module_name.split(".")) - 1]
