"""Train the supervised-learning filter (SLF) by regression on the true state.

SLF is the paper's learned baseline: the same network and input window as the DAOF policy, but
open loop (measurements and controls only) and fitted by least squares to x_t on simulated data.
The loss is the DAOF cost ‖x_t − x̂_t‖²_W with the env's default weights, so both learners
optimise the same error measure. Each "batch" is a fresh set of simulated episodes (seeded from
the run's seed and the batch index, so a resumed run sees the same data). With ``dropout`` in the
config, measurement entries of each batch go missing at random (``training_dropout_mask``, drawn
from a stream of its own, independent of the simulation's noise) and are filled as at run time, so
the SLF learns to filter through gaps (with ``network.missing_mask`` it also sees where they are).
"""

from __future__ import annotations

import numpy as np
import torch
from omegaconf import DictConfig
from torchrl._utils import timeit

from daof.envs.gaps import training_dropout_mask
from daof.train.base import FilterTrainer

__all__ = ["SLFTrainer", "gap_seed"]


def gap_seed(simulation_seed: int) -> int:
    """Seed of a batch's training gaps: a stream independent of the one ``simulate`` draws from.

    Seeding both with the same number would make the gap pattern a function of the noise draws.
    """
    return int(np.random.SeedSequence([int(simulation_seed), 1]).generate_state(1, np.uint64)[0] >> 1)


class SimulatedBatchTrainer(FilterTrainer):
    """Supervised training on batches of fresh simulated episodes (the SLF's, KalmanNet's): Adam, the
    env's default loss weights W = 1/(n·error_scale²), and a batch counter that seeds each batch."""

    def __init__(self, cfg: DictConfig):
        super().__init__(cfg)
        self.system.to(self.device)
        o = cfg.optim
        self.optim = torch.optim.Adam(self.filter.parameters(), lr=float(o.lr), weight_decay=float(o.weight_decay))
        s = self.system
        self.weights = 1.0 / (s.state_dim * s.error_scale**2)
        self.batches = 0

    def extra_state(self) -> dict:
        return {"optim": self.optim.state_dict(), "batches": self.batches}

    def load_extra_state(self, blob: dict) -> None:
        self.optim.load_state_dict(blob["optim"])
        self.batches = blob["batches"]

    def batch_seed(self) -> int:
        """Simulation seed of the next batch: from the run's seed and the batch index."""
        return int(self.cfg.seeds.train) * 1_000_003 + self.batches


class SLFTrainer(SimulatedBatchTrainer):
    """Regression of x_t on the open-loop window; ``train()`` runs (or resumes) it."""

    kinds = ("SLF",)

    def _dataset(self) -> tuple[torch.Tensor, torch.Tensor]:
        """One batch of fresh episodes as (windows [M, N·F], targets [M, n])."""
        c = self.cfg.collector
        seed = self.batch_seed()
        data = self.system.simulate(int(c.env_batch), int(c.episode_steps), seed, device=self.device)
        y = data["measurement"]
        if any(self.training_gaps):
            generator = torch.Generator().manual_seed(gap_seed(seed))
            mask = training_dropout_mask(tuple(y.shape), *self.training_gaps, self.system.dt, generator)
            y = y.masked_fill(mask.to(self.device), float("nan"))
        frames = self.filter.open_loop_frames(y, data["control"], data["prev_control"])
        windows = self.filter.layout.sliding_windows(frames)
        return windows.flatten(0, 1), data["state"].flatten(0, 1)

    def train(self) -> dict:
        """Fit on fresh simulated batches until ``collector.total_frames`` samples were seen."""
        total = int(self.cfg.collector.total_frames)
        bar = self.start(total)
        batch_size = int(self.cfg.optim.batch_size)
        epochs = int(self.cfg.optim.epochs_per_batch)
        try:
            while self.frames < total:
                with timeit("collect"):
                    windows, targets = self._dataset()
                for group in self.optim.param_groups:  # optim.lr_final: a cosine over the budget
                    group["lr"] = float(self.cfg.optim.lr) * self.lr_factor()
                with timeit("update"):
                    for _ in range(epochs):
                        order = torch.randperm(windows.shape[0]).to(self.device)
                        for idx in order.split(batch_size):
                            estimate = self.filter.estimate(windows[idx])
                            loss = ((estimate - targets[idx]).pow(2) * self.weights).sum(-1).mean()
                            self.optim.zero_grad(set_to_none=True)
                            loss.backward()
                            self.optim.step()
                            self.updates += 1
                self.batches += 1
                self.frames += windows.shape[0]
                self.after_batch(bar, windows.shape[0], {"train/loss": loss.item()}, total)
        finally:
            bar.close()
        return self.finish()
