"""Computational cost of a filter, measured the way the protocol defines it.

Cost per estimate: mean wall time of one filter update for one trajectory (batch 1), streaming
step by step through the filter's ``run_streaming`` loop, after a warm-up, with a stated torch thread
count. Throughput: estimates per second when the filter runs all runs of the study at once.
"""

from __future__ import annotations

import time

import torch
from tensordict import TensorDictBase

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


def cost_per_estimate(filt, data: TensorDictBase, warmup_steps: int = 50, min_seconds: float = 1.0) -> float:
    """Milliseconds per estimate at batch 1 (first run of ``data``), median of repeated passes."""
    one = data[:1]
    filt.run_streaming(one[:, : min(warmup_steps, one.shape[1])])
    steps = one.shape[1]
    samples = []
    spent = 0.0
    while spent < min_seconds or len(samples) < 3:
        start = time.perf_counter()
        filt.run_streaming(one)
        elapsed = time.perf_counter() - start
        samples.append(elapsed / steps)
        spent += elapsed
        if len(samples) >= 50:
            break
    samples.sort()
    return 1e3 * samples[len(samples) // 2]


def throughput(filt, data: TensorDictBase) -> tuple[float, torch.Tensor, float]:
    """(estimates per second at batch = runs, the estimates, wall seconds) from one full run."""
    start = time.perf_counter()
    estimates = filt.run(data)
    wall = time.perf_counter() - start
    return data.numel() / wall, estimates, wall
