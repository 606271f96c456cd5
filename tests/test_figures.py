"""The report's figures: readable layouts (at most three panels a row, legends off the data), a
distinct style per series, the window study's intervals."""

from types import SimpleNamespace

import matplotlib.pyplot as plt
import pytest
import torch
from PIL import Image

from daof.evaluate import figures

NAMES = ["EKF", "UKF", "PF", "PF-oracle", "PF-joint", "SLF", "DAOF-v2", "DAOF-v1", "DAOF-v1 (N=10)", "DAOF-v1 (N=5)"]


def _study(state_dim: int = 2, runs: int = 6, steps: int = 40, names=NAMES):
    """A study-shaped namespace: truth, estimates and per-run RMSEs of ``names``."""
    g = torch.Generator().manual_seed(0)
    truth = torch.randn(runs, steps, state_dim, generator=g).cumsum(1)
    estimates = {n: truth + 0.1 * (k + 1) * torch.randn(truth.shape, generator=g) for k, n in enumerate(names)}
    per_run = {n: (e - truth).pow(2).mean(1).sqrt() for n, e in estimates.items()}
    system = SimpleNamespace(
        name="toy",
        scenario="nominal",
        dt=0.01,
        time_unit="s",
        state_dim=state_dim,
        state_names=[f"s{j}" for j in range(state_dim)],
        state_units=["m"] * state_dim,
    )
    results = {n: SimpleNamespace(per_run_rmse=per_run[n].tolist()) for n in names}
    return SimpleNamespace(system=system, data={"state": truth}, estimates=estimates, results=results, runs=runs)


def test_every_series_of_a_report_has_its_own_style():
    styles = figures.series_styles(NAMES + ["KF", "KF-stationary", "KalmanNet", "PF-proposal"])
    pairs = {(s["color"], s["ls"]) for s in styles.values()}
    assert len(pairs) == len(NAMES) + 4
    assert styles["UKF"]["ls"] == "--" and styles["DAOF-v1"]["ls"] == "-" and styles["KalmanNet"]["ls"] == "-"
    # a filter keeps its style whichever other series a figure shows
    assert figures.series_styles(["SLF", "my filter"])["SLF"] == styles["SLF"]
    assert figures.series_styles(["my filter", "PF-proposal"])["PF-proposal"] == styles["PF-proposal"]
    assert figures.series_styles(["UKF (validation set)"])["UKF (validation set)"] == styles["UKF"]
    # a filter's training seeds: its colour, a line style each, none of them the model-based dash
    seeds = figures.series_styles([f"DAOF-v1 (seed {k})" for k in (1, 2, 3)] + ["UKF"])
    assert {s["color"] for n, s in seeds.items() if n != "UKF"} == {styles["DAOF-v1"]["color"]}
    assert len({s["ls"] for s in seeds.values()}) == 4


def test_layout_problems_finds_a_wide_row_and_a_legend_on_the_data():
    fig, axes = plt.subplots(1, 6, figsize=(30, 3))
    for ax in axes:
        ax.plot(range(10), label="a")
    axes[0].legend(loc="center")
    problems = figures.layout_problems(fig)
    plt.close(fig)
    assert any("px wide" in p for p in problems)
    assert any("6 panels in a row" in p for p in problems)
    assert any("legend overlaps" in p for p in problems)


def test_a_one_panel_figure_gets_a_legend_that_fits_its_width():
    """Four columns of long names are wider than one panel: the legend takes fewer columns, not the edge."""
    labels = ["DAOF-v1", "DAOF-v2", "KalmanNet", "SLF", "UKF (validation set)", "PF-oracle (validation set)"]
    fig, axes = figures._grid(1, "toy")
    for k, label in enumerate(labels):
        axes[0].plot(range(5), [k] * 5, label=label)
    figures._legend_below(fig, axes)
    assert figures.layout_problems(fig) == [] and fig.legends[0]._ncols < 4
    fig.legends[0].remove()
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=6)
    assert "a legend is wider than the figure (cut off)" in figures.layout_problems(fig)
    plt.close(fig)


@pytest.mark.parametrize("state_dim", [2, 6])
def test_every_figure_is_readable(tmp_path, state_dim):
    """Rendered under DAOF_STRICT_FIGURES=1 (conftest): ``_save`` raises on any layout problem."""
    study = _study(state_dim)
    names = study.system.state_names
    paths = [
        figures.plot_one_run(study, tmp_path / "run0.png") if state_dim == 2 else None,  # 6 states: one figure each
        figures.plot_one_run_state(study, 1, tmp_path / "run0_s1.png"),
        figures.plot_per_run_boxes(study, tmp_path / "boxes.png"),
        figures.plot_learning_curves(
            {
                n: [{"frames": f, **{f"rmse_{s}": 1 / (1 + f / 1e5) for s in names}} for f in (0, 4e5, 1.6e6)]
                for n in NAMES[5:]
            },
            names,
            tmp_path / "curves.png",
            references={"UKF (validation set)": [0.5] * state_dim},
        ),
        figures.plot_scenario_rmse(
            {sc: {n: [1.0] * state_dim for n in NAMES} for sc in ("nominal", "mismatch")},
            names,
            study.system.state_units,
            tmp_path / "scenarios.png",
        ),
    ]
    for path in filter(None, paths):
        width, height = Image.open(path).size
        assert width <= figures.MAX_WIDTH_PX and height <= 1.2 * width * (state_dim if "run0.png" in str(path) else 1)


@pytest.mark.parametrize(("unit", "label"), [("s", "time [s]"), ("step", "step")])
def test_the_time_axis_says_the_systems_time_unit(tmp_path, unit, label, monkeypatch):
    study = _study()
    study.system.time_unit = unit
    drawn = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: drawn.append(fig) or path)
    figures.plot_one_run(study, tmp_path / "run0.png")
    assert {ax.get_xlabel() for ax in drawn[0].axes} == {label}
    plt.close(drawn[0])


def test_window_study_draws_the_paired_intervals(tmp_path):
    rows = [
        {
            "window": n,
            "rmse": [1.0, 2.0],
            "cost_ms": 0.1,
            "ratio": [0.98, 1.0],
            "low": [0.95, 0.97],
            "high": [1.01, 1.02],
            "reference": "UKF",
        }
        for n in (1, 5, 20)
    ]
    captured = {}

    def keep(fig, path):
        captured["fig"] = fig
        return path

    original = figures._save
    figures._save = keep
    try:
        figures.plot_window_study(rows, ["beta", "r"], tmp_path / "w.png")
    finally:
        figures._save = original
    ax = captured["fig"].axes[0]
    assert ax.get_ylabel() == "RMSE beta / UKF"
    caps = [line for line in ax.lines if line.get_marker() == "_"]  # errorbar caps: low and high per window
    assert sorted(round(float(y), 2) for line in caps for y in line.get_ydata()) == [0.95] * 3 + [1.01] * 3
    plt.close(captured["fig"])
