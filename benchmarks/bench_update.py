"""Cost of one DSAC-T gradient update of a DAOF training run, by part, for γ = 0 and γ > 0.

    .venv/bin/python benchmarks/bench_update.py --threads 1
    .venv/bin/python benchmarks/bench_update.py --config-path recipes/linear --override version=v2

Builds the trainer of a recipe config (default: ``recipes/veh2dof/config.yaml``, DAOF-v1, N = 20,
3 × 256 GELU, batch 256), fills its replay buffer with the initial policy's transitions, and times
the critic targets, the critic loss with its backward, the actor loss, and a whole update
(``DSACTTrainer._update``: the actor's part runs every ``loss.delay``-th update), median over
repeats. With γ = 0 the targets are the reward and the target actor and critics are not evaluated.
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
from hydra import compose, initialize_config_dir

from daof.train.dsac import DSACTTrainer

ROOT = Path(__file__).resolve().parents[1]


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def time_update(trainer: DSACTTrainer, repeats: int) -> tuple[float, float, float, float]:
    """Median ms of the targets, critic loss + backward, actor loss + backward and a whole update."""
    collector = trainer._make_collector(int(trainer.cfg.collector.warmup_frames))
    for batch in collector:
        trainer.buffer.extend(trainer.to_replay(batch))
    collector.shutdown()
    batch, loss = trainer.buffer.sample(), trainer.loss
    return (
        median_ms(lambda: loss.compute_targets(batch), repeats),
        median_ms(lambda: loss.qvalue_loss(batch)[0].backward(), repeats),
        median_ms(lambda: loss.actor_loss(batch)[0].backward(), repeats),
        median_ms(trainer._update, repeats),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--config-path", default="recipes/veh2dof")
    parser.add_argument("--override", action="append", default=[], help="a config override key=value (repeatable)")
    parser.add_argument("--gammas", default="0,0.5")
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"# DSAC-T update cost, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {args.threads} thread(s)"
    )
    print("| γ | targets [ms] | critic loss + backward [ms] | actor loss + backward [ms] | update [ms] |")
    print("|---|---|---|---|---|")
    for gamma in [float(g) for g in args.gammas.split(",")]:
        with initialize_config_dir(str(ROOT / args.config_path), version_base="1.3"):
            overrides = [*args.override, f"loss.gamma={gamma}", "logger.backend=", f"output_dir={tempfile.mkdtemp()}"]
            cfg = compose(config_name="config", overrides=overrides)
        targets, critic, actor, update = time_update(DSACTTrainer(cfg), args.repeats)
        print(f"| {gamma:g} | {targets:.2f} | {critic:.1f} | {actor:.1f} | {update:.1f} |")


if __name__ == "__main__":
    main()
