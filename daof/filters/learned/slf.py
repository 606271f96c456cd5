"""SLF: x̂_t = φ(y_{t−N+1..t}, u_{t−N+1..t}), the supervised-learning filter (open loop, trained by regression).

The paper's learned baseline: the same network and window length as DAOF's policy, but its frames
hold measurements and controls only (no fed-back estimate), so every step of an episode can be
filtered at once (``run``). In an env it needs a window of its own layout:
``make_env(..., layout=slf.layout)``. Its window always starts behind copies of the first frame.
"""

from __future__ import annotations

import torch

from daof.filters.learned.base import LearnedFilter, register

__all__ = ["SLF"]


@register
class SLF(LearnedFilter):
    """The open-loop SLF (module docstring); ``daof.train.supervised`` trains it."""

    kind = "SLF"
    closed_loop = False

    def _frame(self, prev_estimate: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
        return measured  # open loop: no fed-back estimate in the frame

    @torch.inference_mode()
    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Every step at once: the windows of the open-loop frames, as the env would build them after a reset."""
        return self.estimate(self.layout.sliding_windows(self.open_loop_frames(y, u, u_prev)))

    def uncertainty_features(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """(estimates, features): the open-loop windows of every step at once, x̂_t and ρ_t (``LearnedFilter``)."""
        windows = self.layout.sliding_windows(self.open_loop_frames(y, u, u_prev))
        estimates = self.estimate(windows)
        return estimates, torch.cat([windows, estimates, self._startup_column(y)], -1)
