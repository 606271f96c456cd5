"""FilteringEnv: any StochasticSystem as a natively batched TorchRL environment.

The filtering MDP (docs/design.md): at step t the agent sees the measurement y_t, the known controls
u_t and u_{t−1}, and its own previous estimate x̂_{t−1}; its action is the estimate x̂_t; the
reward is r_t = −‖x_t − x̂_t‖²_W. After a reset the previous estimate is the prior mean x̂_0 and
the first measurement is y_1 (see ``daof.envs.system`` for the time convention).

Keys. Observations: ``measurement``, ``control`` (u_t), ``prev_control`` (u_{t−1}, what the
DAOF-v1 predictor needs), ``prev_estimate`` (x̂_{t−1}) and ``step`` (t, the number of measurements
since the reset: 1 right after it; DAOF-v1 sizes its update bound by it). The true state x_t travels under
``true_state`` for logging and supervised training only: no filter module in this project reads
it, and a filter that did would be cheating. A system with gaps (``daof.envs.gaps.GappySystem``) adds
``missing``, the 0/1 flags of the channels whose measurement is a held value.

Fed-back estimate. The next step's ``prev_estimate`` is the action, unless the policy also
writes ``fed_back_estimate`` (``FEEDBACK_KEY``): then that is fed back while the reward scores the
action. A DSAC-T collector uses it to feed back the policy's deterministic estimate, the one the
deployed filter feeds back, and to explore in the reward only (``daof.train.dsac``, ``collector.feedback``).

Reward weights. By default W = diag(1 / (n · s_i²)) with s the system's ``error_scale`` (the
typical error of a decent filter per state, from the system's data: ``daof.envs.scales``), so such
a filter earns about −1 per step and the states count equally relative to what is achievable.
"""

from __future__ import annotations

import torch
from daof.envs.checks import as_seed
from daof.envs.gaps import MISSING_KEY
from daof.envs.system import StochasticSystem
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["FEEDBACK_KEY", "FilteringEnv", "default_reward_weights", "make_env"]

#: optional policy output: the estimate to feed back as the next ``prev_estimate`` (default: the action)
FEEDBACK_KEY = "fed_back_estimate"


def default_reward_weights(system: StochasticSystem) -> torch.Tensor:
    """W = 1 / (n · s²) per state, s the system's ``error_scale`` (module docstring)."""
    return 1.0 / (system.state_dim * system.error_scale**2)


