"""The study's figures (PNG): one run's states and errors, per-run RMSE, calibration, learning curves, windows,
scenarios.

Every figure is a grid of at most three panels a row with one legend below it (never on the data);
every series keeps one colour and line style across the figures of a report (``series_styles``:
model-based filters dashed, learned filters solid). ``_save`` checks each figure's layout
(``layout_problems``) and warns, or raises where ``DAOF_STRICT_FIGURES=1`` (the test suite sets it).
"""

from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

__all__ = [
    "is_learned",
    "layout_problems",
    "plot_one_run",
    "plot_one_run_state",
    "plot_calibration",
    "plot_per_run_boxes",
    "plot_learning_curves",
    "plot_scenario_rmse",
    "plot_window_study",
    "series_styles",
]

#: panels per row of a grid
COLUMNS = 3
#: a panel's size [in] and the saved figure's resolution
PANEL = (4.4, 3.2)
DPI = 110
#: widest figure a page shows readably [px]
MAX_WIDTH_PX = COLUMNS * PANEL[0] * DPI + 200
#: names of learned filters start with one of these (the rest are model-based references)
LEARNED_PREFIXES = ("DAOF", "SLF", "KalmanNet")


#: a learned filter's row trained on one of several seeds: "DAOF-v1 (seed 2)"
SEED_ROW = re.compile(r"^(?P<filter>.+) \(seed (?P<seed>\d+)\)$")


def is_learned(name: str) -> bool:
    """Whether ``name`` is a learned filter's row (DAOF-v1, DAOF-v2 (N=5), SLF, KalmanNet, …)."""
    return name.startswith(LEARNED_PREFIXES)


#: filters with a fixed style in every report (others take the next free ones); the first ten get
#: tab20's strong colours, so they go to the filters every report shows
KNOWN_SERIES = (
    *("DAOF-v1", "DAOF-v2", "SLF", "KalmanNet", "UKF", "EKF", "PF-oracle", "PF", "KF", "PF-joint"),
    *("KF-stationary", "PF-proposal", "DAOF-v1 (N=10)", "DAOF-v1 (N=5)", "DAOF-v1 (N=1)"),
)


#: line styles of a learned filter's training seeds, in order (model-based filters are dashed)
SEED_STYLES = ("-", "-.", ":")


def series_styles(names) -> dict[str, dict]:
    """A distinct (colour, line style) per name, the same for a filter in every figure: tab20's
    colours (the ten strong ones first), model-based filters dashed, learned ones solid; a learned
    filter's training seeds ("SLF (seed 2)") share its colour, with a line style each.
    A reference line's label "UKF (validation set)" takes the UKF's style."""
    palette = plt.get_cmap("tab20").colors
    order = sorted(range(20), key=lambda i: (i % 2, i))
    styles, unknown = {}, []
    for name in dict.fromkeys(names):
        base = name.removesuffix(" (validation set)")
        seed = SEED_ROW.match(base)
        base, k = (seed["filter"], int(seed["seed"])) if seed else (base, None)
        if base not in KNOWN_SERIES and base not in unknown:
            unknown.append(base)
        slot = KNOWN_SERIES.index(base) if base in KNOWN_SERIES else len(KNOWN_SERIES) + unknown.index(base)
        ls = "--" if not is_learned(base) else "-" if k is None else SEED_STYLES[(k - 1) % len(SEED_STYLES)]
        styles[name] = {"color": palette[order[slot % 20]], "ls": ls}
    return styles


def _grid(panels: int, title: str, height: float = PANEL[1]):
    """A figure of ``panels`` axes, at most ``COLUMNS`` a row, unused cells removed."""
    cols = min(COLUMNS, panels)
    rows = math.ceil(panels / cols)
    size = (PANEL[0] * cols, height * rows + 0.9)
    fig, axes = plt.subplots(rows, cols, figsize=size, squeeze=False, layout="constrained")
    flat = list(axes.flat)
    for ax in flat[panels:]:
        ax.remove()
    fig.suptitle(title)
    return fig, flat[:panels]


def _legend_below(fig, axes, ncol: int = 4) -> None:
    """One legend for the figure, under its panels (entries gathered from every panel, once each)."""
    entries = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    for columns in range(min(ncol, len(entries)), 0, -1):  # as many columns as fit the figure's width
        legend = fig.legend(entries.values(), entries.keys(), loc="outside lower center", ncol=columns)
        if columns == 1 or not _beyond_the_figure(fig, legend):
            return
        legend.remove()


def _beyond_the_figure(fig, legend) -> bool:
    """Whether ``legend`` sticks out of the figure's left or right edge (it would be cut off when saved)."""
    fig.canvas.draw()
    box, width = legend.get_window_extent(), fig.bbox.width
    return box.x0 < -0.5 or box.x1 > width + 0.5


