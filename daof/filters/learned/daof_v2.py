"""DAOF-v2, model-free, in its two action forms.

* ``DAOFv2`` (``v2_action="estimate"``, the paper's): x̂_t = π(h_t^N), squashed onto the plausible
  state range.
* ``DAOFv2Increment`` (``v2_action="increment"``): x̂_t = x̂_{t−1} + b_t ⊙ π(h_t^N), π ∈ [−1, 1]ⁿ.
  x̂_{t−1} is in h_t, so the function class is the same; the action is sized like the error, not
  like the state's range. b_t = correction_sigmas · max(σ_Δ, ρ_t · σ_0) from simulated training
  data (``increment_scale``). No model used.

``DAOFv2(config)`` builds the form ``config.v2_action`` asks for; both are ``DAOFv2`` instances.
"""

from __future__ import annotations

import torch

from daof.envs.system import StochasticSystem
from daof.filters.learned.base import LearnedFilter, UpdateFilter, register
from daof.filters.learned.config import FilterConfig
from daof.filters.learned.network import SCHEDULE_STEPS, startup_feature

__all__ = ["DAOFv2", "DAOFv2Increment", "increment_scale"]


def increment_scale(states: torch.Tensor, system: StochasticSystem) -> torch.Tensor:
    """σ_t = max(σ_Δ, ρ_t · σ_0) per step t = 1..SCHEDULE_STEPS, [S, n], from [runs, steps, n] true states.

    σ_Δ: std of x_t − x_{t−1} over every run and step; σ_0: std of x_1 − x̂_0 (the prior mean's error
    at the first estimate); ρ_t the start-up feature. Data only: no model of the dynamics.
    """
    step_change = (states[:, 1:] - states[:, :-1]).flatten(0, 1).std(0)
    first_error = (states[:, 0] - system.prior.mean.to(states)).pow(2).mean(0).sqrt()
    rho = startup_feature(torch.arange(1, SCHEDULE_STEPS + 1, device=states.device).unsqueeze(-1))
    return torch.maximum(step_change, rho * first_error).float()


@register
class DAOFv2(LearnedFilter):
    """DAOF-v2 with the paper's action: the estimate x̂_t = π(h_t^N) itself (module docstring)."""

    kind = "DAOF-v2"

    @classmethod
    def for_config(cls, config: FilterConfig) -> type[LearnedFilter]:
        return DAOFv2Increment if config.v2_action == "increment" else DAOFv2


class DAOFv2Increment(UpdateFilter, DAOFv2):
    """DAOF-v2 acting by increments: x̂_t = x̂_{t−1} + b_t ⊙ π(h_t^N), b_t fitted on simulated data."""

    def predict(self, prev_estimate: torch.Tensor, prev_control: torch.Tensor) -> torch.Tensor:
        """No model: the update is added to x̂_{t−1} itself."""
        return prev_estimate

    def _initial_bound(self) -> torch.Tensor:
        return self.config.correction_sigmas * self.system.error_scale

    def _fit_action(self, data) -> None:
        self.correction_scale.copy_(self.config.correction_sigmas * increment_scale(data["state"], self.system))
