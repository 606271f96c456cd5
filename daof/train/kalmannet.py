"""Train KalmanNet end to end: MSE over simulated sequences, back-propagation through time, Adam.

The authors' recipe (Revach et al., IEEE TSP 2022; github.com/KalmanNet/KalmanNet_TSP,
``Pipelines/Pipeline_EKF.py``): batches of labelled sequences filtered from x̂_0, the MSE of the
estimates against the true states, Adam with weight decay, the best validation checkpoint kept.
Here the data budget is counted like the SLF's: each "batch" is ``collector.env_batch`` fresh
episodes of ``collector.episode_steps`` steps (seeded from the run's seed and the batch index,
so a resumed run sees the same data), passed over ``optim.epochs_per_batch`` times in groups of
``optim.batch_size`` sequences. Each group is filtered from the start of its episodes and updated
every ``optim.bptt_steps`` steps (truncated BPTT: the recurrent state goes on, its gradient stops;
bptt_steps ≥ episode_steps is the authors' full BPTT). The loss is the SLF's: ‖x_t − x̂_t‖²_W with
the env's default weights W = 1/(n·error_scale²).
"""

from __future__ import annotations

import torch
from torchrl._utils import timeit

from daof.filters.learned.kalmannet import KalmanNetState
from daof.train.supervised import SimulatedBatchTrainer

__all__ = ["KalmanNetTrainer"]


class KalmanNetTrainer(SimulatedBatchTrainer):
    """MSE with (truncated) BPTT over fresh simulated sequences; ``train()`` runs (or resumes) it."""

    kinds = ("KalmanNet",)

    def _update(self, data, idx: torch.Tensor) -> float:
        """Filter the episodes ``idx`` from x̂_0, one Adam step per ``bptt_steps`` segment; the mean loss."""
        o = self.cfg.optim
        y, u_prev, u, x = (data[k][idx] for k in ("measurement", "prev_control", "control", "state"))
        state, losses = None, []
        for start in range(0, y.shape[1], int(o.bptt_steps)):
            part = slice(start, start + int(o.bptt_steps))
            estimate, state = self.filter.filter_sequence(y[:, part], u_prev[:, part], u[:, part], state)
            loss = ((estimate - x[:, part]).pow(2) * self.weights).sum(-1).mean()
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            if float(o.max_grad_norm) > 0:
                torch.nn.utils.clip_grad_norm_(self.filter.parameters(), float(o.max_grad_norm))
            self.optim.step()
            self.updates += 1
            state = KalmanNetState(*(v.detach() for v in state))
            losses.append(loss.item())
        return sum(losses) / len(losses)

    def train(self) -> dict:
        """Fit on fresh simulated batches until ``collector.total_frames`` steps were seen."""
        c, o = self.cfg.collector, self.cfg.optim
        total = int(c.total_frames)
        bar = self.start(total)
        try:
            while self.frames < total:
                with timeit("collect"):
                    data = self.system.simulate(int(c.env_batch), int(c.episode_steps), self.batch_seed())
                for group in self.optim.param_groups:  # optim.lr_final: a cosine over the budget
                    group["lr"] = float(o.lr) * self.lr_factor()
                with timeit("update"):
                    for _ in range(int(o.epochs_per_batch)):
                        for idx in torch.randperm(int(c.env_batch)).split(int(o.batch_size)):
                            loss = self._update(data, idx)
                self.batches += 1
                new = int(c.env_batch) * int(c.episode_steps)
                self.frames += new
                self.after_batch(bar, new, {"train/loss": loss}, total)
        finally:
            bar.close()
        return self.finish()
