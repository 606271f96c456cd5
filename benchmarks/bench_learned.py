"""Cost per estimate of the learned filters at batch 1, next to the UKF and EKF (docs/design.md, protocol).

    .venv/bin/python benchmarks/bench_learned.py --threads 1
    .venv/bin/python benchmarks/bench_learned.py --checkpoint runs/veh2dof/nominal/daof-v1-N20-s1/best.pt

The cost does not depend on the weights, so by default freshly built filters of the default size
(3 × 256 GELU, N = 20) are timed; ``--checkpoint`` times trained ones instead. Cost: one trajectory
streamed step by step through ``run_streaming`` (the SLF too, although ``run`` vectorises it over
time), after a warm-up, median over passes (``daof.evaluate.timing.cost_per_estimate``).
"""

from __future__ import annotations

import argparse
import os
import platform

import torch
from daof.envs import make_system

from daof.evaluate.timing import cost_per_estimate
from daof.filters import EKF, UKF
from daof.filters.learned import FilterConfig, LearnedFilter, load_filter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--checkpoint", action="append", default=[], help="a trained filter (repeatable)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    system = make_system("veh2dof")
    data = system.simulate(1, 500, seed=20261122)
    filters = {path: load_filter(path, system) for path in args.checkpoint}
    if not filters:
        for kind in ("DAOF-v1", "DAOF-v2", "SLF"):
            f = LearnedFilter(FilterConfig(kind=kind, system="veh2dof", window=args.window), system)
            f.fit_normalizer(runs=4, steps=100)
            filters[f"{kind} (N={args.window})"] = f.eval()
    filters.update({"UKF": UKF(system), "EKF": EKF(system)})
    print(
        f"torch {torch.__version__}, threads {args.threads}, {platform.machine()}, {os.cpu_count()} CPUs, "
        f"load {tuple(round(x, 2) for x in os.getloadavg())}"
    )
    print("| filter | cost per estimate [ms] |\n|---|---|")
    for name, filt in filters.items():
        print(f"| {name} | {cost_per_estimate(filt, data):.3f} |")


if __name__ == "__main__":
    main()
