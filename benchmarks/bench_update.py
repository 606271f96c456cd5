"""One DSAC-T update of a DAOF training against TorchRL's ``SACLoss`` update on the same networks and batch.

    .venv/bin/python benchmarks/bench_update.py                      # DAOF-v1 veh2dof default, eager
    .venv/bin/python benchmarks/bench_update.py --compile            # eager and compiled, interleaved
    .venv/bin/python benchmarks/bench_update.py --override filter=daof_v2 --override loss.gamma=0.5

Builds the trainer of ``daof.train.config.compose_config(overrides)`` (default DAOF-v1 on veh2dof:
N = 20, 3 × 256 GELU, batch 256, γ = 0), fills its replay buffer with the initial policy's
transitions and samples one batch. "DSAC-T" is ``DSACTTrainer.update_on`` (the trainer's own update:
critics every update, actor, α and targets every ``loss.delay``-th), timed per update over one
cycle of ``delay`` updates. "SAC" is TorchRL's ``SACLoss`` (actor, critics and α every update, as
its sota-implementation steps them) on a copy of the same actor and critics, the critic's mean μ
as its Q, with the same Adam optimisers. Both run in one interleaved loop; ``--compile`` adds both
updates under TorchRL's ``compile_with_warmup``. Prints wall and thread-CPU medians in ms (the CPU
time is the steadier one on a shared machine) and the DSAC-T / SAC ratios as one JSON line.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl import compile_with_warmup
from torchrl.objectives import SACLoss, SoftUpdate

from daof.train.config import compose_config
from daof.train.dsac import DSACTTrainer
from daof.train.policies import stochastic_actor


def filled_trainer(overrides: list[str]) -> DSACTTrainer:
    """The trainer of ``overrides`` with ``warmup_frames`` of the initial policy in its buffer."""
    cfg = compose_config([*overrides, "logger.backend=", f"output_dir={tempfile.mkdtemp()}"])
    trainer = DSACTTrainer(cfg)
    collector = trainer._make_collector(int(cfg.collector.warmup_frames))
    for batch in collector:
        trainer.buffer.extend(trainer.to_replay(batch))
    collector.shutdown()
    return trainer


def sac_update(trainer: DSACTTrainer):
    """TorchRL's SAC update on copies of the trainer's actor and critic: (update function, loss)."""
    filter = copy.deepcopy(trainer.filter)
    critic = copy.deepcopy(trainer.critic)
    critic.module._actor = [filter]
    mean_only = TensorDictModule(lambda q: q[..., :1], ["state_action_value"], ["state_action_value"])
    loss = SACLoss(stochastic_actor(filter), TensorDictSequential(critic, mean_only), num_qvalue_nets=2)
    loss.set_keys(action=filter.action_key)
    loss.make_value_estimator(gamma=float(trainer.cfg.loss.gamma))
    updater = SoftUpdate(loss, tau=float(trainer.cfg.loss.tau))
    optims = [
        torch.optim.Adam(list(loss.qvalue_network_params.flatten_keys().values()), lr=1e-4),
        torch.optim.Adam(list(loss.actor_network_params.flatten_keys().values()), lr=1e-4),
        torch.optim.Adam([loss.log_alpha], lr=1e-3),
    ]

    def update(batch):
        out = loss(batch)
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
        for optim in optims:
            optim.step()
            optim.zero_grad(set_to_none=True)
        updater.step()
        return out

    return update


def timed(fn) -> tuple[float, float]:
    """(wall ms, thread-CPU ms) of one call."""
    wall, cpu = time.perf_counter(), time.thread_time()
    fn()
    return 1e3 * (time.perf_counter() - wall), 1e3 * (time.thread_time() - cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--override", action="append", default=[], help="a training config override (repeatable)")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--compile", action="store_true", help="also time both updates compiled")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    trainer = filled_trainer(args.override or ["filter=daof_v1", "system=veh2dof"])
    batch = trainer.buffer.sample()
    delay = int(trainer.cfg.loss.delay)

    def ours(update):  # one cycle of ``delay`` updates, as the trainer runs them
        return lambda: [update(batch, k == 0) for k in range(delay)]

    def sac(update):
        return lambda: [update(batch) for _ in range(delay)]

    variants = {
        "dsac_t": ours(trainer.update_on),
        "dsac_t_full": lambda: [trainer.update_on(batch, True) for _ in range(delay)],  # actor every update
        "sac": sac(sac_update(trainer)),
    }
    if args.compile:
        started = time.perf_counter()
        variants["dsac_t_compiled"] = ours(compile_with_warmup(trainer.update_on, warmup=1))
        variants["sac_compiled"] = sac(compile_with_warmup(sac_update(trainer), warmup=1))
        for fn in list(variants.values())[3:]:
            for _ in range(3):  # warm-up call, compile, and a recompile for the other ``delayed``
                fn()
        compile_s = time.perf_counter() - started
    for fn in variants.values():
        fn()
    times = {name: ([], []) for name in variants}
    for r in range(args.repeats):  # interleaved, the order alternating
        for name in list(variants)[:: 1 if r % 2 == 0 else -1]:
            wall, cpu = timed(variants[name])
            times[name][0].append(wall / delay)
            times[name][1].append(cpu / delay)
    result = {
        "bench": "update",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        + ("+dirty" if subprocess.run(["git", "diff", "--quiet", "HEAD"]).returncode else ""),
        "overrides": args.override,
        "torch": torch.__version__,
        "threads": args.threads,
        "cpu": platform.processor() or platform.machine(),
        "load": os.getloadavg()[0],
        "ms_per_update_wall": {k: round(statistics.median(v[0]), 2) for k, v in times.items()},
        "ms_per_update_cpu": {k: round(statistics.median(v[1]), 2) for k, v in times.items()},
    }
    for key in ("wall", "cpu"):
        ms = result[f"ms_per_update_{key}"]
        result[f"ratio_{key}"] = {"eager": round(ms["dsac_t"] / ms["sac"], 3)}
        if args.compile:
            result[f"ratio_{key}"]["compiled"] = round(ms["dsac_t_compiled"] / ms["sac_compiled"], 3)
    if args.compile:
        result["compile_s"] = round(compile_s, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
