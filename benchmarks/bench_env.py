"""Throughput of the filtering env against the raw system it wraps.

A transition is one env step of one run, so a step of a batch-B env counts B transitions. For
each batch size this times

* ``raw``: ``system.advance`` alone (f, g and the noise draws; what any simulator must pay),
* ``loop``: a manual ``env.step_and_maybe_reset`` loop with a constant policy (history window,
  resets at episode ends; nothing is stored),
* ``rollout``: ``env.rollout(steps, policy, break_when_any_done=False)``, which also stacks the
  trajectory into one TensorDict,

and reports the faster of loop / rollout as the env's rate and raw / env as the env overhead.
Each number is the best of ``--repeats`` timed runs after a warm-up.

    .venv/bin/python benchmarks/bench_env.py --threads 1
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import torch
from daof.envs import make_env


def best_rate(fn, transitions: int, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return transitions / best


def bench(batch: int, steps: int, window: int, repeats: int, name: str) -> dict[str, float]:
    env = make_env(name, batch_size=batch, window=window, seed=0)
    system = env.base_env.system
    action = torch.zeros(batch, system.state_dim)

    def policy(td):
        return td.set("action", action)

    generator = torch.Generator().manual_seed(0)

    @torch.no_grad()
    def raw():
        sim = system.reset_episode(batch, generator)
        for _ in range(steps):
            sim, _ = system.advance(sim, generator)

    @torch.no_grad()
    def loop():
        td = env.reset()
        for _ in range(steps):
            td.set("action", action)
            _, td = env.step_and_maybe_reset(td)

    @torch.no_grad()
    def rollout():
        env.rollout(steps, policy, break_when_any_done=False)

    transitions = batch * steps
    return {
        "raw": best_rate(raw, transitions, repeats),
        "loop": best_rate(loop, transitions, repeats),
        "rollout": best_rate(rollout, transitions, repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--steps", type=int, default=None, help="steps per timed run (default: by batch)")
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--system", default="veh2dof")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    print(
        f"# {datetime.datetime.now().isoformat(timespec='seconds')}  torch {torch.__version__}  "
        f"threads {torch.get_num_threads()}  cpus {os.cpu_count()}  load {os.getloadavg()[0]:.2f}  "
        f"{platform.processor() or platform.machine()}"
    )
    print(f"# system {args.system}, window {args.window}, constant policy, transitions/s")
    print(f"# each number the best of {args.repeats} timed runs after a warm-up")
    columns = ("raw system", "env loop", "env rollout", "env best")
    print(f"{'batch':>6} {'steps':>6} " + " ".join(f"{c:>12}" for c in columns) + f" {'overhead':>9}")
    for batch in args.batches:
        steps = args.steps or max(100, min(500, 100_000 // batch))
        r = bench(batch, steps, args.window, args.repeats, args.system)
        env_rate = max(r["loop"], r["rollout"])
        print(
            f"{batch:>6} {steps:>6} {r['raw']:>12,.0f} {r['loop']:>12,.0f} {r['rollout']:>12,.0f} "
            f"{env_rate:>12,.0f} {r['raw'] / env_rate:>8.2f}x"
        )


if __name__ == "__main__":
    main()
