"""DSAC-T: distributional soft actor-critic with the three refinements, as a TorchRL loss.

Follows DSAC-T as ``docs/design.md`` states it (the GOPS ``dsact.py`` form of the algorithm) and the structure of
TorchRL's ``SACLoss``/``TQCLoss``: functional actor and critics with target copies, ``vmap`` over
the critic ensemble, a TD(0) value estimator for the targets y_q and y_z, and keys set through
``_AcceptedKeys``/``set_keys``. The critic outputs (μ, raw scale) on its last dim, σ = softplus(raw).

With ``reward_components=K > 1`` the reward is a vector whose sum is the task's reward, and each
critic outputs K (μ, raw) pairs: one value distribution per reward term (a decomposed critic,
van Seijen et al., NeurIPS 2017). Q = Σ_k Q_k holds for any γ, since the Bellman equation is
linear in the reward; the entropy bonus is split evenly over the K terms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data.tensor_specs import Composite, TensorSpec
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.common import LossModule
from torchrl.objectives.sac import compute_rsample_log_prob
from torchrl.objectives.utils import (
    ValueEstimators,
    _cache_values,
    _vmap_func,
    dispatch_value_estimator,
)


def critic_surrogate(
    mu: Tensor,
    sigma: Tensor,
    y_q: Tensor,
    y_b: Tensor,
    sigma_bar: Tensor,
    epsilon: float,
) -> Tensor:
    """The DSAC-T critic surrogate L_i (spec, step 5), averaged over the batch (last dim).

    Its gradient is the Gaussian NLL gradient with y_q in the mean term and the clipped sample
    y_b in the std term, both scaled by (σ̄² + ε):
    ∂L/∂μ = −(σ̄²+ε)(y_q − μ̂)/(σ̂²+ε),  ∂L/∂σ = −(σ̄²+ε)((μ̂ − y_b)² − σ̂²)/(σ̂³+ε)  (per sample / B).
    Only ``mu`` and ``sigma`` carry gradient; ``sigma_bar`` has the leading dims (all but the batch).
    """
    mu_hat, sigma_hat = mu.detach(), sigma.detach()
    grad_mu = -(y_q - mu_hat) / (sigma_hat.pow(2) + epsilon)
    grad_sigma = -((mu_hat - y_b).pow(2) - sigma_hat.pow(2)) / (sigma_hat.pow(3) + epsilon)
    return (sigma_bar.pow(2) + epsilon) * (grad_mu * mu + grad_sigma * sigma).mean(-1)


def clip_sampled_target(y_z: Tensor, mu: Tensor, sigma_bar: Tensor, xi: float) -> Tensor:
    """y_b = μ̂ + clamp(y_z − μ̂, −ξσ̄, ξσ̄): the sampled target clipped around the online mean."""
    mu_hat = mu.detach()
    bound = xi * sigma_bar
    return mu_hat + torch.maximum(torch.minimum(y_z - mu_hat, bound), -bound)


class DSACTLoss(LossModule):
    """DSAC-T loss (Duan et al., arXiv 2310.05858) over a Gaussian value distribution.

    Args:
        actor_network: stochastic actor; its distribution (``get_dist``) is sampled for the
            action written under ``tensor_keys.action`` (e.g. ``"correction"`` for DAOF-v1).
        qvalue_network: critic reading the observation keys and ``tensor_keys.action``, writing
            ``state_action_value`` with last dim 2K: K pairs (μ_k, raw_k), σ_k = softplus(raw_k).
            One module: TorchRL expands it to ``num_qvalue_nets`` copies and re-samples each
            parameter tensor of the copies uniformly in [min, max] of the module's, which
            undoes any structured init (zeroed rows or columns). A list of ``num_qvalue_nets``
            modules of one architecture: each critic keeps its own init.

    Keyword Args:
        num_qvalue_nets: critics in the ensemble (2 in DSAC-T).
        action_spec: used for ``target_entropy="auto"`` (−dim A); the actor's spec otherwise.
        target_entropy: "auto" or a float.
        alpha_init: α₀ (e in DSAC-T: log_alpha starts at 1).
        xi: clip size ξ of y_z around μ̂, in units of σ̄.
        epsilon: ε in the surrogate's denominators and its (σ̄² + ε) scale.
        tau_b: rate of the moving average σ̄.
        sample_clip: the N(0, 1) draw for z′ is clamped to ±sample_clip before scaling by σ′.
        reward_components: K, the length of the reward vector under ``tensor_keys.reward``
            (1: the scalar reward of DSAC-T; K > 1: one value distribution per reward term).
        delay_actor, delay_qvalue: keep target copies of actor / critics (update them with
            :class:`~torchrl.objectives.SoftUpdate`).

    The discount lives in the value estimator: ``make_value_estimator(ValueEstimators.TD0, gamma=…)``.
    Targets bootstrap on ``terminated`` only, so a truncated transition still bootstraps.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (defaults as in ``SACLoss``)."""

        action: NestedKey = "action"
        value: NestedKey = "state_value"
        state_action_value: NestedKey = "state_action_value"
        log_prob: NestedKey = "action_log_prob"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)

    actor_network: TensorDictModule
    qvalue_network: TensorDictModule
    actor_network_params: TensorDictParams
    qvalue_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        qvalue_network: TensorDictModule | list[TensorDictModule],
        *,
        num_qvalue_nets: int = 2,
        action_spec: TensorSpec | None = None,
        target_entropy: str | float = "auto",
        alpha_init: float = math.e,
        xi: float = 3.0,
        epsilon: float = 0.1,
        tau_b: float = 0.005,
        sample_clip: float = 3.0,
        reward_components: int = 1,
        actor_samples: int = 1,
        delay_actor: bool = True,
        delay_qvalue: bool = True,
    ) -> None:
        self._in_keys = None
        self._out_keys = None
        super().__init__()
        self.delay_actor = delay_actor
        self.delay_qvalue = delay_qvalue
        self.num_qvalue_nets = num_qvalue_nets
        self.convert_to_functional(actor_network, "actor_network", create_target_params=delay_actor)
        if isinstance(qvalue_network, (list, tuple)) and len(qvalue_network) != num_qvalue_nets:
            raise ValueError(f"got {len(qvalue_network)} critics for num_qvalue_nets={num_qvalue_nets}")
        self.convert_to_functional(qvalue_network, "qvalue_network", num_qvalue_nets, create_target_params=delay_qvalue)
        self.xi, self.epsilon, self.tau_b, self.sample_clip = xi, epsilon, tau_b, sample_clip
        if int(actor_samples) < 1:
            raise ValueError(f"actor_samples must be >= 1, got {actor_samples}")
        self.actor_samples = int(actor_samples)
        if int(reward_components) < 1:
            raise ValueError(f"reward_components must be >= 1, got {reward_components}")
        self.reward_components = int(reward_components)
        device = next(iter(self.actor_network_params.values(True, True))).device
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(alpha_init), device=device))
        # σ̄_ik, one per critic and reward term, and whether it has been set from a first batch:
        # buffers, so they are checkpointed with the loss.
        self.register_buffer("sigma_bar", torch.zeros(num_qvalue_nets, self.reward_components, device=device))
        self.register_buffer("sigma_bar_initialised", torch.zeros((), dtype=torch.bool, device=device))
        self._target_entropy_arg = target_entropy
        self._action_spec = action_spec
        self._target_entropy = None
        self._make_vmap()
        # Like SACLoss: default the action / log-prob keys to what the actor samples.
        sample_keys = getattr(self.actor_network, "dist_sample_keys", [])
        log_prob_keys = getattr(self.actor_network, "log_prob_keys", [])
        if len(sample_keys) == 1:
            self.set_keys(action=sample_keys[0])
        if len(log_prob_keys) == 1:
            self.set_keys(log_prob=log_prob_keys[0])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "sigma_bar"
        if key in state_dict and state_dict[key].ndim == 1:  # saved before σ̄ had a reward-term dim
            state_dict[key] = state_dict[key].unsqueeze(-1)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _make_vmap(self):
        """The critic ensemble in one call: the input is shared, the parameters stacked on dim 0.

        A critic whose module ``splits_action`` (its output is ``from_action_free(action_free(...), a)``,
        with the first part reading no action and the second no parameter) is called in those two
        parts, so ``forward`` computes the action-free part once and the actor loss reuses it.
        """
        self._vmap_qnetworkN0 = _vmap_func(self.qvalue_network, (None, 0), randomness=self.vmap_randomness)
        module = getattr(self.qvalue_network, "module", None)
        self._critic_split = getattr(module, "splits_action", False) and hasattr(module, "input_keys")
        if self._critic_split:
            self._vmap_action_free = _vmap_func(
                self.qvalue_network, (None, None, 0), func="action_free", randomness=self.vmap_randomness
            )

    # ------------------------------------------------------------------ keys and estimators
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=self.tensor_keys.value,
                reward=self.tensor_keys.reward,
                done=self.tensor_keys.done,
                terminated=self.tensor_keys.terminated,
            )
        self._target_entropy = None  # the action key may have changed
        self._set_in_keys()

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        value_type, hp = self._prepare_value_estimator_kwargs(value_type, **hyperparams)
        if value_type is None:
            return self
        dispatch_value_estimator(
            self,
            value_type,
            supported=self.SUPPORTED_VALUE_ESTIMATORS,
            tensor_keys={
                "value_target": "value_target",
                "value": self.tensor_keys.value,
                "reward": self.tensor_keys.reward,
                "done": self.tensor_keys.done,
                "terminated": self.tensor_keys.terminated,
            },
            value_network=None,
            **hp,
        )
        # read once here: a float() of the (possibly CUDA) γ on every update would synchronise
        self._zero_discount = float(self.value_estimator.gamma) == 0.0
        return self

    def _set_in_keys(self):
        keys = [
            self.tensor_keys.action,
            ("next", self.tensor_keys.reward),
            ("next", self.tensor_keys.done),
            ("next", self.tensor_keys.terminated),
            *self.actor_network.in_keys,
            *[("next", key) for key in self.actor_network.in_keys],
            *self.qvalue_network.in_keys,
        ]
        self._in_keys = list(dict.fromkeys(keys))

    @property
    def in_keys(self):
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self):
        if self._out_keys is None:
            self._out_keys = [
                "loss_qvalue",
                "loss_actor",
                "loss_alpha",
                "alpha",
                "entropy",
                "q_mean",
                "q_std",
                "sigma_bar",
                "td_error_abs",
                "nll",
            ]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    @property
    def target_entropy(self) -> float:
        """−dim(A) for "auto", from ``action_spec`` or the actor's spec at ``tensor_keys.action``."""
        if self._target_entropy is None:
            if self._target_entropy_arg != "auto":
                self._target_entropy = float(self._target_entropy_arg)
            else:
                spec = self._action_spec
                if spec is None:
                    spec = getattr(self.actor_network, "spec", None)
                if spec is None:
                    raise RuntimeError("target_entropy='auto' needs an action_spec or an actor spec.")
                if isinstance(spec, Composite):
                    spec = spec[self.tensor_keys.action]
                self._target_entropy = -float(spec.shape[-1:].numel())
        return self._target_entropy

    @property
    def _alpha(self) -> Tensor:
        with torch.no_grad():
            return self.log_alpha.exp()

    @property
    @_cache_values
    def _cached_detached_qvalue_params(self):
        return self.qvalue_network_params.detach()

    # ------------------------------------------------------------------ pieces
    def _critic_mu_sigma(self, tensordict: TensorDictBase, params) -> tuple[Tensor, Tensor]:
        """All critics at once: μ, σ of shape [num_qvalue_nets, *batch, K]."""
        return self._critics(tensordict, params)[:2]

    def _critics(self, tensordict: TensorDictBase, params, free: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """μ, σ and, for a critic that splits off its action, its action-free part ([E, *batch, ·]; else None).

        ``free``: that part, already computed (the actor loss's reuse of the critic loss's).
        """
        if self._critic_split:
            module = self.qvalue_network.module
            keys = module.input_keys
            step = tensordict.get(keys["step"]) if "step" in keys else None
            if free is None:
                free = self._vmap_action_free(tensordict.get(keys["window"]), step, params)
            out = module.from_action_free(free, tensordict.get(keys["action"]))
        else:
            td = tensordict.select(*self.qvalue_network.in_keys, strict=False)
            out = self._vmap_qnetworkN0(td, params).get(self.tensor_keys.state_action_value)
        K = self.reward_components
        if out.shape[-1] != 2 * K:
            raise ValueError(f"the critic must output 2·reward_components = {2 * K} values, got {out.shape[-1]}")
        out = out.unflatten(-1, (K, 2))
        return out[..., 0], F.softplus(out[..., 1]), free

    def _sample_actor(self, tensordict: TensorDictBase, params, samples: int = 1) -> tuple[Tensor, Tensor]:
        """ã ~ π(·|s) and log π(ã|s); ``samples`` > 1 draws that many per state (dim 0)."""
        with (
            set_exploration_type(ExplorationType.RANDOM),
            params.to_module(self.actor_network, preserve_module_state=False),
        ):
            dist = self.actor_network.get_dist(tensordict)
            if samples == 1:
                return compute_rsample_log_prob(dist)
            action = dist.rsample((samples,))
            return action, dist.log_prob(action)

    def compute_targets(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """y_q and y_z (spec, step 1), each of shape ``[*batch, K]``, without gradient.

        a′, log π′ come from the target actor; μ′ is the min over target critics of μ′_j and z′ is
        the sample μ′_j + clamp(N(0,1), ±sample_clip)·σ′_j of that same (argmin-mean) critic, per
        reward term. With γ = 0 both targets are the reward, and nothing is sampled or evaluated.
        """
        reward = self._reward(tensordict)
        estimator = self.value_estimator  # built on first use, which sets ``_zero_discount``
        if self._zero_discount:
            reward = reward.reshape(*tensordict.batch_size, -1).expand(*tensordict.batch_size, self.reward_components)
            return reward, reward.clone()
        steps_key = estimator.tensor_keys.steps_to_next_obs
        target_td = tensordict.select("next", steps_key, strict=False).copy()
        with torch.no_grad():
            next_td = target_td.get("next").copy()
            next_action, next_log_prob = self._sample_actor(next_td, self.target_actor_network_params)
            next_td.set(self.tensor_keys.action, next_action)
            mu_n, sigma_n = self._critic_mu_sigma(next_td, self.target_qvalue_network_params)
            noise = torch.randn_like(mu_n).clamp(-self.sample_clip, self.sample_clip)
            z_n = mu_n + noise * sigma_n
            idx = mu_n.argmin(0, keepdim=True)
            mu_next = mu_n.gather(0, idx).squeeze(0)
            z_next = z_n.gather(0, idx).squeeze(0)
            soft = self._alpha * next_log_prob.reshape(*mu_next.shape[:-1], 1) / self.reward_components
            # Both targets in one TD(0) call: last dim (y_q, y_z); reward/terminated broadcast.
            next_value = torch.stack([mu_next - soft, z_next - soft], -1)
            for key in (self.tensor_keys.reward, self.tensor_keys.terminated, self.tensor_keys.done):
                nested = ("next", *key) if isinstance(key, tuple) else ("next", key)
                value = target_td.get(nested)
                while value.ndim < next_value.ndim:
                    value = value.unsqueeze(-1)
                target_td.set(nested, value.expand_as(next_value))
            steps = target_td.get(steps_key, None)
            if steps is not None:
                while steps.ndim < next_value.ndim:
                    steps = steps.unsqueeze(-1)
                target_td.set(steps_key, steps.expand_as(next_value))
            targets = estimator.value_estimate(target_td, next_value=next_value)
        return targets[..., 0], targets[..., 1]

    def _reward(self, tensordict: TensorDictBase) -> Tensor:
        """The next reward, checked to have ``reward_components`` terms on its last dim when K > 1."""
        reward = tensordict.get(("next", self.tensor_keys.reward))
        if self.reward_components > 1 and reward.shape[-1] != self.reward_components:
            raise ValueError(
                f"reward {self.tensor_keys.reward!r} has {reward.shape[-1]} terms, the loss expects "
                f"reward_components={self.reward_components}"
            )
        return reward

    @torch.no_grad()
    def _update_sigma_bar(self, sigma: Tensor) -> Tensor:
        """σ̄_i ← (1−τ_b)σ̄_i + τ_b·mean(σ_i) in training mode (first batch: σ̄_i = mean(σ_i)), per reward term."""
        batch_mean = sigma.detach().reshape(sigma.shape[0], -1, sigma.shape[-1]).mean(1)
        if not self.training:
            return self.sigma_bar.clone() if self.sigma_bar_initialised else batch_mean
        if self.sigma_bar_initialised:
            self.sigma_bar.lerp_(batch_mean, self.tau_b)
        else:
            self.sigma_bar.copy_(batch_mean)
            self.sigma_bar_initialised.fill_(True)
        return self.sigma_bar.clone()

    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Critic loss Σ_i L_i (spec, steps 1–5) and its diagnostics; updates σ̄ first."""
        y_q, y_z = self.compute_targets(tensordict)
        mu, sigma, free = self._critics(tensordict, self.qvalue_network_params)
        sigma_bar = self._update_sigma_bar(sigma)  # [E, K]
        sb = sigma_bar.reshape(sigma_bar.shape[0], *[1] * (mu.ndim - 2), sigma_bar.shape[1])
        y_b = clip_sampled_target(y_z, mu, sb, self.xi)

        def per_term(x: Tensor) -> Tensor:  # [E, *batch, K] -> [E, K, batch]
            return x.movedim(-1, 1).flatten(2)

        flat = (per_term(mu), per_term(sigma), per_term(y_q.expand_as(mu)), per_term(y_b))
        loss = critic_surrogate(*flat, sigma_bar, self.epsilon).sum()
        with torch.no_grad():
            err = y_q - mu
            nll = 0.5 * math.log(2 * math.pi) + sigma.log() + err.pow(2) / (2 * sigma.pow(2))
            metadata = {
                "td_error": err.abs().sum(-1).max(0)[0],
                "q_mean": mu.sum(-1).mean(),
                "q_std": sigma.mean(),
                "sigma_bar": sigma_bar,
                "td_error_abs": err.abs().sum(-1).mean(),
                "nll": nll.mean(),
            }
        if free is not None:  # the critics' action-free part, for the actor loss on the same batch
            metadata["action_free"] = free
        return loss, metadata

    def actor_loss(
        self, tensordict: TensorDictBase, action_free: Tensor | None = None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """L_π = mean[α log π(ã|s) − Σ_k min_i μ_ik(s, ã)] with the critics' parameters detached.

        The mean is over the batch and, with ``actor_samples`` = M > 1, over M actions drawn per
        state: the same objective with 1/M of its sampling variance. The noise of one draw scales
        with the policy's spread, which can far exceed the error the actor is learning to remove.
        The critics see each state's input expanded (a view) beside its M actions.
        ``action_free``: the critic loss's action-free part on the same batch and critic weights
        (``qvalue_loss``'s metadata), reused detached instead of evaluated again: the same values.
        """
        M = self.actor_samples
        action, log_prob = self._sample_actor(tensordict, self.actor_network_params, M)
        td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        if M > 1:  # samples on a last batch dim: [*B, M]
            td_q = td_q.unsqueeze(-1).expand(*td_q.batch_size, M)
            action, log_prob = action.movedim(0, -2), log_prob.movedim(0, -1)
        td_q.set(self.tensor_keys.action, action)
        if action_free is not None:  # the critic loss's, on this batch and these critic weights: detached
            action_free = action_free.detach()
            action_free = action_free.unsqueeze(-2) if M > 1 else action_free
        mu = self._critics(td_q, self._cached_detached_qvalue_params, action_free)[0]
        min_mu = mu.min(0)[0].sum(-1)
        log_prob = log_prob.reshape(min_mu.shape)
        loss = (self._alpha * log_prob - min_mu).mean()
        return loss, {"log_prob": log_prob.detach()}

    def alpha_loss(self, log_prob: Tensor) -> Tensor:
        """L_α = −log_alpha · mean(log π + target_entropy), log π detached."""
        return -self.log_alpha * (log_prob.detach() + self.target_entropy).mean()

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loss_qvalue, meta_q = self.qvalue_loss(tensordict)
        loss_actor, meta_actor = self.actor_loss(tensordict, meta_q.pop("action_free", None))
        loss_alpha = self.alpha_loss(meta_actor["log_prob"])
        tensordict.set(self.tensor_keys.priority, meta_q.pop("td_error"))
        return TensorDict(
            {
                "loss_qvalue": loss_qvalue,
                "loss_actor": loss_actor,
                "loss_alpha": loss_alpha,
                "alpha": self._alpha,
                "entropy": -meta_actor["log_prob"].mean(),
                **meta_q,
            },
            batch_size=[],
        )
