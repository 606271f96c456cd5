"""Validation of learned filters during training: RMSE per state and learning curves."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import torch

from daof.io import atomic_write_text

__all__ = ["rmse_per_state", "write_curve_csv", "plot_learning_curve"]


def _thousands(x, _pos=None) -> str:
    """Tick label for sample counts: 250000 -> 250k."""
    return f"{x / 1000:g}k" if abs(x) >= 1000 else f"{x:g}"


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
    history: list[dict], state_names, path: str | Path, title: str, references: dict | None = None
) -> None:
    """Validation RMSE per state against environment steps (one panel per state)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    frames = [h["frames"] for h in history]
    fig, axes = plt.subplots(1, len(state_names), figsize=(4.5 * len(state_names), 3.4), squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[0], state_names)):
        ax.plot(frames, [h[f"rmse_{name}"] for h in history], marker=".", label="validation")
        for label, values in (references or {}).items():
            ax.axhline(values[i], ls="--", lw=1, color="gray")
            ax.annotate(label, (frames[0], values[i]), fontsize=7, color="gray", va="bottom")
        ax.set_yscale("log")
        ax.xaxis.set_major_formatter(_thousands)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(f"RMSE {name}")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