def _count_label(x, _pos=None) -> str:
    """Tick label for sample counts: 250000 -> 250k, 1600000 -> 1.6M."""
    if abs(x) >= 1e6:
        return f"{x / 1e6:g}M"
    return f"{x / 1e3:g}k" if abs(x) >= 1e3 else f"{x:g}"


def layout_problems(fig) -> list[str]:
    """What makes ``fig`` hard to read: too wide, more than ``COLUMNS`` panels a row, a legend on a panel."""
    fig.canvas.draw()
    problems = []
    width = fig.get_figwidth() * DPI
    if width > MAX_WIDTH_PX:
        problems.append(f"{width:.0f} px wide (at most {MAX_WIDTH_PX:.0f})")
    rows: dict[float, int] = {}
    for ax in fig.axes:
        top = round(ax.get_position().y1, 3)
        rows[top] = rows.get(top, 0) + 1
    if rows and max(rows.values()) > COLUMNS:
        problems.append(f"{max(rows.values())} panels in a row (at most {COLUMNS})")
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    for legend in legends:
        if _beyond_the_figure(fig, legend):
            problems.append("a legend is wider than the figure (cut off)")
        box = legend.get_window_extent()
        for ax in fig.axes:
            if box.overlaps(ax.get_window_extent()):
                problems.append(f"a legend overlaps the panel '{ax.get_ylabel() or ax.get_title()}'")
    return problems


def _save(fig, path: Path) -> Path:
    problems = layout_problems(fig)
    if problems:
        message = f"{Path(path).name}: " + "; ".join(problems)
        if os.environ.get("DAOF_STRICT_FIGURES") == "1":
            plt.close(fig)
            raise ValueError(message)
        warnings.warn(message, stacklevel=3)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _reference_name(names) -> str | None:
    """The model-based filter the errors panel shows beside the learned ones (the oracle where there is one)."""
    model_based = [n for n in names if not is_learned(n)]
    for preferred in ("PF-oracle", "PF-joint", "KF"):
        if preferred in model_based:
            return preferred
    return model_based[0] if model_based else None


def _time_label(system) -> str:
    """The time axis of a system: "step" for a discrete-time model, else "time [<unit>]"."""
    unit = system.time_unit
    return "step" if unit == "step" else f"time [{unit}]"


def _state_row(axes, t, truth, estimates: dict, styles: dict, label: str, time_label: str) -> None:
    """One state in up to three panels: model-based estimates, learned estimates, errors (learned + reference)."""
    groups = {
        "model-based filters": {n: e for n, e in estimates.items() if not is_learned(n)},
        "learned filters": {n: e for n, e in estimates.items() if is_learned(n)},
    }
    groups = {title: group for title, group in groups.items() if group}
    reference = _reference_name(estimates)
    shown_errors = {n: e for n, e in estimates.items() if is_learned(n) or n == reference}
    for ax, (title, group) in zip(axes, groups.items()):
        ax.plot(t, truth, color="black", lw=1.4, label="true state")
        for name, est in group.items():
            ax.plot(t, est, lw=0.9, label=name, color=styles[name]["color"], ls=styles[name]["ls"])
        ax.set_title(title, fontsize=9)
        ax.set_ylabel(label)
    err = axes[len(groups)]
    for name, est in shown_errors.items():
        err.plot(t, est - truth, lw=0.8, label=name, color=styles[name]["color"], ls=styles[name]["ls"])
    err.axhline(0, color="black", lw=0.6)
    err.set_title("estimation error", fontsize=9)
    err.set_ylabel(f"error {label}")
    for ax in axes:
        ax.set_xlabel(time_label)
        ax.grid(alpha=0.3)


def _study_rows(names) -> list[str]:
    """The study's rows without the window study's extra ones ("DAOF-v1 (N=5)")."""
    return [n for n in names if "(N=" not in n]


def _panels_per_state(names) -> int:
    return int(any(not is_learned(n) for n in names)) + int(any(is_learned(n) for n in names)) + 1


def plot_one_run(study, path: Path, run: int = 0, names=None) -> Path:
    """One run, a row per state: model-based and learned estimates against the truth, and the errors."""
    s = study.system
    names = names or _study_rows(study.estimates)
    styles = series_styles(names)
    truth = study.data["state"][run]
    t = torch.arange(1, truth.shape[0] + 1) * s.dt
    per_state = _panels_per_state(names)
    fig, axes = _grid(per_state * s.state_dim, f"{s.name} ({s.scenario}), run {run}: estimates and errors")
    for j, (state, unit) in enumerate(zip(s.state_names, s.state_units)):
        estimates = {name: study.estimates[name][run, :, j] for name in names}
        row = axes[j * per_state : (j + 1) * per_state]
        _state_row(row, t, truth[:, j], estimates, styles, f"{state} [{unit}]", _time_label(s))
    _legend_below(fig, axes)
    return _save(fig, path)


