"""What the training and the experiment configurations share: unknown override keys and Hydra's errors as one line."""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing

__all__ = ["check_override_keys", "one_line"]


def _dataclass_of(tp) -> type | None:
    """The dataclass a field's type holds (``X``, ``X | None``), or None."""
    if dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next((arg for arg in typing.get_args(tp) if dataclasses.is_dataclass(arg)), None)
    return None


def known_key(schema: type, parts: list[str]) -> str | None:
    """None if ``parts`` is a key of ``schema``, else the nearest valid key at the level that failed ("": none)."""
    hints = typing.get_type_hints(schema)
    head, rest = parts[0], parts[1:]
    if head not in hints:
        near = difflib.get_close_matches(head, sorted(hints), n=1)
        return near[0] if near else ""
    if not rest:
        return None
    tp = hints[head]
    inner = _dataclass_of(tp)
    if inner is not None:
        return known_key(inner, rest)
    value = _dataclass_of(typing.get_args(tp)[1]) if typing.get_origin(tp) is dict else None
    if value is not None and len(rest) > 1:  # any key of the dict (profiles.tiny), then the value's own fields
        return known_key(value, rest[1:])
    return None  # a key of a free-form dict, or an element: left to OmegaConf


def check_override_keys(schema: type, overrides: list[str], what: str, where: str, groups=()) -> None:
    """An override of a key ``schema`` lacks (config group names aside): one ``ValueError`` line, nearest key named."""
    for item in overrides:
        if "=" not in item and not item.startswith("~"):
            raise ValueError(f"override {item!r} is not key=value")
        key = item.split("=", 1)[0].lstrip("+~")
        if key in groups:
            continue
        near = known_key(schema, key.split("."))
        if near is not None:
            hint = f"; did you mean {near!r}?" if near else ""
            raise ValueError(f"unknown {what} key {key!r}{hint} ({where})")


def one_line(error: BaseException) -> str:
    """Hydra's or OmegaConf's message, and its cause's, on one line."""
    parts = []
    while error is not None and len(parts) < 2:
        lines = [x.strip() for x in str(error).strip().splitlines() if x.strip()]
        lines = [x for x in lines if not x.startswith(("full_key", "object_type", "reference_type", "To append"))]
        parts += [x.rstrip(".") for x in lines[: 2 - len(parts)] if x.rstrip(".") not in parts]
        error = error.__cause__
    return ": ".join(parts) or type(error).__name__
