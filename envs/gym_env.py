"""The filtering MDP as a single-episode gymnasium env, registered as ``daof/Veh2DOF-v0``.

Importing ``daof.envs`` registers the id. gymnasium 1.0 removed the plugin entry points through
which an installed package registered its ids at gymnasium's import (the ``module:id`` form replaced
them), so a fresh interpreter names the module in the id: ``gymnasium.make("daof.envs:daof/Veh2DOF-v0")``;
TorchRL's ``GymEnv("daof/Veh2DOF-v0")`` works once ``daof.envs`` is imported.

Same MDP as ``daof.envs.filtering_env.FilteringEnv`` with batch 1 and its history window: the
observation is h_t^N (the last N frames [x̂_{t−1}, y_t, u_t, u_{t−1}], oldest first, padded with
the first frame after a reset), the action is the estimate x̂_t, the reward −‖x_t − x̂_t‖²_W.
It drives the same ``StochasticSystem`` (``reset_episode`` / ``advance``) with a torch.Generator
consumed in the same order, so the same seed gives the same episode as ``make_env(..., seed)``.
For users of gymnasium-based tooling; training in this project uses the batched TorchRL env.
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
import torch
from daof.envs.history import FrameLayout
from daof.envs.registry import make_system
from daof.envs.system import StochasticSystem
from gymnasium import spaces

__all__ = ["FilteringGymEnv", "Veh2DOFGymEnv", "GYM_ID"]

GYM_ID = "daof/Veh2DOF-v0"


class FilteringGymEnv(gymnasium.Env):
    """One episode of any ``StochasticSystem`` as a gymnasium env (numpy float32 in and out).

    Args:
        system: the system to filter.
        window: N, the number of frames in the observation.
        max_steps: T; the episode is ``truncated`` (never ``terminated``) after T estimates.
        reward_weights: W per state; default 1/(n·error_scale²) as in the TorchRL env.
        include_controls: frames carry (u_t, u_{t−1}) (systems with controls).

    The window is the closed-loop ``FrameLayout`` of the TorchRL env (``self.layout``, "same" padding).
    ``info`` carries ``true_state`` (x_t of the new observation) for logging only.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        system: StochasticSystem,
        window: int = 20,
        max_steps: int = 500,
        reward_weights=None,
        include_controls: bool = True,
    ):
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.layout = FrameLayout.for_system(system, window, include_controls=include_controls)
        self.system = system
        self.window = window
        self.max_steps = int(max_steps)
        n = system.state_dim
        if reward_weights is None:
            reward_weights = 1.0 / (n * system.error_scale**2)
        self.reward_weights = torch.as_tensor(reward_weights, dtype=torch.float32)
        if self.reward_weights.shape != (n,) or (self.reward_weights < 0).any():
            raise ValueError(f"reward_weights must be {n} non-negative numbers, got {reward_weights}")
        self.frame_dim = self.layout.frame_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.layout.width,), np.float32)
        self.action_space = spaces.Box(
            system.state_low.numpy().astype(np.float32), system.state_high.numpy().astype(np.float32)
        )
        self._rng: torch.Generator | None = None
        self._sim = self._obs = None
        self._window: torch.Tensor | None = None
        self._steps = 0

    def _frame(self, prev_estimate: torch.Tensor) -> torch.Tensor:
        values = {key: self._obs[key][0] for key in self.layout.keys if key != "prev_estimate"}
        return self.layout.frame({**values, "prev_estimate": prev_estimate.float()})

    def _info(self) -> dict:
        return {"true_state": self._obs["state"][0].numpy().copy(), "step": self._steps}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or self._rng is None:
            # Without a seed the first reset draws one from gymnasium's np_random.
            seed = int(seed) if seed is not None else int(self.np_random.integers(2**31))
            self._rng = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            sim = self.system.reset_episode(1, self._rng)
            self._sim, self._obs = self.system.advance(sim, self._rng)
        self._steps = 0
        # Padding "same": N copies of the first frame (prior mean x̂_0, y_1, u_1, u_0).
        self._window = self.layout.first_window(self._frame(self.system.prior.mean))
        return self._window.numpy().astype(np.float32), self._info()

    def step(self, action):
        if self._sim is None:
            raise RuntimeError("call reset() before step()")
        estimate = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(self.system.state_dim)
        if not torch.isfinite(estimate).all():
            raise ValueError(f"the estimate (action) is not finite: {estimate.tolist()}")
        error = self._obs["state"][0] - estimate
        reward = -float((error.pow(2) * self.reward_weights).sum())
        with torch.no_grad():
            self._sim, self._obs = self.system.advance(self._sim, self._rng)
        self._steps += 1
        self._window = self.layout.slide(self._window, self._frame(estimate))
        truncated = self._steps >= self.max_steps
        return self._window.numpy().astype(np.float32), reward, False, truncated, self._info()


class Veh2DOFGymEnv(FilteringGymEnv):
    """The 2-DOF vehicle (Experiment I) as a gymnasium env; ``overrides`` go to ``make_system``."""

    def __init__(
        self,
        scenario: str = "nominal",
        window: int = 20,
        max_steps: int = 500,
        reward_weights=None,
        **overrides,
    ):
        from daof.envs.registry import SYSTEMS

        known = {f.name for f in dataclasses.fields(SYSTEMS["veh2dof"][1])}
        for name in overrides:  # a TypeError, as for any callable: gymnasium and TorchRL's GymEnv rely on it
            if name not in known:
                raise TypeError(f"Veh2DOFGymEnv got an unexpected keyword argument {name!r}")
        super().__init__(make_system("veh2dof", scenario, **overrides), window, max_steps, reward_weights)


if GYM_ID not in gymnasium.registry:
    gymnasium.register(id=GYM_ID, entry_point="daof.envs.gym_env:Veh2DOFGymEnv")
