"""The protocol's accuracy metrics (docs/design.md, "The benchmark protocol")."""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import bootstrap

__all__ = [
    "pooled_rmse",
    "per_run_rmse",
    "diverged_runs",
    "count_diverged",
    "paired_rmse_ratio",
    "calibration",
    "DIVERGENCE_FACTOR",
    "COVERAGE_SIGMAS",
    "GAUSSIAN_COVERAGE",
]


def _check(estimates: torch.Tensor, truth: torch.Tensor) -> None:
    if estimates.shape != truth.shape or estimates.ndim != 3:
        raise ValueError(
            f"estimates and truth must both be [runs, steps, states], got {tuple(estimates.shape)} "
            f"and {tuple(truth.shape)}"
        )


#: the interval whose coverage the study reports: ±2σ
COVERAGE_SIGMAS = 2.0
#: the share of a Gaussian within ±2σ of its mean, P(|z| ≤ 2) = erf(2/√2): what a calibrated std covers
GAUSSIAN_COVERAGE = 0.9544997361036416


def calibration(estimates: torch.Tensor, truth: torch.Tensor, std: torch.Tensor) -> dict[str, list]:
    """How well a filter's claimed error std matches its errors e = x̂ − x, per state, over every run and step.

    ``nees``: the mean of e_i² / σ_i² (the normalised estimation error squared of each state alone;
    1 for a calibrated std, above 1 overconfident, below 1 too cautious). ``coverage``: the share
    with |e_i| ≤ 2σ_i (``GAUSSIAN_COVERAGE`` = 95.45 % for calibrated Gaussian errors).
    ``excluded``: per state, the entries left out of both because e or σ is not finite or σ ≤ 0
    (a diverged run's NaN estimates, a collapsed std); counted, never a crash. A state with every
    entry excluded has NaN for both.
    """
    _check(estimates, truth)
    if std.shape != estimates.shape:
        shapes = f"{tuple(std.shape)} and {tuple(estimates.shape)}"
        raise ValueError(f"std and estimates must both be [runs, steps, states], got {shapes}")
    error = (estimates.double() - truth.double()).flatten(0, 1)
    sigma = std.double().flatten(0, 1)
    valid = torch.isfinite(error) & torch.isfinite(sigma) & (sigma > 0)
    count = valid.sum(0)
    z = torch.where(valid, error / torch.where(valid, sigma, 1.0), 0.0)
    nees = z.square().sum(0) / count
    covered = ((z.abs() <= COVERAGE_SIGMAS) & valid).sum(0) / count
    return {"nees": nees.tolist(), "coverage": covered.tolist(), "excluded": (~valid).sum(0).tolist()}


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


#: a run whose RMSE on some state is above this multiple of the reference's RMSE on that run has diverged
DIVERGENCE_FACTOR = 10.0


def diverged_runs(
    run_rmse: torch.Tensor,
    reference_rmse: torch.Tensor | None = None,
    factor: float = DIVERGENCE_FACTOR,
    implausible: torch.Tensor | None = None,
) -> torch.Tensor:
    """Which runs [runs] (bool) diverged: non-finite RMSE, RMSE above ``factor``× the reference's, or ``implausible``.

    ``run_rmse`` is [runs, states]; ``reference_rmse`` the reference's RMSE per run [runs, states]
    (or pooled, [states]); ``implausible`` a [runs] mask of runs with an estimate outside the
    system's plausible range (``StochasticSystem.diverged_runs``).
    """
    bad = ~torch.isfinite(run_rmse).all(-1)
    if reference_rmse is not None:
        bad |= (run_rmse > factor * reference_rmse.to(run_rmse)).any(-1)
    if implausible is not None:
        bad |= implausible.to(bad.device)
    return bad


def count_diverged(
    run_rmse: torch.Tensor, oracle_rmse: torch.Tensor | None = None, factor: float = DIVERGENCE_FACTOR
) -> int:
    """How many runs ``diverged_runs`` flags (non-finite, or above ``factor``× the oracle's RMSE)."""
    return int(diverged_runs(run_rmse, oracle_rmse, factor).sum())


def paired_rmse_ratio(
    run_rmse: torch.Tensor, reference_run_rmse: torch.Tensor, *, draws: int = 4000, level: float = 0.95, seed: int = 0
) -> dict:
    """Pooled-RMSE ratio of a filter to a reference on the same runs, with a paired bootstrap interval.

    Both inputs are per-run RMSEs [runs, states] of equally long runs, so the pooled MSE is the
    mean of the per-run MSEs. ``scipy.stats.bootstrap(paired=True, method="percentile")`` resamples
    the runs with replacement (the same runs for both filters: the comparison is paired) ``draws``
    times from ``numpy.random.default_rng(seed)``; the interval is the percentile interval at
    ``level``. Returns per state: ``ratio``, ``low``, ``high`` and ``better_runs`` (runs where the
    filter's RMSE is below the reference's).

    (Until issue 31 this was a hand-written torch bootstrap: the same statistic and interval, but
    another random stream, so interval ends moved within their Monte Carlo error, about 1e-3
    relatively on 20 veh2dof runs. scipy takes 1.5-2x its time, tens of ms per comparison.)
    """
    a, b = run_rmse.double().pow(2), reference_run_rmse.double().pow(2)
    if a.shape != b.shape or a.ndim != 2 or a.shape[0] < 2:
        shapes = f"{tuple(a.shape)}, {tuple(b.shape)}"
        raise ValueError(f"need per-run RMSEs [runs >= 2, states] of the same shape, got {shapes}")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    interval = bootstrap(
        (a.numpy(), b.numpy()),
        _pooled_ratio,
        n_resamples=draws,
        paired=True,
        vectorized=True,
        axis=0,
        confidence_level=level,
        method="percentile",
        rng=np.random.default_rng(seed),
    ).confidence_interval
    return {
        "ratio": (a.mean(0) / b.mean(0)).sqrt().tolist(),
        "low": np.atleast_1d(interval.low).tolist(),
        "high": np.atleast_1d(interval.high).tolist(),
        "better_runs": (a < b).sum(0).tolist(),
        "runs": a.shape[0],
        "level": level,
    }


def _pooled_ratio(mse: np.ndarray, reference_mse: np.ndarray, axis: int) -> np.ndarray:
    """sqrt of the ratio of mean per-run MSEs along ``axis`` (the bootstrap's statistic)."""
    return np.sqrt(mse.mean(axis) / reference_mse.mean(axis))
