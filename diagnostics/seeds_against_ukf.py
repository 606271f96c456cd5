"""How much does a learned filter's lead over the UKF depend on its training seed?

Each checkpoint against the UKF on Experiment I's evaluation data (veh2dof, 100 runs × 500 steps,
seed 20261122), with the report's paired bootstrap interval::

    python -m daof.train filter=daof_v1 system=veh2dof seed=2 output_dir=runs/seeds/daof-v1-s2
    python diagnostics/seeds_against_ukf.py runs/seeds/daof-v1-s*/best.pt

(An experiment with ``training_seeds=[1,2,3]`` gives the same per seed, with the whole study.)
"""

import sys

import torch
from daof.envs import make_system

from daof.evaluate.metrics import paired_rmse_ratio
from daof.filters.kalman import UKF
from daof.filters.learned import load_filter

EVALUATION_SEED, RUNS, STEPS = 20261122, 100, 500


def main(paths: list[str]) -> None:
    torch.set_num_threads(1)
    system = make_system("veh2dof")
    data = system.simulate(RUNS, STEPS, EVALUATION_SEED)

    def per_run(estimates: torch.Tensor) -> torch.Tensor:
        return (estimates.double() - data["state"].double()).pow(2).mean(1).sqrt()

    ukf = per_run(UKF(system).run(data))
    print("UKF RMSE", [round(v, 5) for v in ukf.pow(2).mean(0).sqrt().tolist()])
    for path in paths:
        run = per_run(load_filter(path).run(data))
        c = paired_rmse_ratio(run, ukf)
        cells = [f"{r:.3f} [{lo:.3f}, {hi:.3f}], {b}/{RUNS} runs better" for r, lo, hi, b in
                 zip(c["ratio"], c["low"], c["high"], c["better_runs"])]  # fmt: skip
        print(path, "RMSE", [round(v, 5) for v in run.pow(2).mean(0).sqrt().tolist()], "ratio to the UKF", cells)


if __name__ == "__main__":
    main(sys.argv[1:])
