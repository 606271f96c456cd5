"""The protocol's accuracy metrics (shared/specs/benchmark.md, "Metrics")."""

from __future__ import annotations

import torch

__all__ = ["pooled_rmse", "per_run_rmse", "count_diverged", "paired_rmse_ratio"]


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


def paired_rmse_ratio(
    run_rmse: torch.Tensor, reference_run_rmse: torch.Tensor, *, draws: int = 4000, level: float = 0.95, seed: int = 0
) -> dict:
    """Pooled-RMSE ratio of a filter to a reference on the same runs, with a paired bootstrap interval.

    Both inputs are per-run RMSEs [runs, states] of equally long runs, so the pooled MSE is the
    mean of the per-run MSEs. Runs are resampled with replacement (the same runs for both
    filters: the comparison is paired) ``draws`` times; the interval is the percentile interval
    at ``level``. Returns per state: ``ratio``, ``low``, ``high`` and ``better_runs`` (runs where
    the filter's RMSE is below the reference's).
    """
    a, b = run_rmse.double().pow(2), reference_run_rmse.double().pow(2)
    if a.shape != b.shape or a.ndim != 2 or a.shape[0] < 2:
        shapes = f"{tuple(a.shape)}, {tuple(b.shape)}"
        raise ValueError(f"need per-run RMSEs [runs >= 2, states] of the same shape, got {shapes}")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    generator = torch.Generator().manual_seed(seed)
    index = torch.randint(a.shape[0], (draws, a.shape[0]), generator=generator)
    ratios = (a[index].mean(1) / b[index].mean(1)).sqrt()  # [draws, states]
    tail = (1 - level) / 2
    low, high = ratios.quantile(torch.tensor([tail, 1 - tail], dtype=ratios.dtype), dim=0)
    return {
        "ratio": (a.mean(0) / b.mean(0)).sqrt().tolist(),
        "low": low.tolist(),
        "high": high.tolist(),
        "better_runs": (a < b).sum(0).tolist(),
        "runs": a.shape[0],
        "level": level,
    }
