"""Computational cost of a filter, measured the way the protocol defines it.

Cost per estimate: wall time of one filter update for one trajectory (batch 1), streaming step
by step through the filter's ``run_streaming`` loop, after a warm-up, with a stated torch thread
count; measured by ``torch.utils.benchmark.Timer``. Throughput: estimates per second when the
filter runs all runs of the study at once.
"""

from __future__ import annotations

import time

import torch
from tensordict import TensorDictBase
from torch.utils.benchmark import Timer

__all__ = ["cost_per_estimate", "throughput", "threads"]


class threads:
    """Context manager that sets torch's intra-op thread count and restores it."""

    def __init__(self, count: int):
        self.count = int(count)

    def __enter__(self):
        self.saved = torch.get_num_threads()
        torch.set_num_threads(self.count)
        return self

    def __exit__(self, *exc):
        torch.set_num_threads(self.saved)


def cost_per_estimate(
    filt, data: TensorDictBase, warmup_steps: int = 50, min_seconds: float = 1.0, num_threads: int | None = None
) -> float:
    """Milliseconds per estimate at batch 1 (first run of ``data``): median over passes through all its steps.

    After a warm-up on the first ``warmup_steps`` steps, ``torch.utils.benchmark.Timer.blocked_autorange``
    streams the run through ``filt.run_streaming`` for at least ``min_seconds`` (after untimed passes
    that size its blocks of passes) and takes the median time of a pass. ``num_threads``: torch's intra-op
    thread count while timing (the Timer sets and restores it); by default the current one.
    """
    one = data[:1]
    filt.run_streaming(one[:, : min(warmup_steps, one.shape[1])])
    count = torch.get_num_threads() if num_threads is None else int(num_threads)
    timer = Timer("filt.run_streaming(one)", globals={"filt": filt, "one": one}, num_threads=count)
    return 1e3 * timer.blocked_autorange(min_run_time=min_seconds).median / one.shape[1]


def throughput(filt, data: TensorDictBase, with_std: bool = False):
    """(estimates per second at batch = runs, the estimates, their std, wall seconds) from one full run.

    ``with_std``: the run is ``run_with_std`` where the filter has one; the std is None otherwise.
    Timed by hand rather than with ``torch.utils.benchmark.Timer``: the study needs the estimates
    of this very run, and a Timer would run the whole study's filtering more than once.
    """
    start = time.perf_counter()
    run_with_std = getattr(filt, "run_with_std", None) if with_std else None
    estimates, std = run_with_std(data) if run_with_std is not None else (filt.run(data), None)
    wall = time.perf_counter() - start
    return data.numel() / wall, estimates, std, wall
