"""The protocol's accuracy metrics (shared/specs/benchmark.md, "Metrics")."""

from __future__ import annotations

import torch

__all__ = ["pooled_rmse", "per_run_rmse", "count_diverged"]


def _check(estimates: torch.Tensor, truth: torch.Tensor) -> None:
    if estimates.shape != truth.shape or estimates.ndim != 3:
        raise ValueError(
            f"estimates and truth must both be [runs, steps, states], got {tuple(estimates.shape)} "
            f"and {tuple(truth.shape)}"
        )


def pooled_rmse(estimates: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """sqrt of the mean over all runs and steps of the squared error, per state -> [states].

    Non-finite estimates stay in (a filter does not get to drop its failures): they make the
    RMSE non-finite.
    """
    _check(estimates, truth)
    return (estimates.double() - truth.double()).pow(2).mean((0, 1)).sqrt()


def per_run_rmse(estimates: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """RMSE of every run over its steps, per state -> [runs, states]."""
    _check(estimates, truth)
    return (estimates.double() - truth.double()).pow(2).mean(1).sqrt()


def count_diverged(run_rmse: torch.Tensor, oracle_rmse: torch.Tensor | None = None, factor: float = 10.0) -> int:
    """Runs whose RMSE is non-finite or, given the oracle's pooled RMSE, above ``factor``× it."""
    bad = ~torch.isfinite(run_rmse).all(-1)
    if oracle_rmse is not None:
        bad |= (run_rmse > factor * oracle_rmse.to(run_rmse)).any(-1)
    return int(bad.sum())
