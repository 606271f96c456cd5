"""How much room does `mismatch` leave a model-free filter? A PF told each run's true μ and B.

    .venv/bin/python diagnostics/mismatch_bound.py \
        --study runs/experiment1/paper/mismatch/study --figure docs/results/experiment1-mismatch/rmse_vs_mu.png

In the `mismatch` scenario every run has its own road friction μ ~ U[0.7, 1.0] and tyre shape
B ~ U[8, 12]; the model-based filters keep the nominal μ = 0.9, B = 10. A bootstrap PF that is
given each run's true μ and B (and every other part of the true model) is near-optimal for that
run, so no filter that must infer μ and B from the data can beat it on average: its RMSE is the
floor. A PF on the state (β, r, μ, B), μ and B static and drawn from the scenario's prior
(``daof.filters.JointParameterPF``, the study's PF-joint), is the Bayes filter of the scenario
itself: told nothing about the run, like a learned filter, it infers μ and B as it goes. The gap
between the nominal-model PF-oracle and these two is what a filter can win by not trusting the
nominal model.

It prints both (each at two particle counts, to show convergence) beside the study's filters
(read from the study's cache of estimates, ``--study``), their RMSE per band of true μ, and their
RMSE on the runs whose side slip leaves the range of the 100-step training episodes; with
``--figure`` it plots per-run RMSE against the true μ.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from daof.envs import make_system
from daof.envs.vehicle2dof import Vehicle2DOF

from daof.evaluate.metrics import per_run_rmse, pooled_rmse
from daof.filters import JointParameterPF, ParticleFilter
from daof.io import safe_load


class KnownParameterVeh2DOF(Vehicle2DOF):
    """veh2dof whose model ``f``/``g`` use each run's true μ and B (``mu``, ``B``: ``[runs]``).

    Only for filters that keep the run axis first (the PF's particles are ``[runs, N, 2]``).
    """

    def __init__(self, mu: torch.Tensor, B: torch.Tensor):
        super().__init__(scenario="mismatch")
        self.mu, self.B = mu, B

    def _per_run(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        shape = (-1,) + (1,) * (x.dim() - 2)  # [runs] -> [runs, 1, ...] against x's middle axes
        return {"mu": self.mu.view(shape).to(x), "B": self.B.view(shape).to(x)}

    def f(self, x, u):
        return self.f_with(x, u, self._per_run(x))

    def g(self, x, u):
        return self.g_with(x, u, self._per_run(x))


def fmt(values) -> str:
    return " / ".join(f"{v:.5f}" for v in values)


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=20261122, help="the study's evaluation seed")
    parser.add_argument("--particles", type=int, nargs="+", default=[10000, 20000])
    parser.add_argument("--joint-particles", type=int, nargs="*", default=[20000, 40000])
    parser.add_argument("--train-runs", type=int, default=3200, help="episodes for the |β| range")
    parser.add_argument("--train-steps", type=int, default=100, help="the recipes' env.episode_steps")
    parser.add_argument("--study", type=Path, help="a mismatch study's cache dir")
    parser.add_argument("--figure", type=Path, help="write per-run RMSE against the true μ here")
    args = parser.parse_args()

    system = make_system("veh2dof", scenario="mismatch")
    data = system.simulate(args.runs, args.steps, args.seed)
    # simulate draws each run's parameters first from the seeded generator: the same draw again
    params = system.reset_episode(args.runs, torch.Generator().manual_seed(args.seed))["params"]
    mu, B = params["mu"], params["B"]
    truth = data["state"]

    estimates: dict[str, torch.Tensor] = {}
    for n in args.particles:
        pf = ParticleFilter(KnownParameterVeh2DOF(mu, B), num_particles=n, max_elements=args.runs * n)
        start = time.perf_counter()
        estimates[f"PF, true μ and B ({n:,})"] = pf.run(data).float()
        print(f"known-parameter PF with {n:,} particles: {time.perf_counter() - start:.0f} s", flush=True)
    for n in args.joint_particles:
        pf = JointParameterPF(system, num_particles=n, seed=0, max_elements=args.runs * n)  # one chunk
        start = time.perf_counter()
        estimates[f"PF, μ and B inferred ({n:,})"] = pf.run(data).float()
        print(f"joint-parameter PF with {n:,} particles: {time.perf_counter() - start:.0f} s", flush=True)
    if args.study is not None:
        for path in sorted(args.study.glob("*.pt")):
            if "@" in path.stem or "N=" in path.stem:  # dropout studies and the window study
                continue
            blob = safe_load(path, map_location=None)
            key = {k: blob["key"].get(k) for k in ("scenario", "runs", "steps", "seed")}
            if key != {"scenario": "mismatch", "runs": args.runs, "steps": args.steps, "seed": args.seed}:
                raise SystemExit(f"{path} is a study of {key}, not of this data")
            estimates[path.stem] = blob["estimates"]

    floor = pooled_rmse(estimates[f"PF, true μ and B ({args.particles[-1]:,})"], truth)  # the most particles
    bands = [(0.7, 0.775), (0.775, 0.85), (0.85, 0.925), (0.925, 1.0)]
    in_band = [(mu >= lo) & (mu < hi if hi < 1.0 else mu <= hi) for lo, hi in bands]
    names = ", ".join(system.state_names)
    print(f"\nveh2dof mismatch: {args.runs} runs x {args.steps} steps, seed {args.seed}; RMSE [{names}]")
    header = " | ".join(f"μ ∈ [{lo}, {hi}) ({int(m.sum())} runs)" for (lo, hi), m in zip(bands, in_band))
    print(f"| filter | RMSE | ratio to the floor | {header} |")
    print("|---|---|---|" + "---|" * len(bands))
    for name, est in estimates.items():
        rmse = pooled_rmse(est, truth)
        per_band = " | ".join(fmt(pooled_rmse(est[m], truth[m])) for m in in_band)
        print(f"| {name} | {fmt(rmse)} | {fmt(rmse / floor)} | {per_band} |")

    # where the learned filters have no data: |β| beyond the 99.9 % quantile of training episodes
    train = system.simulate(args.train_runs, args.train_steps, seed=1)["state"][..., 0].abs()
    limit = torch.quantile(train.flatten().double(), 0.999).item()
    outside = truth[..., 0].abs() > limit  # [runs, steps]
    runs_outside = outside.any(1)
    print(
        f"\n|β| beyond {limit:.3f} rad (the 99.9 % quantile of {args.train_runs} x {args.train_steps}-step "
        f"training-like episodes): {int(outside.sum())} of {outside.numel()} steps, in {int(runs_outside.sum())} runs "
        f"(true μ {', '.join(f'{m:.3f}' for m in mu[runs_outside].tolist())})"
    )
    print("| filter | RMSE, runs that stay inside | RMSE, runs that leave it |\n|---|---|---|")
    for name, est in estimates.items():
        inside, leave = (pooled_rmse(est[m], truth[m]) for m in (~runs_outside, runs_outside))
        print(f"| {name} | {fmt(inside)} | {fmt(leave)} |")

    if args.figure is not None:
        plot(estimates, truth, mu, system, args.figure)
        print(f"\nfigure: {args.figure}")


def plot(estimates: dict[str, torch.Tensor], truth: torch.Tensor, mu: torch.Tensor, system, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # the PFs with the most particles of each kind
    bayes = list({n.split(" (")[0]: n for n in estimates if n.startswith("PF, ")}.values())
    shown = [n for n in ("UKF", "PF-oracle", "SLF", "DAOF-v2") if n in estimates] + bayes
    fig, axes = plt.subplots(1, system.state_dim, figsize=(6 * system.state_dim, 4.2), constrained_layout=True)
    for i, ax in enumerate(axes):
        for name in shown:
            ax.scatter(mu.numpy(), per_run_rmse(estimates[name], truth)[:, i].numpy(), s=12, label=name, alpha=0.8)
        ax.axvline(0.9, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("true road friction μ of the run (nominal model: 0.9)")
        ax.set_ylabel(f"per-run RMSE {system.state_names[i]} [{system.state_units[i]}]")
        ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle("veh2dof mismatch: per-run RMSE against the run's true μ")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
