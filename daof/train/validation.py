"""Validation of learned filters during training: RMSE per state and learning curves."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import torch

from daof.io import atomic_write_text

__all__ = ["rmse_per_state", "write_curve_csv", "plot_learning_curve"]


def rmse_per_state(estimates: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Pooled RMSE per state over runs and steps: sqrt(mean((x̂ − x)²)) -> [state_dim]."""
    if estimates.shape != truth.shape:
        raise ValueError(f"estimates {tuple(estimates.shape)} and truth {tuple(truth.shape)} differ in shape")
    return (estimates - truth).pow(2).flatten(0, -2).mean(0).sqrt()


def write_curve_csv(history: list[dict], path: str | Path) -> None:
    """Write the validation history (one dict per validation) as CSV."""
    if not history:
        return
    fh = io.StringIO()  # written whole, then renamed into place
    writer = csv.DictWriter(fh, fieldnames=list(history[0]))
    writer.writeheader()
    writer.writerows(history)
    atomic_write_text(path, fh.getvalue())


def plot_learning_curve(
    history: list[dict], state_names, path: str | Path, title: str, references: dict | None = None, *, name: str
) -> None:
    """Validation RMSE per state of filter ``name`` against environment steps (``daof.evaluate.figures``)."""
    from daof.evaluate.figures import plot_learning_curves

    if history:
        plot_learning_curves({name: history}, state_names, Path(path), references, title=title)
