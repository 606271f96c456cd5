"""Start-up schedules of a DAOF training run, from a UKF on simulated data.

Right after a reset every filter carries the prior's error, which is far larger than its settled
error (on ``linear`` 13× on position at t = 1). Three things are sized per step t from the UKF's
covariances (``_KalmanBase.covariance_schedule``), for t = 1..SCHEDULE_STEPS, then held:

* DAOF-v1's update bound b_t, so that the first updates can pull in the prior's error at all,
  and the scale of its innovation input (``LearnedFilter.set_schedules``);
* the reward weights W_t, so that a start-up step earns about what a settled step does. DSAC-T's
  critic weighs the mean term of each sample by (σ̄² + ε)/(σ² + ε): without this, the large,
  noisy start-up returns are learned hundreds of times more slowly than the rest and the
  start-up is never fitted (docs/experiment1.md).
"""

from __future__ import annotations

import torch

from daof.envs.system import StochasticSystem
from daof.filters.kalman import UKF
from daof.filters.learned import SCHEDULE_STEPS

__all__ = ["ukf_schedule", "reward_weight_schedule"]


def ukf_schedule(system: StochasticSystem, seed: int, runs: int = 16) -> dict[str, torch.Tensor]:
    """A UKF's ``covariance_schedule`` for t = 1..SCHEDULE_STEPS on ``runs`` simulated runs, float32."""
    data = system.simulate(runs, SCHEDULE_STEPS, seed)
    return {key: value.float() for key, value in UKF(system).covariance_schedule(data).items()}


def reward_weight_schedule(system: StochasticSystem, error_std: torch.Tensor) -> torch.Tensor:
    """W_t = W · ρ_t per step, [steps, n]; W = 1/(n · error_scale²) is the env's default.

    ρ_t = min(1, (σ_settled / σ_t)²), made non-decreasing in t (running max), with σ_t the given
    error std per step (DSAC-T runs pass the UKF's estimate error √diag P⁺_t, what a good filter
    reaches at step t) and σ_settled its mean over the second half: a good filter earns about the
    same at every step, and from the first step that reaches 1 on every step keeps W.

    Scaling by the prediction error √diag P⁻_t instead was measured worse: it leaves the start-up
    so cheap that the entropy bonus puts the actor's widest exploration there, and the squashed
    loc (the deterministic filter) then overshoots the first updates 1.6–2.4× (docs/experiment1.md).
    """
    n = system.state_dim
    weights = 1.0 / (n * system.error_scale.float() ** 2)
    settled = error_std[len(error_std) // 2 :].mean(0)
    ratio = (settled / error_std.clamp_min(1e-12)).pow(2)
    return ratio.clamp(max=1.0).cummax(0).values * weights
