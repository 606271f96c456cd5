"""Does a particle filter converge? RMSE and wall time of the bootstrap PF and the proposal PF at several counts.

    OMP_NUM_THREADS=1 python diagnostics/reference_convergence.py bearing --runs 20 --steps 30
    OMP_NUM_THREADS=1 python diagnostics/reference_convergence.py veh2dof --runs 20 --steps 500
    OMP_NUM_THREADS=1 python diagnostics/reference_convergence.py veh2dof --runs 5 --steps 100 --timing 2000

``bearing`` is the bearing-only tracking system of ``tests/test_reference_check.py`` (two precise bearing
sensors), where the bootstrap PF's weights degenerate; ``veh2dof`` is the nominal 2-DOF vehicle. Every
filter runs on the same simulated data (seed 20261122) beside a UKF; each count runs with two seeds, so
the spread between them shows the Monte Carlo error left at that count. Wall times are of one process
on a shared machine: compare them within one run. ``--timing N`` instead times both PFs with N
particles side by side, alternating, five times each, and prints the best of each and their ratio.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import time
from pathlib import Path

import torch
from daof.envs import make_system

from daof.evaluate.metrics import pooled_rmse
from daof.filters import UKF, ParticleFilter, ProposalParticleFilter

COUNTS = {
    "bearing": {"PF": [1000, 10000, 20000, 40000], "PF-proposal": [100, 1000, 2000, 4000]},
    "veh2dof": {"PF": [10000, 20000], "PF-proposal": [1000, 2000, 4000]},
}


def bearing_system():
    """The test file's ``BearingTracking`` (defined there, as a user would, outside daof)."""
    path = Path(__file__).resolve().parents[1] / "tests" / "test_reference_check.py"
    spec = importlib.util.spec_from_file_location("test_reference_check", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.BearingTracking()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("system", choices=sorted(COUNTS))
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--timing", type=int, default=0, help="time both PFs at this particle count instead")
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = bearing_system() if args.system == "bearing" else make_system("veh2dof")
    data = system.simulate(args.runs, args.steps, 20261122)
    if args.timing:
        timing(system, data, args.timing)
        return
    filters = [("UKF", UKF(system))]
    classes = {"PF": ParticleFilter, "PF-proposal": ProposalParticleFilter}
    for name, counts in COUNTS[args.system].items():
        filters += [(f"{name} N={n} seed={s}", classes[name](system, n, seed=s)) for n in counts for s in (1, 2)]
    names = " / ".join(system.state_names)
    print(f"{args.system}: {args.runs} runs x {args.steps} steps; RMSE {names}; wall time")
    for label, filt in filters:
        start = time.perf_counter()
        rmse = pooled_rmse(filt.run(data), data["state"]).tolist()
        wall = time.perf_counter() - start
        print(f"{label:28s} " + " / ".join(f"{v:.4f}" for v in rmse) + f"   {wall:7.1f} s", flush=True)


def timing(system, data, particles: int, repeats: int = 5) -> None:
    """Best-of-``repeats`` wall time of the bootstrap and the proposal PF, alternating, and their ratio."""
    best = {"PF": math.inf, "PF-proposal": math.inf}
    for _ in range(repeats):
        for name, cls in (("PF", ParticleFilter), ("PF-proposal", ProposalParticleFilter)):
            start = time.perf_counter()
            cls(system, particles, seed=1).run(data)
            best[name] = min(best[name], time.perf_counter() - start)
    steps = data.numel() * particles
    for name, wall in best.items():
        print(f"{name:12s} N={particles}: {wall:.3f} s, {wall / steps * 1e9:.0f} ns per particle-step")
    print(f"proposal / bootstrap: {best['PF-proposal'] / best['PF']:.1f}x per particle")


if __name__ == "__main__":
    main()
