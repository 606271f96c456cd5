"""Cost per estimate of the learned filters at batch 1, next to the UKF and EKF (docs/design.md, protocol),
and of their exported steps (docs/deploy.md).

    .venv/bin/python benchmarks/bench_learned.py --threads 1
    .venv/bin/python benchmarks/bench_learned.py --checkpoint runs/veh2dof/nominal/daof-v1-N20-s1/best.pt
    .venv/bin/python benchmarks/bench_learned.py --export torch,aoti,onnx

The cost does not depend on the weights, so by default freshly built filters of the default size
(3 × 256 GELU, N = 20; DAOF-v1 with a UKF's schedules) are timed; ``--checkpoint`` times trained
ones instead. Cost: one trajectory streamed step by step through ``run_streaming`` (the SLF too,
although ``run`` vectorises it over time), after a warm-up, median over passes
(``daof.evaluate.timing.cost_per_estimate``).

``--export FORMATS`` exports each learned filter (``daof.export``) and times, interleaved in one
run, every path on the same 500-step trajectory: eager ``run_streaming``, the exported step in each
format (streamed by ``daof.export.trajectory``: the per-step inputs sliced beforehand, the loop
holds the call and the carry) and the UKF. Each pass times every path once, in an order rotated
from pass to pass; the table gives the median over passes with the 25–75 % range, and the ratios
of medians. Then batched throughput: estimates per second streaming ``--batch`` runs at once.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch
from daof.envs import make_system

from daof.evaluate.timing import cost_per_estimate
from daof.filters import EKF, UKF
from daof.filters.learned import FilterConfig, LearnedFilter, load_filter
from daof.train.schedules import ukf_schedule


def fresh_filters(system, window: int) -> dict[str, LearnedFilter]:
    """Freshly initialised filters of the default size, normalisation (and DAOF-v1's schedules) fitted."""
    filters = {}
    for kind in ("DAOF-v1", "DAOF-v2", "SLF"):
        f = LearnedFilter(FilterConfig(kind=kind, system="veh2dof", window=window), system)
        f.fit_normalizer(runs=4, steps=100)
        if kind == "DAOF-v1":
            f.set_schedules(ukf_schedule(system, seed=3, runs=4))
        filters[f"{kind} (N={window})"] = f.eval()
    return filters


def load() -> str:
    return f"load {tuple(round(x, 2) for x in os.getloadavg())}"


def interleaved(paths: dict, passes: int, per_pass: int) -> dict[str, list[float]]:
    """Seconds per estimate of every path per pass: each pass runs each path once, the order rotated."""
    names = list(paths)
    for run in paths.values():  # warm-up
        run()
    times = {name: [] for name in names}
    for p in range(passes):
        for name in names[p % len(names) :] + names[: p % len(names)]:
            start = time.perf_counter()
            paths[name]()
            times[name].append((time.perf_counter() - start) / per_pass)
    return times


def quartiles(values: list[float]) -> tuple[float, float, float]:
    q1, q2, q3 = statistics.quantiles(values, n=4)
    return q1, q2, q3


def export_all(filters: dict, formats: list[str], out: Path) -> dict[str, Path]:
    """Export every filter in ``formats`` (``daof.export``); name -> its directory."""
    from daof.export import export_filter

    directories = {}
    for name, f in filters.items():
        directories[name] = out / name.split()[0]
        start = time.perf_counter()
        export_filter(f, directories[name], formats)
        print(f"exported {name} as {','.join(formats)} in {time.perf_counter() - start:.0f} s ({load()})", flush=True)
    return directories


def paths_on(data, filters: dict, directories: dict, formats: list[str]) -> dict:
    """(filter, path) -> function streaming ``data`` through it: eager and every exported format."""
    from daof.export import load_step, read_contract, trajectory

    signals = (data["measurement"], data["control"], data["prev_control"])
    paths = {}
    for name, f in filters.items():
        paths[(name, "eager")] = lambda f=f: f.run_streaming(data)
        info = read_contract(directories[name])
        for fmt in formats:
            paths[(name, fmt)] = trajectory(load_step(directories[name], fmt), info, *signals)
    return paths


def compare_exported(filters: dict, system, formats: list[str], passes: int, batch: int) -> None:
    """The side-by-side table (batch 1) and the batched throughput of eager and exported paths, with the UKF."""
    one = system.simulate(1, 500, seed=20261122)
    many = system.simulate(batch, 100, seed=20261123)
    with tempfile.TemporaryDirectory() as tmp:
        directories = export_all(filters, formats, Path(tmp))
        paths = paths_on(one, filters, directories, formats)
        ukf = UKF(system)
        paths[("UKF", "eager")] = lambda: ukf.run_streaming(one)
        print(f"timing {len(paths)} paths × {passes} passes at batch 1 ({load()})", flush=True)
        times = interleaved(paths, passes, one.shape[1])
        ukf_median = statistics.median(times[("UKF", "eager")])
        print(f"\nbatch 1, one thread, 500 steps, {passes} interleaved passes ({load()} after)")
        print("| filter | path | µs per estimate: median | 25–75 % | × eager | UKF ÷ this |\n|---|---|---|---|---|---|")
        for (name, path), values in times.items():
            q1, q2, q3 = quartiles(values)
            eager = statistics.median(times[(name, "eager")])
            row = f"| {name} | {path} | {1e6 * q2:.1f} | {1e6 * q1:.1f}–{1e6 * q3:.1f} | {q2 / eager:.2f} | "
            print(row + f"{ukf_median / q2:.1f} |")

        rates = interleaved(paths_on(many, filters, directories, formats), max(3, passes // 3), batch * many.shape[1])
        print(f"\nbatched throughput: {batch} runs × {many.shape[1]} steps, one thread ({load()} after)")
        print("| filter | path | estimates per second (median) | × eager |\n|---|---|---|---|")
        for (name, path), values in rates.items():
            median = statistics.median(values)
            print(f"| {name} | {path} | {1 / median:,.0f} | {statistics.median(rates[(name, 'eager')]) / median:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--checkpoint", action="append", default=[], help="a trained filter (repeatable)")
    parser.add_argument("--export", default="", help="also time the exported steps: formats among torch,aoti,onnx")
    parser.add_argument("--passes", type=int, default=15, help="interleaved passes (with --export)")
    parser.add_argument("--batch", type=int, default=256, help="runs at once for the throughput (with --export)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    system = make_system("veh2dof")
    filters = {path: load_filter(path, system) for path in args.checkpoint} or fresh_filters(system, args.window)
    print(f"torch {torch.__version__}, threads {args.threads}, {platform.machine()}, {os.cpu_count()} CPUs, {load()}")
    if args.export:
        compare_exported(filters, system, [fmt.strip() for fmt in args.export.split(",")], args.passes, args.batch)
        return
    data = system.simulate(1, 500, seed=20261122)
    filters |= {"UKF": UKF(system), "EKF": EKF(system)}
    print("| filter | cost per estimate [ms] |\n|---|---|")
    for name, filt in filters.items():
        print(f"| {name} | {cost_per_estimate(filt, data):.3f} |")


if __name__ == "__main__":
    main()
