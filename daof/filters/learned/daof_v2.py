"""DAOF-v2, model-free: x̂_t = π(h_t^N), the paper's form, squashed onto the plausible state range.

No model used: the network reads the window h_t^N (x̂_{t−1} is in it) and gives the estimate
itself. Its increment form x̂_t = x̂_{t−1} + b_t ⊙ π(h_t^N) (``v2_action="increment"``) was measured
worse on every system and removed on 2026-12-07 (docs/log/2026-12-07-daof-v2-increment-form-removed.md).
"""

from __future__ import annotations

from daof.filters.learned.base import LearnedFilter, register

__all__ = ["DAOFv2"]


@register
class DAOFv2(LearnedFilter):
    """DAOF-v2 with the paper's action: the estimate x̂_t = π(h_t^N) itself (module docstring)."""

    kind = "DAOF-v2"
