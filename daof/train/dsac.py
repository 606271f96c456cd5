"""Train a DAOF filter (v1 or v2) with DSAC-T on any registered system.

The loop of TorchRL's sota-implementations: a ``Collector`` over the batched filtering env runs
the stochastic actor, a ``TensorDictReplayBuffer`` stores transitions, and every collected batch
is followed by gradient updates on DSAC-T's schedule (critics every update; actor, α and the
Polyak-averaged targets every ``delay``-th). A fixed validation set (seeds disjoint from any
evaluation seed) is filtered deterministically every ``validation.every_frames`` frames; the best
validation checkpoint is kept as the filter's result (early stopping on validation data).

Checkpoints (``checkpoint.pt``) hold every piece of training state: actor, critics and their
targets, α, σ̄, optimisers, counters, the global RNG states and the env's generator, the replay
buffer (included, not rebuilt), the validation history and the logger state. They are written at
batch boundaries, with the episodes in flight (the env's simulator state, the window and the
collector's carried step), so a resumed run continues those episodes and is the uninterrupted run
bit for bit (``tests/test_resume_continuity.py``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl._utils import timeit
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from daof.envs.filtering_env import FEEDBACK_KEY, FilteringEnv, default_reward_weights
from daof.envs.history import FRAME_KEY, with_window
from daof.envs.recorded import find_recorded
from daof.filters.learned import DAOFv1
from daof.losses import DSACTLoss, ForeachSoftUpdate
from daof.train.base import FilterTrainer
from daof.train.baseline import BASELINES, ZeroActionBaseline
from daof.train.checkpoint import restore_rng
from daof.train.networks import WINDOW_INITS, make_critic, start_on_newest_frame
from daof.train.policies import exploration_policy, stochastic_actor
from daof.train.schedules import reward_weight_schedule, ukf_schedule

__all__ = ["DSACTTrainer"]

#: keys the replay buffer does not need (the per-step frame is inside the window already)
_DROP_KEYS = [FRAME_KEY, ("next", FRAME_KEY), "loc", "scale", "reward_per_state", FEEDBACK_KEY]
#: largest exploration std of the automatic entropy target, in units of the action's half-range
MAX_EXPLORATION_STD = 0.3
_LOGGED = ("loss_qvalue", "loss_actor", "alpha", "entropy", "td_error_abs", "nll")


class DSACTTrainer(FilterTrainer):
    """Owns every piece of one DSAC-T training run; ``train()`` runs (or resumes) it."""

    kinds = ("DAOF-v1", "DAOF-v2")

    def __init__(self, cfg: DictConfig):
        super().__init__(cfg)
        self._make_schedules()
        self.system.to(self.device)  # after the schedules: their UKF run simulates on the CPU
        if isinstance(self.filter, DAOFv1):  # its update is K̄_t ν_t + a residual that starts at 0
            self._start_at_the_reference()
            self.starts_as_a_filter = True
        self._init_window(self.filter.policy.mlp)
        self._make_loss()
        self._make_data()
        self.feedback()  # refuse an impossible collector.feedback before any work
        self.collector: Collector | None = None  # while ``train`` runs
        self._resume: dict | None = None  # what a resumed run restores once its collector exists
        self.deployed_weights()  # and an unknown validation.actor

    # ----------------------------------------------------------------- factories
    def _make_schedules(self) -> None:
        """DAOF-v1's update bound and input scale, and the reward weights, per start-up step.

        All come from one UKF run (``daof.train.schedules``), so they need a model;
        ``reward.weights=constant`` switches the weights off. Deterministic in ``seeds.normalizer``,
        so a resumed run rebuilds the same.
        """
        cfg = self.cfg
        self.reward_weights = None
        mode = cfg.reward.weights
        if not self.system.has_model or not (self.filter.config.kind == "DAOF-v1" or mode != "constant"):
            return
        schedule = ukf_schedule(self.system, seed=int(cfg.seeds.normalizer) + 1)
        self.filter.set_schedules(schedule)
        if mode != "constant":
            self.reward_weights = reward_weight_schedule(self.system, schedule["estimate"])

    def _make_loss(self) -> None:
        cfg = self.cfg
        per_state = bool(cfg.loss.critic_per_state)
        # a critic per state: the reward is a sum of per-state terms, each learned on its own
        terms = self.system.state_dim if per_state else 1
        form = str(cfg.network.critic_form)
        # "own": each of the two critics keeps its own init (the quadratic critic's m(h) = 0, the
        # window init); "resampled": one critic that TorchRL copies and re-samples (the runs before 115f8b2)
        init = str(cfg.network.critic_init)
        if init not in ("own", "resampled"):
            raise ValueError(f"network.critic_init must be 'own' or 'resampled', got {init!r}")
        weights = None
        if form == "reward_quadratic":  # the reward's curvature in the action is known only at γ = 0
            if float(cfg.loss.gamma) != 0.0:
                raise ValueError("network.critic_form=reward_quadratic is exact only with loss.gamma=0")
            weights = self.reward_weights if self.reward_weights is not None else default_reward_weights(self.system)
        scale = str(cfg.network.critic_scale)
        critics = [
            make_critic(self.filter, int(cfg.network.num_cells), int(cfg.network.depth), terms, form, weights, scale)
            for _ in range(2 if init == "own" else 1)
        ]
        for critic in critics:  # initialised on the CPU, then moved: the same initial critics on every device
            self._init_window(critic.module.mlp)
            critic.to(self.device)
        self.critic = critics[0]
        self.loss = DSACTLoss(
            stochastic_actor(self.filter),
            critics if len(critics) > 1 else self.critic,
            num_qvalue_nets=2,
            target_entropy=self.target_entropy(),
            alpha_init=float(cfg.loss.alpha_init),
            epsilon=float(cfg.loss.epsilon),
            reward_components=terms,
            actor_samples=int(cfg.loss.actor_samples),
        )
        self.loss.set_keys(action=self.filter.action_key)
        if per_state:
            self.loss.set_keys(reward="reward_per_state")
        self.loss.make_value_estimator(gamma=float(cfg.loss.gamma))
        self.target_updater = ForeachSoftUpdate(self.loss, tau=float(cfg.loss.tau))  # SoftUpdate's numbers, faster
        o = cfg.optim
        self.optim_critic = torch.optim.Adam(
            list(self.loss.qvalue_network_params.flatten_keys().values()), lr=float(o.lr_critic)
        )
        self.optim_actor = torch.optim.Adam(
            list(self.loss.actor_network_params.flatten_keys().values()), lr=float(o.lr_actor)
        )
        self.optim_alpha = torch.optim.Adam([self.loss.log_alpha], lr=float(o.lr_alpha))

    def _init_window(self, mlp: torch.nn.Sequential) -> None:
        """``network.window_init=newest``: the network starts on the window's newest frame alone."""
        init = str(self.cfg.network.window_init)
        if init not in WINDOW_INITS:
            raise ValueError(f"network.window_init must be one of {WINDOW_INITS}, got {init!r}")
        if init == "newest":
            start_on_newest_frame(mlp, (self.filter.config.window - 1) * self.filter.frame_dim)

    def _start_at_the_reference(self) -> None:
        """A residual policy starts at zero: the deterministic filter is the reference-gain update itself.

        The actor's last layer is zeroed (loc = 0, so tanh(loc) = 0) and its log-std bias set to the
        exploration std of the entropy target, so training starts from the filter that the update
        of a UKF's mean gain gives (the Kalman filter on ``linear``; docs/linear_check.md) and
        explores around it, instead of from a random update.
        """
        n = self.system.state_dim
        if self.cfg.loss.target_entropy == "auto":
            std = self.exploration_std()
        else:  # the same std on every state, with the fixed target's entropy
            std = torch.full((n,), math.exp(self.target_entropy() / n) / math.sqrt(2 * math.pi * math.e))
        last = [m for m in self.filter.policy.mlp if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias[:n].zero_()
            last.bias[n:].copy_(std.log())

    def exploration_std(self) -> torch.Tensor:
        """Per state, the std of the entropy target's exploration noise in action units (``target_entropy``)."""
        width = self.filter.high - self.filter.low
        k = float(self.cfg.loss.exploration_std)
        if k <= 0:
            raise ValueError(f"loss.exploration_std must be > 0, got {k}")
        return torch.minimum(k * self.filter.error_scale / self.filter.action_scale, MAX_EXPLORATION_STD * width / 2)

    def target_entropy(self) -> float:
        """Entropy of exploration noise of ``loss.exploration_std`` error scales per state.

        DSAC-T's −dim(A) presumes actions in [−1, 1]; an estimate's units and range are the
        system's, and what matters for filtering is the noise relative to the achievable error.
        The target is the entropy of a Gaussian with std k · ``system.error_scale`` per state
        (the tanh barely bends at the small corrections a trained filter makes):
        Σ_i log(√(2πe) · k · e_i / a_i), with a the state-unit size of one unit of action
        (``LearnedFilter.action_scale``: DAOF-v1 acts in units of its settled update bound).
        Each std is capped at ``MAX_EXPLORATION_STD`` times the action's half-range: an action in
        [low, high] has entropy below Σ log(high − low), and an unreachable target drives α up
        without bound until the entropy term drowns the critic (found with DAOF-v2's increment form on
        veh14dof, a form removed on 2026-12-07: docs/log/2026-12-02-veh14dof-entropy-target-cap.md).
        ``loss.target_entropy`` set to a number overrides it (it must be below that bound).
        """
        width = self.filter.high - self.filter.low  # the actor's action range (2 for an update in [−1, 1])
        fixed = self.cfg.loss.target_entropy
        if fixed != "auto":
            most = float(width.log().sum())
            if float(fixed) >= most:
                raise ValueError(
                    f"loss.target_entropy={fixed} is unreachable: actions in this range have entropy < {most:.3g}"
                )
            return float(fixed)
        return float((self.exploration_std() * math.sqrt(2 * math.pi * math.e)).log().sum())

    def _make_data(self) -> None:
        cfg = self.cfg
        c = cfg.collector
        env = FilteringEnv(
            self.system,
            int(c.env_batch),
            int(c.episode_steps),
            self.reward_weights,
            seed=int(cfg.seeds.train),
            device=self.device,
        )
        self.base_env = env
        baseline = str(cfg.reward.baseline)
        if baseline not in BASELINES:
            raise ValueError(f"reward.baseline must be one of {BASELINES}, got {baseline!r}")
        if baseline != "none" and float(cfg.loss.gamma) != 0.0:
            raise ValueError("reward.baseline keeps the actor's objective only with loss.gamma=0")
        self.baseline = ZeroActionBaseline(self.filter, env.reward_weights) if baseline != "none" else None
        self.env = with_window(env, self.filter.layout)
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(int(cfg.buffer.size), device=self.device),
            batch_size=int(cfg.optim.batch_size),
        )

    def feedback(self) -> str:
        """``collector.feedback``: what the env feeds back into h_{t+1}, the sampled action or the mean.

        "mean" feeds back the deterministic estimate, as the deployed filter does, so the windows the
        networks learn on hold no exploration noise; the noise stays in the action the reward
        scores. It changes which h the data visit, not the value of an action, only at γ = 0
        (with γ > 0 an action's value includes its effect on the next window), so γ > 0 is refused.
        """
        mode = str(self.cfg.collector.feedback)
        if mode == "mean" and float(self.cfg.loss.gamma) != 0.0:
            raise ValueError("collector.feedback=mean keeps each action's value only with loss.gamma=0")
        return mode

    def _make_collector(self, remaining: int) -> Collector:
        c = self.cfg.collector
        frames_per_batch = int(c.env_batch) * int(c.steps_per_batch)
        return Collector(
            self.env,
            exploration_policy(self.filter, self.feedback()),
            frames_per_batch=frames_per_batch,
            total_frames=max(remaining, frames_per_batch),
            auto_register_policy_transforms=False,
        )

    def deployed_weights(self) -> AbstractContextManager:
        """``validation.actor``: the filter validated and saved is the online actor (``online``)
        or DSAC-T's Polyak-averaged target actor (``target``), swapped in for the duration."""
        which = str(self.cfg.validation.actor)
        if which == "online":
            return nullcontext()
        if which == "target":
            return self._target_actor_swapped_in()
        raise ValueError(f"validation.actor must be 'online' or 'target', got {which!r}")

    @contextmanager
    def _target_actor_swapped_in(self) -> Iterator[None]:
        # to_module swaps on the call, not on entering: called here, inside the with-block
        with self.loss.target_actor_network_params.to_module(self.loss.actor_network):
            yield

    # ----------------------------------------------------------------- checkpoint parts
    def extra_state(self) -> dict:
        state = {
            "loss": self.loss.state_dict(),
            "optim_critic": self.optim_critic.state_dict(),
            "optim_actor": self.optim_actor.state_dict(),
            "optim_alpha": self.optim_alpha.state_dict(),
            "buffer": self.buffer.state_dict(),
        }
        bank = find_recorded(self.base_env.system)
        if bank is not None:  # the episodes a replayed env has yet to deal
            state["episode_bank"] = bank.state_dict()
        if self.collector is not None:
            state["in_flight"] = {
                "env": self.base_env.episode_state(),
                "window": self.env.transform.state_dict(),
                "carrier": self.collector._carrier.clone(),
                "traj_pool": self.collector._traj_pool.state_dict(),
            }
        return state

    def load_extra_state(self, blob: dict) -> None:
        self.loss.load_state_dict(blob["loss"])
        self.optim_critic.load_state_dict(blob["optim_critic"])
        self.optim_actor.load_state_dict(blob["optim_actor"])
        self.optim_alpha.load_state_dict(blob["optim_alpha"])
        self.buffer.load_state_dict(blob["buffer"])
        bank = find_recorded(self.base_env.system)
        if bank is not None and "episode_bank" in blob:
            bank.load_state_dict(blob["episode_bank"])
        self._resume = {"in_flight": blob.get("in_flight"), "rng": blob["rng"], "bank": blob.get("episode_bank")}

    def _continue_episodes(self, collector: Collector) -> None:
        """After a resume: the new collector continues the checkpoint's episodes, with its generators.

        Making the collector resets the env (new episodes, drawn from the env's generator or dealt from
        a replayed env's bank), so the episodes, the window, the carried step, the bank and every
        generator are put back after it.
        """
        saved, self._resume = self._resume, None
        if saved is None:
            return
        bank = find_recorded(self.base_env.system)
        if bank is not None and saved["bank"] is not None:
            bank.load_state_dict(saved["bank"])
        if saved["in_flight"] is not None:
            state = saved["in_flight"]
            self.base_env.load_episode_state(state["env"])
            self.env.transform.load_state_dict(state["window"])
            collector._carrier = TensorDict(state["carrier"], batch_size=self.env.batch_size)
            collector._traj_pool.load_state_dict(state["traj_pool"])
        restore_rng(saved["rng"], self.generators())

    def generators(self) -> dict[str, torch.Generator]:
        return {"env": self.base_env.rng}

    # ----------------------------------------------------------------- training
    def _update(self) -> dict:
        """One DSAC-T gradient update on a sampled batch.

        Critics step every update; the actor, α and the Polyak-averaged targets only every
        ``delay``-th update, where the actor loss is computed at all. Every backward runs before
        any optimiser step, because the actor loss reads the (detached) critic weights.
        """
        out = self.update_on(self.buffer.sample(), self.updates % int(self.cfg.loss.delay) == 0)
        self.updates += 1
        return out

    def update_on(self, batch: TensorDictBase, delayed: bool) -> dict:
        """The gradient steps of one update on ``batch``; ``delayed``: also the actor, α and targets."""
        if delayed:
            out = self.loss(batch)
        else:
            loss_q, meta = self.loss.qvalue_loss(batch)
            out = {"loss_qvalue": loss_q, **meta}
        self.optim_critic.zero_grad(set_to_none=True)
        out["loss_qvalue"].backward()
        if delayed:
            self.optim_actor.zero_grad(set_to_none=True)
            self.optim_alpha.zero_grad(set_to_none=True)
            (out["loss_actor"] + out["loss_alpha"]).backward()
        self.optim_critic.step()
        if delayed:
            self.optim_actor.step()
            self.optim_alpha.step()
            self.target_updater.step()
        return out

    def to_replay(self, batch: TensorDictBase) -> TensorDictBase:
        """A collected batch as flat replay transitions: unused keys dropped, the reward baseline
        taken off (``reward.baseline``)."""
        batch = batch.reshape(-1).exclude(*_DROP_KEYS)
        if self.baseline is not None:
            batch = self.baseline.subtract(batch)
        return batch

    def set_learning_rates(self) -> float:
        """Actor and critic learning rates on a cosine from ``lr`` to ``optim.lr_final`` × lr over the budget.

        Returns the factor (``FilterTrainer.lr_factor``).
        """
        factor = self.lr_factor()
        for optim, key in ((self.optim_actor, "lr_actor"), (self.optim_critic, "lr_critic")):
            for group in optim.param_groups:
                group["lr"] = float(self.cfg.optim[key]) * factor
        return factor

    def train(self) -> dict:
        """Collect, update, validate and checkpoint until ``collector.total_frames``."""
        c = self.cfg.collector
        total = int(c.total_frames)
        bar = self.start(total)
        collector = self.collector = self._make_collector(total - self.frames)
        self._continue_episodes(collector)
        updates_per_batch = round(int(c.env_batch) * int(c.steps_per_batch) * float(self.cfg.optim.utd))
        try:
            for batch in collector:
                if self.frames >= total:
                    break
                with timeit("collect"):
                    reward = batch["next", "reward"].mean().item()  # what the filter earns, before any baseline
                    batch = self.to_replay(batch)
                    self.buffer.extend(batch)
                    self.frames += batch.numel()
                metrics = {}
                if self.frames >= int(c.warmup_frames):
                    self.set_learning_rates()
                    with timeit("update"):
                        for _ in range(updates_per_batch):
                            metrics = {**metrics, **self._update()}
                log = {"train/reward": reward, "train/updates": self.updates}
                log.update({f"train/{k}": float(metrics[k].detach().mean()) for k in _LOGGED if k in metrics})
                self.after_batch(bar, batch.numel(), log, total)
        finally:
            collector.shutdown()
            self.collector = None
            bar.close()
        return self.finish()