class FilteringEnv(EnvBase):
    """Batched, batch-locked env: action = estimate x̂_t, reward = −‖x_t − x̂_t‖²_W.

    Args:
        system: the system to filter.
        batch_size: number of parallel episodes B (an int or ``[B]``).
        max_steps: episode length T; an episode ends ``truncated`` after T estimates.
        reward_weights: per-state weights W (``[state_dim]``), default 1/(n·error_scale²), or one
            row per step t = 1..S (``[S, state_dim]``; steps after S use the last row).
        seed: seed of the env's ``torch.Generator`` (``set_seed`` can change it later).
        device: where the simulation runs.
    """

    batch_locked = True

    def __init__(
        self,
        system: StochasticSystem,
        batch_size: int | tuple[int, ...] = 1,
        max_steps: int = 500,
        reward_weights=None,
        seed: int | None = None,
        device="cpu",
    ):
        batch_size = torch.Size([batch_size] if isinstance(batch_size, int) else batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"FilteringEnv needs a batch size [B] with B >= 1, got {list(batch_size)}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        super().__init__(device=device, batch_size=batch_size)
        self.system = system.to(self.device)
        self.max_steps = int(max_steps)
        n = system.state_dim
        if reward_weights is None:
            reward_weights = default_reward_weights(system)
        self.reward_weights = torch.as_tensor(reward_weights, dtype=torch.float32, device=self.device)
        w = self.reward_weights
        if w.ndim not in (1, 2) or w.shape[-1] != n or w.numel() == 0 or (w < 0).any() or not torch.isfinite(w).all():
            raise ValueError(
                f"reward_weights must be {n} non-negative numbers or a [steps, {n}] schedule, "
                f"got shape {tuple(w.shape)}"
            )
        self._make_specs()
        self.rng = torch.Generator(device=self.device)
        self._set_seed(seed if seed is not None else int(torch.seed() % 2**31))
        self._sim: TensorDict | None = None
        self._obs: TensorDict | None = None
        self._prev_estimate: torch.Tensor | None = None

    # ----------------------------------------------------------------- specs
    def _make_specs(self) -> None:
        s, B, dev = self.system, self.batch_size, self.device
        n, m, c = s.state_dim, s.measurement_dim, s.control_dim
        self.observation_spec = Composite(
            measurement=Unbounded(shape=(*B, m), device=dev),
            control=Unbounded(shape=(*B, c), device=dev),
            prev_control=Unbounded(shape=(*B, c), device=dev),
            prev_estimate=Unbounded(shape=(*B, n), device=dev),
            step=Unbounded(shape=(*B, 1), dtype=torch.int64, device=dev),
            true_state=Unbounded(shape=(*B, n), device=dev),
            # the reward's terms, −W_i(x_i − x̂_i)², for a critic per state (0 after a reset)
            reward_per_state=Unbounded(shape=(*B, n), device=dev),
            **({MISSING_KEY: Unbounded(shape=(*B, m), device=dev)} if s.reports_missing else {}),
            shape=B,
            device=dev,
        )
        self.action_spec = Bounded(
            low=s.state_low.to(dev).expand(*B, n),
            high=s.state_high.to(dev).expand(*B, n),
            shape=(*B, n),
            device=dev,
        )
        self.reward_spec = Unbounded(shape=(*B, 1), device=dev)
        flag = Categorical(2, shape=(*B, 1), dtype=torch.bool, device=dev)
        self.full_done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=B, device=dev
        )

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(as_seed(seed) if seed is not None else 0)

    # ----------------------------------------------------------------- episodes in flight
    def episode_state(self) -> dict | None:
        """The episodes under way (simulator state, last observation, fed-back estimate), as plain data.

        With ``load_episode_state`` and the generator's state a resumed training continues them.
        """
        if self._sim is None:
            return None
        return {"sim": self._sim.to_dict(), "obs": self._obs.to_dict(), "prev_estimate": self._prev_estimate.clone()}

    def load_episode_state(self, state: dict) -> None:
        """Inverse of ``episode_state``."""
        self._sim = TensorDict(state["sim"], batch_size=self.batch_size, device=self.device)
        self._obs = TensorDict(state["obs"], batch_size=self.batch_size, device=self.device)
        self._prev_estimate = state["prev_estimate"].to(self.device).clone()

    # ----------------------------------------------------------------- dynamics
    def _observation(self, reward_per_state: torch.Tensor | None = None) -> dict:
        if reward_per_state is None:
            reward_per_state = torch.zeros_like(self._prev_estimate)
        missing = {MISSING_KEY: self._obs[MISSING_KEY]} if self.system.reports_missing else {}
        return {
            **missing,
            "reward_per_state": reward_per_state,
            "measurement": self._obs["measurement"],
            "control": self._obs["control"],
            "prev_control": self._obs["prev_control"],
            "prev_estimate": self._prev_estimate,
            "step": self._sim["t"].unsqueeze(-1),
            "true_state": self._obs["state"],
        }

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
        B = self.batch_size[0]
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(B)
        # Draw a whole batch of new episodes and take the masked rows: the random stream does
        # not depend on which runs are reset.
        sim = self.system.reset_episode(B, self.rng, self.device)
        sim, obs = self.system.advance(sim, self.rng)
        prior_mean = self.system.prior.mean.to(self.device).expand(B, -1).clone()
        if mask is None or self._sim is None:
            self._sim, self._obs, self._prev_estimate = sim, obs, prior_mean
        else:
            self._sim[mask] = sim[mask]
            self._obs[mask] = obs[mask]
            self._prev_estimate = torch.where(mask[:, None], prior_mean, self._prev_estimate)
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {**self._observation(), "done": false, "terminated": false.clone(), "truncated": false.clone()},
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        estimate = tensordict["action"]
        if not torch.isfinite(estimate).all():
            bad = (~torch.isfinite(estimate)).any(-1).nonzero().flatten().tolist()
            raise ValueError(f"the estimate (action) is not finite in run(s) {bad[:10]}")
        error = self._obs["state"] - estimate
        weights = self.reward_weights
        if weights.ndim == 2:  # W_t of the step being estimated
            weights = weights[self._sim["t"].clamp(1, len(weights)) - 1]
        reward_per_state = -(error.pow(2) * weights)
        fed_back = tensordict.get(FEEDBACK_KEY, None)
        if fed_back is not None and fed_back.shape != estimate.shape:
            raise ValueError(f"{FEEDBACK_KEY} has shape {tuple(fed_back.shape)}, the action {tuple(estimate.shape)}")
        self._sim, self._obs = self.system.advance(self._sim, self.rng)
        self._prev_estimate = (estimate if fed_back is None else fed_back).detach().clone()
        # sim["t"] counts measured steps; the episode ends after max_steps estimates.
        truncated = (self._sim["t"] > self.max_steps).unsqueeze(-1)
        return TensorDict(
            {
                **self._observation(reward_per_state),
                "reward": reward_per_state.sum(-1, keepdim=True),
                "done": truncated.clone(),
                "terminated": torch.zeros_like(truncated),
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )


def make_env(
    name: str,
    batch_size: int = 1,
    window: int = 20,
    scenario: str = "nominal",
    seed: int | None = None,
    device="cpu",
    max_steps: int = 500,
    include_controls: bool = True,
    reward_weights=None,
    layout=None,
    **overrides,
):
    """The filtering env of system ``name`` with its history window (a ``TransformedEnv``).

    The window is padded with copies of the first frame (``daof.envs.history``); ``overrides`` go
    to ``make_system`` (system parameters). ``layout`` (a ``FrameLayout``, e.g. a learned filter's
    ``filter.layout``) gives the window instead of ``window`` and ``include_controls``.
    """
    from daof.envs.history import FrameLayout, with_window
    from daof.envs.registry import make_system

    system = make_system(name, scenario, **overrides)
    env = FilteringEnv(system, batch_size, max_steps, reward_weights, seed, device)
    if layout is None:
        layout = FrameLayout.for_system(system, window, include_controls=include_controls)
    return with_window(env, layout)
