"""The study's figures (PNG): one run's states and errors, per-run RMSE, learning curves, windows."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

__all__ = [
    "plot_one_run",
    "plot_one_run_state",
    "plot_per_run_boxes",
    "plot_learning_curves",
    "plot_scenario_rmse",
    "plot_window_study",
]


def _thousands(x, _pos=None) -> str:
    """Tick label for sample counts: 250000 -> 250k."""
    return f"{x / 1000:g}k" if abs(x) >= 1000 else f"{x:g}"


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_one_run(study, path: Path, run: int = 0, names=None) -> Path:
    """Estimated vs true state (top row) and error over time (bottom row), per state, all filters."""
    s = study.system
    names = names or list(study.estimates)
    truth = study.data["state"][run]
    t = torch.arange(1, truth.shape[0] + 1) * s.dt
    fig, axes = plt.subplots(2, s.state_dim, figsize=(6 * s.state_dim, 6.5), sharex=True, squeeze=False)
    for j, (state, unit) in enumerate(zip(s.state_names, s.state_units)):
        estimates = {name: study.estimates[name][run, :, j] for name in names}
        _state_and_error_panels(axes[0, j], axes[1, j], t, truth[:, j], estimates, f"{state} [{unit}]")
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"{s.name} ({s.scenario}), run {run}: estimates and errors")
    return _save(fig, path)


def _state_and_error_panels(top, bottom, t, truth, estimates: dict, label: str) -> None:
    """One state: true and estimated trajectories (top), estimation errors over time (bottom)."""
    top.plot(t, truth, color="black", lw=1.6, label="true")
    for name, est in estimates.items():
        top.plot(t, est, lw=0.9, label=name)
        bottom.plot(t, est - truth, lw=0.8, label=name)
    top.set_ylabel(label)
    bottom.set_ylabel(f"error {label}")
    bottom.set_xlabel("time [s]")
    bottom.axhline(0, color="black", lw=0.6)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)


def plot_one_run_state(study, j: int, path: Path, run: int = 0, names=None, units=None) -> Path:
    """State ``j`` of one run: estimated vs true (top) and error over time (bottom), all filters."""
    s = study.system
    names = names or list(study.estimates)
    state, unit = s.state_names[j], (units or s.state_units)[j]
    truth = study.data["state"][run, :, j]
    t = torch.arange(1, truth.shape[0] + 1) * s.dt
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    estimates = {name: study.estimates[name][run, :, j] for name in names}
    _state_and_error_panels(top, bottom, t, truth, estimates, f"{state} [{unit}]")
    top.legend(fontsize=7, ncol=3)
    fig.suptitle(f"{s.name} ({s.scenario}), run {run}: {state}, estimates and errors")
    return _save(fig, path)


def plot_per_run_boxes(study, path: Path, names=None, units=None) -> Path:
    """Box plot of per-run RMSE, one panel per state (log scale)."""
    s = study.system
    names = names or list(study.results)
    fig, axes = plt.subplots(1, s.state_dim, figsize=(max(6, 1.1 * len(names)) * s.state_dim / 1.4, 4), squeeze=False)
    for j, (state, unit) in enumerate(zip(s.state_names, units or s.state_units)):
        ax = axes[0, j]
        values = [[row[j] for row in study.results[n].per_run_rmse] for n in names]
        ax.boxplot(values, showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=35, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(f"per-run RMSE {state} [{unit}]")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"{s.name} ({s.scenario}): per-run RMSE over {study.runs} runs")
    return _save(fig, path)


def plot_learning_curves(curves: dict[str, list[dict]], state_names, path: Path, references=None, units=None) -> Path:
    """Validation RMSE per state against training samples / env steps for every learned filter."""
    fig, axes = plt.subplots(1, len(state_names), figsize=(5.5 * len(state_names), 3.8), squeeze=False)
    for j, state in enumerate(state_names):
        ax = axes[0, j]
        for name, history in curves.items():
            if history:
                ax.plot([h["frames"] for h in history], [h[f"rmse_{state}"] for h in history], marker=".", label=name)
        ax.set_yscale("log")
        ax.set_xscale("symlog", linthresh=1e4)
        ax.set_xlim(left=0)  # training samples are never negative (symlog's autoscale pads below 0)
        for label, values in (references or {}).items():
            ax.axhline(values[j], ls="--", lw=0.9, color="gray")
            ax.text(0, values[j], f" {label}", fontsize=7, color="gray", va="bottom")
        ax.xaxis.set_major_formatter(_thousands)
        ax.set_xlabel("training samples (env steps)")
        ax.set_ylabel(f"validation RMSE {state}" + (f" [{units[j]}]" if units else ""))
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("learning curves (validation set)")
    return _save(fig, path)


def plot_window_study(rows: list[dict], state_names, path: Path) -> Path:
    """RMSE per state and cost per estimate against the window length N."""
    windows = [r["window"] for r in rows]
    fig, axes = plt.subplots(1, len(state_names) + 1, figsize=(4.5 * (len(state_names) + 1), 3.6), squeeze=False)
    for j, state in enumerate(state_names):
        axes[0, j].plot(windows, [r["rmse"][j] for r in rows], marker="o")
        axes[0, j].set_ylabel(f"RMSE {state}")
    costs = [r["cost_ms"] for r in rows]
    axes[0, -1].plot(windows, costs, marker="o", color="C3")
    axes[0, -1].set_ylabel("cost per estimate [ms]")
    for ax in axes[0]:
        ax.set_xlabel("window N")
        ax.set_xticks(windows)
        ax.grid(alpha=0.3)
    fig.suptitle("sliding-window study (DAOF-v1)")
    return _save(fig, path)


def plot_scenario_rmse(rmse: dict[str, dict[str, list[float]]], state_names, units, path: Path) -> Path:
    """RMSE per state as grouped bars: one group per scenario, one bar per filter (log scale).

    ``rmse``: scenario -> filter -> RMSE per state.
    """
    scenarios = list(rmse)
    names = list(dict.fromkeys(n for rows in rmse.values() for n in rows))
    width = 0.8 / max(len(names), 1)
    fig, axes = plt.subplots(
        1, len(state_names), figsize=(max(6, 1.8 * len(scenarios) + 2) * len(state_names) / 1.3, 4), squeeze=False
    )
    for j, (state, unit) in enumerate(zip(state_names, units)):
        ax = axes[0, j]
        for k, name in enumerate(names):
            xs = [i + (k - (len(names) - 1) / 2) * width for i, sc in enumerate(scenarios) if name in rmse[sc]]
            ys = [rmse[sc][name][j] for sc in scenarios if name in rmse[sc]]
            ax.bar(xs, ys, width, label=name)
        ax.set_xticks(range(len(scenarios)), scenarios)
        ax.set_yscale("log")
        ax.set_ylabel(f"RMSE {state} [{unit}]")
        ax.grid(alpha=0.3, axis="y")
    axes[0, -1].legend(fontsize=7, bbox_to_anchor=(1.02, 1.0), loc="upper left")  # outside: bars stay visible
    fig.suptitle("RMSE per scenario")
    return _save(fig, path)
