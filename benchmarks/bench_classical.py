"""RMSE and cost per estimate of the classical baselines on veh2dof (docs/design.md, "The benchmark protocol").

    .venv/bin/python benchmarks/bench_classical.py --runs 20 --steps 500 --threads 1
    .venv/bin/python benchmarks/bench_classical.py --scenario mismatch --oracle-particles 20000

On a scenario with uncertain model parameters (``mismatch``) PF-joint, the PF that also infers them
(``JointParameterPF``, as many particles as PF-oracle), is timed too.

RMSE: pooled over runs × steps of one study. Cost: mean wall time of one filter update for one
trajectory (batch 1) streamed step by step through ``run``, after a warm-up, median over
``--repeats`` passes. Throughput: estimates per second of the whole study (batch = runs).
``--models`` also times one call of the numpy and torch model used inside the Kalman filters.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import daof.envs as envs
import numpy as np
import torch

from daof.filters import EKF, UKF, JointParameterPF, ParticleFilter
from daof.filters.kalman import make_model


def per_step_cost(filt, trajectory, repeats: int) -> float:
    """Median wall time (ms) of one update at batch 1, after one warm-up pass."""
    filt.run(trajectory[:, :50])
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        filt.run(trajectory)
        times.append((time.perf_counter() - start) / trajectory.shape[1])
    return 1e3 * statistics.median(times)


def model_costs(system, calls: int = 2000) -> list[str]:
    x, u = np.array([0.01, 0.1]), np.array([0.03])
    rows = ["| model | f (µs) | g (µs) | F = ∂f/∂x (µs) |", "|---|---|---|---|"]
    for kind in ("numpy", "torch"):
        model = make_model(system, kind)
        cells = []
        for fn in (model.f, model.g, model.F):
            fn(x, u)
            start = time.perf_counter()
            for _ in range(calls):
                fn(x, u)
            cells.append(f"{1e6 * (time.perf_counter() - start) / calls:.1f}")
        rows.append(f"| {kind} | " + " | ".join(cells) + " |")
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--scenario", default="nominal", help="veh2dof scenario (nominal, mismatch, outliers)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--oracle-particles", type=int, default=10_000)
    parser.add_argument("--models", action="store_true", help="also time the numpy vs torch model calls")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    system = envs.make_system("veh2dof", args.scenario)
    data = system.simulate(args.runs, args.steps, seed=args.seed)
    truth = data["state"]
    filters = {
        "EKF": EKF(system),
        "UKF": UKF(system),
        "PF": ParticleFilter(system, 1000, seed=args.seed + 1),
        "PF-oracle": ParticleFilter(system, args.oracle_particles, seed=args.seed + 1),
    }
    if system.uncertain_parameters():
        filters["PF-joint"] = JointParameterPF(system, args.oracle_particles, seed=args.seed + 1)
    print(
        f"veh2dof {args.scenario}, {args.runs} runs × {args.steps} steps, seed {args.seed}, "
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, {platform.processor() or platform.machine()}"
    )
    raw = (data["measurement"][..., 1] - truth[..., 1]).pow(2).mean().sqrt()
    print(f"raw yaw-rate measurement RMSE: {raw:.4f} rad/s\n")
    print(
        "| filter | RMSE β (rad) | RMSE r (rad/s) | cost per estimate, batch 1 (ms) | throughput, batch "
        f"{args.runs} (estimates/s) | repairs | diverged |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, filt in filters.items():
        start = time.perf_counter()
        estimate = filt.run(data)
        throughput = args.runs * args.steps / (time.perf_counter() - start)
        stats = dict(filt.stats)
        rmse = (estimate - truth).pow(2).mean((0, 1)).sqrt()
        cost = per_step_cost(filt, data[:1], args.repeats)
        label = f"{name} (N={filt.num_particles})" if isinstance(filt, ParticleFilter) else name
        print(
            f"| {label} | {rmse[0]:.5f} | {rmse[1]:.5f} | {cost:.3f} | {throughput:.0f} | "
            f"{stats.get('repairs', '–')} | {stats['diverged']} |"
        )
    if args.models:
        print()
        print("\n".join(model_costs(system)))


if __name__ == "__main__":
    main()