def plot_one_run_state(study, j: int, path: Path, run: int = 0, names=None, units=None) -> Path:
    """State ``j`` of one run: model-based and learned estimates against the truth, and the errors."""
    s = study.system
    names = names or _study_rows(study.estimates)
    state, unit = s.state_names[j], (units or s.state_units)[j]
    truth = study.data["state"][run, :, j]
    t = torch.arange(1, truth.shape[0] + 1) * s.dt
    fig, axes = _grid(_panels_per_state(names), f"{s.name} ({s.scenario}), run {run}: {state}")
    estimates = {name: study.estimates[name][run, :, j] for name in names}
    _state_row(axes, t, truth, estimates, series_styles(names), f"{state} [{unit}]", _time_label(s))
    _legend_below(fig, axes)
    return _save(fig, path)


def plot_per_run_boxes(study, path: Path, names=None, units=None) -> Path:
    """Per-run RMSE of every filter, one panel per state (log scale: runs spread over decades)."""
    s = study.system
    names = names or list(study.results)
    styles = series_styles(names)
    fig, axes = _grid(s.state_dim, f"{s.name} ({s.scenario}): per-run RMSE over {study.runs} runs", height=3.6)
    for ax, state, unit, j in zip(axes, s.state_names, units or s.state_units, range(s.state_dim)):
        values = [[row[j] for row in study.results[n].per_run_rmse] for n in names]
        boxes = ax.boxplot(values, showfliers=True, patch_artist=True, widths=0.6)
        for box, name in zip(boxes["boxes"], names):
            box.set(facecolor=styles[name]["color"], alpha=0.55)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=40, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel(f"per-run RMSE {state} [{unit}]")
        ax.grid(alpha=0.3, axis="y")
    return _save(fig, path)


def plot_learning_curves(
    curves: dict[str, list[dict]], state_names, path: Path, references=None, units=None, title=None
) -> Path:
    """Validation RMSE per state against training samples for every learned filter, references dashed."""
    styles = series_styles([*curves, *(references or {})])
    fig, axes = _grid(len(state_names), title or "learning curves (validation set)")
    for j, (ax, state) in enumerate(zip(axes, state_names)):
        for name, history in curves.items():
            if history:
                xs = [h["frames"] for h in history]
                ax.plot(xs, [h[f"rmse_{state}"] for h in history], marker=".", label=name, **styles[name])
        for label, values in (references or {}).items():
            ax.axhline(values[j], lw=1.0, label=label, color=styles[label]["color"], ls=styles[label]["ls"])
        ax.set_yscale("log")
        ax.set_xlim(left=0)
        ax.xaxis.set_major_formatter(_count_label)
        ax.set_xlabel("training samples (env steps)")
        ax.set_ylabel(f"validation RMSE {state}" + (f" [{units[j]}]" if units else ""))
        ax.grid(alpha=0.3)
    _legend_below(fig, axes)
    return _save(fig, path)


def plot_window_study(rows: list[dict], state_names, path: Path, units=None) -> Path:
    """Per window N: each state's RMSE, as a ratio to the paired reference with its interval where
    the rows carry one (``ratio``, ``low``, ``high`` from ``paired_comparison``), and the cost per estimate."""
    windows = [r["window"] for r in rows]
    paired = all("ratio" in r for r in rows)
    reference = rows[0].get("reference") if paired else None
    fig, axes = _grid(len(state_names) + 1, "sliding-window study")
    for j, (ax, state) in enumerate(zip(axes, state_names)):
        if paired:
            mid = [r["ratio"][j] for r in rows]
            err = [[m - r["low"][j] for m, r in zip(mid, rows)], [r["high"][j] - m for m, r in zip(mid, rows)]]
            ax.errorbar(windows, mid, yerr=err, marker="o", capsize=4, label="ratio, 95 % paired interval")
            ax.axhline(1.0, color="black", lw=0.8, ls="--", label=f"{reference} (= 1)")
            ax.set_ylabel(f"RMSE {state} / {reference}")
        else:
            ax.plot(windows, [r["rmse"][j] for r in rows], marker="o", label="RMSE")
            ax.set_ylabel(f"RMSE {state}" + (f" [{units[j]}]" if units else ""))
    axes[-1].plot(windows, [r["cost_ms"] for r in rows], marker="o", color="tab:red", label="cost per estimate")
    axes[-1].set_ylabel("cost per estimate [ms]")
    for ax in axes:
        ax.set_xlabel("window N")
        ax.set_xscale("log")
        ax.set_xticks(windows, [str(n) for n in windows])
        ax.minorticks_off()
        ax.grid(alpha=0.3)
    _legend_below(fig, axes)
    return _save(fig, path)


