"""The distributional critic of DSAC-T for a learned filter."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from daof.filters.learned import LearnedFilter

__all__ = ["FilterCritic", "make_critic"]


class FilterCritic(nn.Module):
    """Q(h, a) -> (mean μ, raw scale) per reward term on the actor's own input features (normalised window, ν_t, ρ_t).

    The window uses the filter's own input normalisation (shared buffers, not copied) and the
    action is mapped to [−1, 1] by the actor's bounds, so the critic sees O(1) inputs.
    """

    def __init__(self, actor: LearnedFilter, num_cells: int = 256, depth: int = 3, reward_terms: int = 1):
        super().__init__()
        self._actor = [actor]  # a reference, not a submodule: its weights are not the critic's
        n = actor.system.state_dim
        self.mlp = MLP(
            in_features=actor.policy.feature_dim + n,
            out_features=2 * reward_terms,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.GELU,
        )

    def forward(self, window: torch.Tensor, action: torch.Tensor, step=None) -> torch.Tensor:
        actor = self._actor[0]
        h = actor.policy.features(window, step)
        a = (action - (actor.high + actor.low) / 2) / ((actor.high - actor.low) / 2)
        return self.mlp(torch.cat([h, a], -1))


def make_critic(actor: LearnedFilter, num_cells: int = 256, depth: int = 3, reward_terms: int = 1) -> TensorDictModule:
    """Critic reading (h_t^N, t where the actor reads it, the action key), writing ``state_action_value`` [.., 2K]."""
    net = FilterCritic(actor, num_cells, depth, reward_terms)
    in_keys = dict(zip(["window", "step"], actor.policy_in_keys)) | {"action": actor.action_key}
    return TensorDictModule(net, in_keys=in_keys, out_keys=["state_action_value"])
