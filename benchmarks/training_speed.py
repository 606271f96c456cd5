"""Training speed on one device, as one JSON line: DSAC-T updates/s, collected env frames/s, 14-DOF filter steps/s.

    .venv/bin/python benchmarks/training_speed.py --device cpu
    .venv/bin/python benchmarks/training_speed.py --device cuda          # on a GPU machine

``updates_per_s``: ``DSACTTrainer._update`` (a replay sample and one gradient update, the actor every
``loss.delay``-th) of the training config (default DAOF-v1 on veh2dof) on ``--device``, after the
buffer holds ``collector.warmup_frames`` of the initial policy. ``env_frames_per_s``: the training
collector (stochastic policy, env and window) at the config's ``collector.env_batch`` (``--env-batch``
changes it). ``veh14dof_steps_per_s``: filter steps (runs × steps / s) of the veh14dof simulator's
``advance`` at batch ``--sim-batch`` (1024). Every timed stretch ends with a device synchronisation.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import daof.envs as envs
import torch

from daof.device import resolve_device
from daof.train.config import compose_config
from daof.train.dsac import DSACTTrainer


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rate(fn, count: int, device: torch.device) -> float:
    """``count`` / seconds of one call of ``fn`` (synchronised)."""
    sync(device)
    start = time.perf_counter()
    fn()
    sync(device)
    return count / (time.perf_counter() - start)


def training_rates(overrides: list[str], updates: int, batches: int) -> tuple[float, float]:
    """(env frames/s of the collector, updates/s) of one training config."""
    cfg = compose_config([*overrides, "logger.backend=", f"output_dir={tempfile.mkdtemp()}"])
    trainer = DSACTTrainer(cfg)
    c = cfg.collector
    per_batch = int(c.env_batch) * int(c.steps_per_batch)
    warm = max(int(c.warmup_frames), int(cfg.optim.batch_size))
    collector = trainer._make_collector(warm + (batches + 1) * per_batch)
    it = iter(collector)
    while len(trainer.buffer) < warm:
        trainer.buffer.extend(trainer.to_replay(next(it)))

    def collect():
        for _ in range(batches):
            trainer.buffer.extend(trainer.to_replay(next(it)))

    frames = rate(collect, batches * per_batch, trainer.device)
    collector.shutdown()
    for _ in range(3):  # warm-up (lazy inits, allocator)
        trainer._update()

    def update():
        for _ in range(updates):
            trainer._update()

    return frames, rate(update, updates, trainer.device)


def simulator_rate(device: torch.device, runs: int, steps: int) -> float:
    """veh14dof filter steps per second of ``advance`` at batch ``runs``."""
    system = envs.make_system("veh14dof").to(device)
    generator = torch.Generator(device=device).manual_seed(0)
    with torch.inference_mode():
        sim = system.reset_episode(runs, generator, device)
        for _ in range(2):
            sim, _ = system.advance(sim, generator)

        def advance():
            nonlocal sim
            for _ in range(steps):
                sim, _ = system.advance(sim, generator)

        return rate(advance, runs * steps, device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu | cuda | cuda:<k> | auto")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--override", action="append", default=[], help="a training config override (repeatable)")
    parser.add_argument("--env-batch", type=int, default=None, help="collector.env_batch (default: the config's)")
    parser.add_argument("--updates", type=int, default=200)
    parser.add_argument("--batches", type=int, default=5, help="collected batches timed")
    parser.add_argument("--sim-batch", type=int, default=1024)
    parser.add_argument("--sim-steps", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    overrides = [*(args.override or ["filter=daof_v1", "system=veh2dof"]), f"device={device}"]
    overrides.append(f"threads={args.threads}")
    if args.env_batch is not None:
        overrides.append(f"collector.env_batch={args.env_batch}")
    frames, updates = training_rates(overrides, args.updates, args.batches)
    steps = simulator_rate(device, args.sim_batch, args.sim_steps)
    result = {
        "bench": "training_speed",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "torch": torch.__version__,
        "threads": args.threads,
        "load": os.getloadavg()[0],
        "overrides": overrides,
        "updates_per_s": round(updates, 1),
        "env_frames_per_s": round(frames),
        "veh14dof_steps_per_s": round(steps),
        "veh14dof_batch": args.sim_batch,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
