"""Factories for the Pendulum check of DSAC-T (and TorchRL's SACLoss on the same networks)."""

from __future__ import annotations

import torch
from daof.losses import DSACTLoss
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, DoubleToFloat, EnvBase, GymEnv, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators

ACTIVATIONS = {"gelu": nn.GELU, "relu": nn.ReLU, "tanh": nn.Tanh}


# ---------------------------------------------------------------------------- environment
def make_env(cfg: DictConfig, seed: int) -> EnvBase:
    """Pendulum-v1 (200-step episodes, which end truncated, never terminated)."""
    env = TransformedEnv(
        GymEnv(cfg.env.name, device="cpu"),
        Compose(DoubleToFloat(), StepCounter(), RewardSum()),
    )
    env.set_seed(seed)
    return env


def make_collector(cfg: DictConfig, env: EnvBase, policy: nn.Module) -> Collector:
    """Random actions for ``init_random_frames``, then the stochastic policy."""
    return Collector(
        env,
        policy,
        frames_per_batch=cfg.collector.frames_per_batch,
        total_frames=cfg.collector.total_frames,
        init_random_frames=cfg.collector.init_random_frames,
        device="cpu",
    )


def make_replay_buffer(cfg: DictConfig) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(cfg.replay_buffer.size),
        batch_size=cfg.replay_buffer.batch_size,
    )


# ---------------------------------------------------------------------------- networks
class GaussianHead(nn.Module):
    """Split the actor output into loc and σ_π = exp(clamp(log_std, −20, 0.5)) (spec, Networks)."""

    def __init__(self, log_std_min: float = -20.0, log_std_max: float = 0.5):
        super().__init__()
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = x.chunk(2, -1)
        return loc, log_std.clamp(self.log_std_min, self.log_std_max).exp()


def _mlp(cfg: DictConfig, out_features: int) -> MLP:
    return MLP(
        out_features=out_features,
        num_cells=list(cfg.network.hidden_sizes),
        activation_class=ACTIVATIONS[cfg.network.activation],
    )


def make_actor(cfg: DictConfig, env: EnvBase) -> ProbabilisticActor:
    """Tanh-Gaussian actor, a = (hi−lo)/2·tanh(u) + (hi+lo)/2; deterministic action = squashed loc."""
    action_spec = env.action_spec_unbatched
    net = nn.Sequential(_mlp(cfg, 2 * action_spec.shape[-1]), GaussianHead())
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False},
        return_log_prob=False,
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_critic(cfg: DictConfig, out_features: int) -> TensorDictModule:
    """Q(s, a): 2 outputs (μ, raw scale) for DSAC-T, 1 for SAC; MLP concatenates its inputs."""
    return TensorDictModule(_mlp(cfg, out_features), in_keys=["observation", "action"], out_keys=["state_action_value"])


# ---------------------------------------------------------------------------- losses, optimisers
def make_loss(cfg: DictConfig, env: EnvBase):
    """DSACTLoss or TorchRL's SACLoss on the same actor and critic bodies; returns (loss, updater, actor)."""
    actor = make_actor(cfg, env)
    out_features = 2 if cfg.loss.name == "dsac_t" else 1
    critic = make_critic(cfg, out_features)
    with set_exploration_type(ExplorationType.RANDOM):
        td = env.fake_tensordict()
        actor(td)
        critic(td)
    if cfg.loss.name == "dsac_t":
        loss = DSACTLoss(actor, critic, **cfg.dsac_t.loss)
    elif cfg.loss.name == "sac":
        loss = SACLoss(actor, critic, **cfg.sac.loss)
    else:
        raise ValueError(f"unknown loss {cfg.loss.name!r}: use dsac_t or sac")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.loss.gamma)
    updater = SoftUpdate(loss, tau=cfg.loss.tau)
    return loss, updater, actor


def make_optimizers(cfg: DictConfig, loss) -> dict[str, torch.optim.Optimizer]:
    """One Adam per group (critic, actor, α) so the actor and α can step on a delay."""
    lrs = cfg[cfg.loss.name].optim
    return {
        "critic": torch.optim.Adam(loss.qvalue_network_params.values(True, True), lr=lrs.lr_critic),
        "actor": torch.optim.Adam(loss.actor_network_params.values(True, True), lr=lrs.lr_actor),
        "alpha": torch.optim.Adam([loss.log_alpha], lr=lrs.lr_alpha),
    }


# ---------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate(env: EnvBase, actor: nn.Module, episodes: int, max_steps: int) -> float:
    """Mean undiscounted return of ``episodes`` deterministic episodes (squashed loc)."""
    returns = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(max_steps, actor, break_when_any_done=True)
            returns.append(rollout["next", "reward"].sum().item())
    return sum(returns) / len(returns)
