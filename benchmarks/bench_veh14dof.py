"""Throughput of the veh14dof simulator (envs/vehicle14dof), eager or ``--compile``d.

Measures simulated filter steps per second — run-steps, i.e. runs × steps / wall time, each
filter step being 20 RK4 steps at h = 1 ms plus the sensor model — at batch 1, 64 and 1024,
and the training-data generation rate of ``simulate(runs, 500)``. Prints a markdown table.

    .venv/bin/python benchmarks/bench_veh14dof.py --threads 1
    .venv/bin/python benchmarks/bench_veh14dof.py --threads 1 --compile
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import daof.envs as envs
import torch


def time_steps(system, runs: int, steps: int, warmup: int = 2) -> float:
    """Run-steps per second of ``advance`` at batch ``runs`` (after ``warmup`` steps)."""
    gen = torch.Generator().manual_seed(0)
    with torch.inference_mode():
        sim = system.reset_episode(runs, gen)
        for _ in range(warmup):
            sim, _ = system.advance(sim, gen)
        t0 = time.perf_counter()
        for _ in range(steps):
            sim, _ = system.advance(sim, gen)
        elapsed = time.perf_counter() - t0
    return runs * steps / elapsed


def time_simulate(system, runs: int, steps: int) -> tuple[float, float]:
    """(seconds, run-steps per second) of ``simulate(runs, steps)``."""
    t0 = time.perf_counter()
    with torch.inference_mode():
        system.simulate(runs, steps, seed=0)
    elapsed = time.perf_counter() - t0
    return elapsed, runs * steps / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--steps", type=int, default=None, help="timed filter steps per batch (default: auto)")
    ap.add_argument("--sim-runs", type=int, default=1024, help="runs for the simulate(runs, 500) row")
    ap.add_argument("--sim-steps", type=int, default=500)
    ap.add_argument("--compile", action="store_true", help="torch.compile the RK4 step (opt-in)")
    args = ap.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    system = envs.make_system("veh14dof", dtype=args.dtype, compile=args.compile)

    print(f"date: {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, dtype {args.dtype}, ", end="")
    print(f"compile {args.compile}, ", end="")
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()}")
    print()
    print("| what | batch | filter steps/s (runs × steps / s) | RK4 steps/s | wall per filter step |")
    print("|---|---|---|---|---|")
    if args.compile:
        for runs in sorted({*args.batches, args.sim_runs}):  # dynamic=False: one compile per batch size
            t0 = time.perf_counter()
            time_steps(system, runs, 1, warmup=0)
            print(f"compile + first step at batch {runs}: {time.perf_counter() - t0:.1f} s")
        print()
    for runs in args.batches:
        steps = args.steps or max(5, min(50, 20000 // runs))
        rate = time_steps(system, runs, steps)
        per_step_ms = runs / rate * 1e3
        print(f"| advance | {runs} | {rate:,.0f} | {rate * system.n_sub:,.0f} | {per_step_ms:.1f} ms |")
    secs, rate = time_simulate(system, args.sim_runs, args.sim_steps)
    print(
        f"| simulate({args.sim_runs}, {args.sim_steps}) | {args.sim_runs} | {rate:,.0f} | "
        f"{rate * system.n_sub:,.0f} | total {secs:.1f} s |"
    )


if __name__ == "__main__":
    main()
