"""How good is DAOF-v1's reference update alone? The mean-gain filter against a UKF, same data.

    .venv/bin/python diagnostics/reference_gain.py --system veh2dof

DAOF-v1 estimates x̂_t = f(x̂_{t−1}, u_{t−1}) + K̄_t ν_t + b_t ⊙ π(h_t),
K̄_t a UKF's mean Kalman gain at step t over 16 simulated runs (the schedule a training run builds).
With π = 0, where a residual run starts, that is a gain-scheduled Kalman filter on the model's own
prediction. This prints its RMSE beside the UKF's (and the KF's on ``linear``) over all steps, the
start-up (t < 20) and the settled steps (t ≥ 50) of the validation set the trainings use.
"""

from __future__ import annotations

import argparse

import torch
from daof.envs import make_system

from daof.filters import UKF, KalmanFilter
from daof.filters.learned import FilterConfig, LearnedFilter
from daof.train.schedules import ukf_schedule


def rmse(estimate: torch.Tensor, truth: torch.Tensor, steps: slice) -> list[float]:
    return [round(v, 5) for v in (estimate - truth)[:, steps].pow(2).mean((0, 1)).sqrt().tolist()]


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="veh2dof")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=9100, help="the recipes' validation seed")
    parser.add_argument("--schedule-seed", type=int, default=7_000_002, help="seeds.normalizer + 1, as trainings use")
    args = parser.parse_args()
    system = make_system(args.system)
    config = FilterConfig(kind="DAOF-v1", system=args.system)
    reference = LearnedFilter(config, system)
    reference.set_schedules(ukf_schedule(system, seed=args.schedule_seed))
    last = [m for m in reference.policy.mlp if isinstance(m, torch.nn.Linear)][-1]
    last.weight.zero_(), last.bias.zero_()  # π = 0: tanh(loc) = 0
    data = system.simulate(args.runs, 500, args.seed)
    filters = {"mean-gain reference (DAOF-v1, π = 0)": reference, "UKF": UKF(system)}
    if args.system == "linear":
        filters["KF"] = KalmanFilter(system)
    names = ", ".join(system.state_names)
    print(f"{args.system}: {args.runs} runs x 500 steps, seed {args.seed}; RMSE [{names}]")
    print("| filter | all steps | t < 20 | t ≥ 50 |\n|---|---|---|---|")
    for name, f in filters.items():
        estimate = f.run(data).float()
        parts = [rmse(estimate, data["state"], s) for s in (slice(None), slice(0, 19), slice(49, None))]
        print(f"| {name} | " + " | ".join(str(p) for p in parts) + " |")


if __name__ == "__main__":
    main()
