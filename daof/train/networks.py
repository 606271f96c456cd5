"""The distributional critic of DSAC-T for a learned filter."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from daof.filters.learned import LearnedFilter

__all__ = ["CRITIC_FORMS", "WINDOW_INITS", "FilterCritic", "make_critic", "start_on_newest_frame"]

#: "mlp": Q from an MLP on (h, a) | "quadratic": μ = V(h) − Σ_i p_i(h)(a_i − m_i(h))² (NAF-style)
CRITIC_FORMS = ("mlp", "quadratic")
#: first-layer init over the window: "uniform" (PyTorch's default on every input) | "newest"
#: (``start_on_newest_frame``)
WINDOW_INITS = ("uniform", "newest")


def start_on_newest_frame(mlp: nn.Sequential, older_width: int) -> None:
    """Zero the first layer's weights on the N − 1 older frames (the first ``older_width`` inputs).

    The other inputs (the newest frame, ν_t, ρ_t, the action) get PyTorch's default init for
    their own fan-in, so the network starts as the same network on a one-frame window would, and
    the older frames enter only as far as their gradients move those weights.
    """
    first = next(m for m in mlp if isinstance(m, nn.Linear))
    if not 0 <= older_width < first.in_features:
        raise ValueError(f"older_width must be in [0, {first.in_features}), got {older_width}")
    bound = 1.0 / (first.in_features - older_width) ** 0.5
    with torch.no_grad():
        first.weight[:, :older_width].zero_()
        first.weight[:, older_width:].uniform_(-bound, bound)
        first.bias.uniform_(-bound, bound)


class FilterCritic(nn.Module):
    """Q(h, a) -> (mean μ, raw scale) per reward term on the actor's own input features (normalised window, ν_t, ρ_t).

    The window uses the filter's own input normalisation (shared buffers, not copied) and the
    action is mapped to [−1, 1] by the actor's bounds, so the critic sees O(1) inputs.

    ``form="quadratic"`` makes the mean quadratic in the action, as in NAF (Gu et al., 2016):
    μ_k = V_k(h) − Σ_{i∈k} p_i(h)(a_i − m_i(h))², p_i = softplus > 0, with the raw scale from h
    alone. For a reward −Σ_i W_i(x_i − x̂_i)² with x̂ affine in a (DAOF-v1's update, DAOF-v2's
    increment) and γ = 0 this is the exact form of Q, so the critic's argmax m(h) is never
    misranked by the shape of the fit; the sum over i∈k is over every state (one reward term)
    or over state k alone (a critic per state).
    """

    def __init__(
        self, actor: LearnedFilter, num_cells: int = 256, depth: int = 3, reward_terms: int = 1, form: str = "mlp"
    ):
        super().__init__()
        if form not in CRITIC_FORMS:
            raise ValueError(f"critic form must be one of {CRITIC_FORMS}, got {form!r}")
        n = actor.system.state_dim
        if reward_terms not in (1, n):
            raise ValueError(f"reward_terms must be 1 or the state dim {n}, got {reward_terms}")
        self._actor = [actor]  # a reference, not a submodule: its weights are not the critic's
        self.form = form
        self.reward_terms = reward_terms
        quadratic = form == "quadratic"
        self.mlp = MLP(
            in_features=actor.policy.feature_dim + (0 if quadratic else n),
            out_features=2 * reward_terms + (2 * n if quadratic else 0),
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.GELU,
        )
        if quadratic:  # m(h) starts at 0: no action is preferred to the filter's zero action before data say so
            with torch.no_grad():
                last = self.mlp[-1]
                last.weight[2 * reward_terms : 2 * reward_terms + n].zero_()
                last.bias[2 * reward_terms : 2 * reward_terms + n].zero_()

    def forward(self, window: torch.Tensor, action: torch.Tensor, step=None) -> torch.Tensor:
        actor = self._actor[0]
        h = actor.policy.features(window, step)
        a = (action - (actor.high + actor.low) / 2) / ((actor.high - actor.low) / 2)
        if self.form == "mlp":
            return self.mlp(torch.cat([h, a], -1))
        K, n = self.reward_terms, a.shape[-1]
        value, raw_scale, best, curvature = self.mlp(h).split([K, K, n, n], -1)
        penalty = nn.functional.softplus(curvature) * (a - best).pow(2)
        if K == 1:
            penalty = penalty.sum(-1, keepdim=True)
        return torch.stack([value - penalty, raw_scale], -1).flatten(-2)


def make_critic(
    actor: LearnedFilter, num_cells: int = 256, depth: int = 3, reward_terms: int = 1, form: str = "mlp"
) -> TensorDictModule:
    """Critic reading (h_t^N, t where the actor reads it, the action key), writing ``state_action_value`` [.., 2K]."""
    net = FilterCritic(actor, num_cells, depth, reward_terms, form)
    in_keys = dict(zip(["window", "step"], actor.policy_in_keys)) | {"action": actor.action_key}
    return TensorDictModule(net, in_keys=in_keys, out_keys=["state_action_value"])
