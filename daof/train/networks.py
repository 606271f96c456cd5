"""The distributional critic of DSAC-T for a learned filter."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from daof.filters.learned import LearnedFilter, schedule_row

__all__ = ["CRITIC_FORMS", "CRITIC_SCALES", "WINDOW_INITS", "FilterCritic", "make_critic", "start_on_newest_frame"]

#: "mlp": Q from an MLP on (h, a) | "quadratic": μ = V(h) − Σ_i p_i(h)(a_i − m_i(h))² (NAF-style) |
#: "reward_quadratic": the same with p_i the reward's own curvature in the action (exact at γ = 0)
CRITIC_FORMS = ("mlp", "quadratic", "reward_quadratic")
#: the value distribution's std σ: "window": from h alone | "reward": a quadratic reward's own spread,
#: growing with the action's distance from m(h) (``FilterCritic``, quadratic forms with a critic per state)
CRITIC_SCALES = ("window", "reward")
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
    estimate) and γ = 0 this is the exact form of Q, so the critic's argmax m(h) is never
    misranked by the shape of the fit; the sum over i∈k is over every state (one reward term)
    or over state k alone (a critic per state).

    ``form="reward_quadratic"`` keeps that mean but does not learn p: at γ = 0 it is known. The
    reward −Σ_i W_i(x_i − x̂_i)² with x̂_i = c_i + w_i a_i (w_i the action's half-range times the
    update bound b_t where the actor acts by updates) is −Σ_i W_i w_i² (a_i − a*_i)², so
    p_i = W_i w_i² and the critic learns only V(h), its scale and m(h) = E[a* | h], the action of
    the estimate E[x | h]. Its action-ranking is then exact by construction, and its precision is
    that of the regression m(h), not that of a surface fitted over the whole action range
    (docs/experiment2.md; log 2026-12-04). ``reward_weights`` is W ([n], or a [S, n] schedule read
    at the step the actor reads; without the step, its settled row).

    ``scale="reward"`` (quadratic forms, a critic per state) gives σ the spread a quadratic reward
    term r = −p(a − a*)² has at γ = 0 when a* | h has mean m and variance v (Gaussian):
    Var r = p²(4(a − m)²v + 2v²), i.e. σ² = s² + 2√2·p·s·(a − m)² with s(h) = softplus(raw) the
    spread at a = m (m and p detached: they are fitted by the mean). DSAC-T weights each sample's
    mean term by 1/(σ² + ε), so with ε small against σ² the fit of m(h) is the efficient weighted
    least squares: far-explored actions, whose rewards are the noisiest, count less
    (``diagnostics/reward_vs_label.py``). ``scale="window"`` is σ = softplus(raw) from h alone.
    """

    def __init__(
        self,
        actor: LearnedFilter,
        num_cells: int = 256,
        depth: int = 3,
        reward_terms: int = 1,
        form: str = "mlp",
        reward_weights: torch.Tensor | None = None,
        scale: str = "window",
    ):
        super().__init__()
        if form not in CRITIC_FORMS:
            raise ValueError(f"critic form must be one of {CRITIC_FORMS}, got {form!r}")
        if scale not in CRITIC_SCALES:
            raise ValueError(f"critic scale must be one of {CRITIC_SCALES}, got {scale!r}")
        if (form == "reward_quadratic") != (reward_weights is not None):
            raise ValueError("reward_weights are needed by, and only by, the 'reward_quadratic' critic form")
        n = actor.system.state_dim
        if reward_terms not in (1, n):
            raise ValueError(f"reward_terms must be 1 or the state dim {n}, got {reward_terms}")
        if scale == "reward" and (form == "mlp" or reward_terms != n):
            raise ValueError("critic scale 'reward' needs a quadratic critic form with a critic per state")
        self.scale = scale
        self._actor = [actor]  # a reference, not a submodule: its weights are not the critic's
        self.form = form
        self.reward_terms = reward_terms
        known = form == "reward_quadratic"
        quadratic = form != "mlp"
        if known:
            self.register_buffer("reward_weights", torch.as_tensor(reward_weights, dtype=torch.float32).clone())
        self.mlp = MLP(
            in_features=actor.policy.feature_dim + (0 if quadratic else n),
            out_features=2 * reward_terms + ((n if known else 2 * n) if quadratic else 0),
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
        if self.form == "mlp":
            actor = self._actor[0]
            mid, half = actor.squash_affine()
            return self.mlp(torch.cat([actor.policy.features(window, step), (action - mid) / half], -1))
        return self.from_action_free(self.action_free(window, step), action)

    @property
    def splits_action(self) -> bool:
        """Whether the output is ``from_action_free(action_free(h, t), a)``: the quadratic forms (MLP on h alone)."""
        return self.form != "mlp"

    def action_free(self, window: torch.Tensor, step=None) -> torch.Tensor:
        """A quadratic form's (V, raw scale, m, p) per window, concatenated on the last dim: all that reads h."""
        if window.ndim > 2 and window.shape[-2] > 1 and window.stride(-2) == 0:
            # one window expanded beside several actions (DSACTLoss's actor_samples): the MLP of a
            # quadratic form reads h alone, so it runs once per window and broadcasts
            window = window[..., :1, :]
            step = step[..., :1, :] if isinstance(step, torch.Tensor) and step.ndim == window.ndim else step
        value, raw_scale, best, curvature = self.heads(window, step)
        return torch.cat([value, raw_scale, best, curvature.expand_as(best)], -1)

    def from_action_free(self, free: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(μ, raw scale) per reward term at ``action`` from ``action_free``'s output; reads no parameter."""
        K, n = self.reward_terms, self._actor[0].system.state_dim
        value, raw_scale, best, curvature = free.split([K, K, n, n], -1)
        mid, half = self._actor[0].squash_affine()
        a = (action - mid) / half
        penalty = curvature * (a - best).pow(2)
        if self.reward_terms == 1:
            penalty = penalty.sum(-1, keepdim=True)
        mean = value - penalty
        if self.scale == "reward":
            spread = nn.functional.softplus(raw_scale)
            sigma = (spread.pow(2) + 8**0.5 * spread * (curvature * (a - best).pow(2)).detach()).sqrt()
            raw_scale = sigma + torch.log(-torch.expm1(-sigma))  # softplus⁻¹: the loss reads σ = softplus(raw)
        return torch.stack([mean, raw_scale.expand_as(mean)], -1).flatten(-2)

    def heads(self, window: torch.Tensor, step=None) -> tuple[torch.Tensor, ...]:
        """A quadratic form's (V, raw scale, best action m, curvature p) per window, m in [−1, 1] action units."""
        if self.form == "mlp":
            raise ValueError("an MLP critic of (h, a) has no separate value, best action or curvature")
        h = self._actor[0].policy.features(window, step)
        K, n = self.reward_terms, self._actor[0].system.state_dim
        if self.form == "quadratic":
            value, raw_scale, best, curvature = self.mlp(h).split([K, K, n, n], -1)
            return value, raw_scale, best, nn.functional.softplus(curvature)
        value, raw_scale, best = self.mlp(h).split([K, K, n], -1)
        return value, raw_scale, best, self.reward_curvature(step)

    def reward_curvature(self, step=None) -> torch.Tensor:
        """p_t = W_t ⊙ w_t², the reward's curvature in the critic's action units (``reward_quadratic``)."""
        actor = self._actor[0]
        width = actor.squash_affine()[1]
        if actor.acts_by_update:
            width = width * actor.bound_at(step)
        weights = self.reward_weights if self.reward_weights.ndim == 1 else schedule_row(self.reward_weights, step)
        return weights * width.pow(2)


def make_critic(
    actor: LearnedFilter,
    num_cells: int = 256,
    depth: int = 3,
    reward_terms: int = 1,
    form: str = "mlp",
    reward_weights: torch.Tensor | None = None,
    scale: str = "window",
) -> TensorDictModule:
    """Critic reading (h_t^N, t where the actor reads it, the action key), writing ``state_action_value`` [.., 2K]."""
    net = FilterCritic(actor, num_cells, depth, reward_terms, form, reward_weights, scale)
    in_keys = dict(zip(["window", "step"], actor.policy_in_keys)) | {"action": actor.action_key}
    net.input_keys = in_keys  # argument -> tensordict key, for a loss that calls action_free itself
    return TensorDictModule(net, in_keys=in_keys, out_keys=["state_action_value"])