def plot_scenario_rmse(rmse: dict[str, dict[str, list[float]]], state_names, units, path: Path) -> Path:
    """RMSE per state as grouped bars from zero: one group per scenario, one bar per filter.

    ``rmse``: scenario -> filter -> RMSE per state.
    """
    scenarios = list(rmse)
    names = list(dict.fromkeys(n for rows in rmse.values() for n in rows))
    styles = series_styles(names)
    width = 0.8 / max(len(names), 1)
    fig, axes = _grid(len(state_names), "RMSE per scenario")
    for j, (ax, state, unit) in enumerate(zip(axes, state_names, units)):
        for k, name in enumerate(names):
            xs = [i + (k - (len(names) - 1) / 2) * width for i, sc in enumerate(scenarios) if name in rmse[sc]]
            ys = [rmse[sc][name][j] for sc in scenarios if name in rmse[sc]]
            hatch = None if is_learned(name) else "//"
            ax.bar(xs, ys, width, label=name, color=styles[name]["color"], hatch=hatch, edgecolor="white", lw=0)
        ax.set_xticks(range(len(scenarios)), scenarios)
        ax.set_ylim(bottom=0)
        ax.set_ylabel(f"RMSE {state} [{unit}]")
        ax.grid(alpha=0.3, axis="y")
    _legend_below(fig, axes)
    return _save(fig, path)


#: markers of the calibration figure's series, in order (a filter's colour and line style from ``series_styles``)
MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">", "h", "p")


def plot_calibration(study, path: Path, coverage_band=(0.93, 0.97), nees_band=(0.8, 1.25)) -> Path:
    """Per state (x axis), every filter with an error std: its ±2σ coverage against the Gaussian 95.45 %, and
    its mean NEES on a log axis against 1; the bands shaded are the targets (``coverage_band``, ``nees_band``)."""
    from daof.evaluate.metrics import GAUSSIAN_COVERAGE

    s = study.system
    names = [n for n, r in study.results.items() if r.nees is not None]
    if not names:
        raise ValueError("no filter of the study gives an error std: nothing to plot")
    styles = series_styles(names)
    title = f"{s.name} ({s.scenario}): calibration of the error std, {study.runs} runs × {study.steps} steps"
    fig, (cover, nees) = _grid(2, title)
    width = 0.7 / len(names)
    states = range(s.state_dim)
    for k, name in enumerate(names):
        r, style = study.results[name], styles[name]
        xs = [j + (k - (len(names) - 1) / 2) * width for j in states]
        hollow = "none" if not is_learned(name) else style["color"]
        marker = {"marker": MARKERS[k % len(MARKERS)], "color": style["color"], "mfc": hollow, "ls": "none"}
        cover.plot(xs, [100 * v for v in r.coverage_2sigma], label=name, ms=7, **marker)
        nees.plot(xs, r.nees, label=name, ms=7, **marker)
    band = f"target band ({100 * coverage_band[0]:g}–{100 * coverage_band[1]:g} % / {nees_band[0]:g}–{nees_band[1]:g})"
    cover.axhspan(100 * coverage_band[0], 100 * coverage_band[1], color="0.88", zorder=0, label=band)
    cover.axhline(100 * GAUSSIAN_COVERAGE, color="black", lw=0.9, ls="--", label="Gaussian, right σ (95.45 % / 1)")
    nees.axhspan(*nees_band, color="0.88", zorder=0)
    nees.axhline(1.0, color="black", lw=0.9, ls="--")
    # the bands with room around them, wider where a filter is far off
    covers = [100 * v for n in names for v in study.results[n].coverage_2sigma if math.isfinite(v)]
    cover.set_ylim(min([90.0, *covers]) - 0.5, 100.5)
    values = [v for n in names for v in study.results[n].nees if math.isfinite(v) and v > 0]
    low, high = min([0.5, *values]) / 1.2, max([2.0, *values]) * 1.2
    nees.set_yscale("log")
    nees.set_ylim(low, high)
    ticks = [t for t in (0.01, 0.1, 0.25, 0.5, 0.8, 1, 1.25, 2, 4, 10, 100) if low <= t <= high]
    nees.set_yticks(ticks, [f"{t:g}" for t in ticks])
    nees.minorticks_off()
    cover.set_ylabel("share of errors within ±2σ [%]")
    nees.set_ylabel("mean NEES e²/σ² (log)")
    for ax in (cover, nees):
        ax.set_xticks(list(states), list(s.state_names))
        ax.set_xlabel("state")
        ax.grid(alpha=0.3, axis="y")
    _legend_below(fig, [cover, nees])
    return _save(fig, path)
