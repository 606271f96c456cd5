"""Checks of a system's physical parameters: one ``ValueError`` line naming the field and what is valid."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

__all__ = ["as_seed", "check_params"]


def _finite(name: str, value) -> list[float]:
    values = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value]
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number (or a sequence of numbers), got {value!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return out


def as_seed(value, name: str = "seed") -> int:
    """``value`` as an int seed; a fractional, non-numeric or boolean one is a ``ValueError`` line, never truncated."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value).is_integer():
        return int(value)  # 3.0: nothing is lost
    raise ValueError(f"{name} must be an integer, got {value!r}")


def check_params(params, positive=(), nonnegative=(), intervals=(), probabilities=(), weights=()) -> None:
    """Check the named fields of a parameter dataclass; every numeric field must be finite.

    ``positive``/``nonnegative``: every entry > 0 / ≥ 0; ``intervals``: (low, high) pairs with
    low ≤ high; ``probabilities``: entries in [0, 1]; ``weights``: non-negative entries summing to 1.
    """
    for field, value in vars(params).items():
        if isinstance(value, (int, float, tuple, list)) and not isinstance(value, bool):
            _finite(field, value)
    for field in positive:
        if not all(v > 0 for v in _finite(field, getattr(params, field))):
            raise ValueError(f"{field} must be > 0, got {getattr(params, field)!r}")
    for field in nonnegative:
        if not all(v >= 0 for v in _finite(field, getattr(params, field))):
            raise ValueError(f"{field} must be >= 0, got {getattr(params, field)!r}")
    for field in intervals:
        low, high = _finite(field, getattr(params, field))
        if low > high:
            raise ValueError(f"{field} must be a range (low, high) with low <= high, got {getattr(params, field)!r}")
    for field in probabilities:
        if not all(0.0 <= v <= 1.0 for v in _finite(field, getattr(params, field))):
            raise ValueError(f"{field} must be in [0, 1], got {getattr(params, field)!r}")
    for field in weights:
        values = _finite(field, getattr(params, field))
        if any(v < 0 for v in values) or abs(sum(values) - 1.0) > 1e-9:
            raise ValueError(f"{field} must be non-negative weights summing to 1, got {getattr(params, field)!r}")
