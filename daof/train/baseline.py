"""A control variate for the reward of a filter that acts by updates: the reward of the zero action.

    r'_t = r_t(a_t) − r_t(0),   r_t(a) = −Σ_i W_t,i (x_t,i − x̂_t,i(a))²

x̂_t(0) is what the filter estimates with a zero action: DAOF-v1's prediction f(x̂_{t−1}, u_{t−1})
plus K̄_t ν_t, its reference update. r_t(0) does not depend on the action, so with γ = 0 the
critic's target E[r' | h, a] is Q(h, a) minus a function of h alone: the same argmax and the same
action gradient for the actor. What changes is the noise of the target. With e = x̂_t(0) − x_t,

    r' = −W (2 b a e + b² a²),

so the spread that no action can change (W e², the posterior error) is gone and what is left
shrinks with |a|: near a = 0, r'/a estimates the optimal action with noise √P⁺/b per sample
whatever the size of a, where r/a has the noise of W e² / a. A residual policy that starts at
a = 0 (DAOF-v1's residual on K̄_t ν_t) lives exactly there (docs/linear_check.md; log 2026-12-03).
Training-time only: the reward needs the true state anyway; the deployed filter is unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from daof.filters.learned import LearnedFilter, schedule_row

__all__ = ["BASELINES", "ZeroActionBaseline"]

#: what ``reward.baseline`` may be
BASELINES = ("none", "zero_action")


class ZeroActionBaseline:
    """Takes r_t(0) off the rewards of a batch of transitions (module docstring).

    Args:
        filter: the filter being trained; it must act by updates (``LearnedFilter.acts_by_update``).
        weights: the env's reward weights W, [n] or one row per step [S, n] (the last row held).
    """

    def __init__(self, filter: LearnedFilter, weights: torch.Tensor):
        if not filter.acts_by_update:
            raise ValueError(f"reward.baseline=zero_action needs a filter that acts by updates, not {filter.name}")
        self.filter = filter
        self.weights = weights

    def terms(self, batch: TensorDictBase) -> torch.Tensor:
        """r_t(0) per state, [B, n]."""
        f, step = self.filter, batch["step"]
        zero = torch.zeros_like(batch["prev_estimate"])
        estimate = f._add_prediction(zero, batch["prev_estimate"], batch["prev_control"], step, batch[f.input_key])
        weights = self.weights if self.weights.ndim == 1 else schedule_row(self.weights, step)
        return -(batch["true_state"] - estimate).pow(2) * weights

    def subtract(self, batch: TensorDictBase) -> TensorDictBase:
        """The batch with r_t(0) taken off ``("next", "reward")`` (and off the per-state terms where kept)."""
        terms = self.terms(batch)
        batch["next", "reward"] = batch["next", "reward"] - terms.sum(-1, keepdim=True)
        if ("next", "reward_per_state") in batch.keys(True):
            batch["next", "reward_per_state"] = batch["next", "reward_per_state"] - terms
        return batch
