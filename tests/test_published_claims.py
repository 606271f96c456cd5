"""The numbers docs/results/README.md and docs/*.md quote from committed reports, checked against their results.json.

Each check finds the sentence as the prose prints it and compares every number in it with the
value recomputed from `docs/results/*/results.json`, to the printed digits (half a unit of the
last printed digit). Orderings and "met" flags are recomputed from the per-run RMSEs.
"""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from daof.evaluate.metrics import paired_rmse_ratio
from daof.evaluate.report import PAIRED_DRAWS
from daof.evaluate.summary import learned_filters, learned_winners

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
NUM = r"(-?\d+(?:,\d{3})*(?:\.\d+)?)"


def text(rel: str) -> str:
    """A markdown file of the repository with its whitespace collapsed (sentences span lines)."""
    return " ".join((ROOT / rel).read_text().split())


def report(rel: str) -> dict:
    return json.loads((RESULTS / rel / "results.json").read_text())


def quoted(doc: str, pattern: str) -> tuple[str, ...]:
    """The numbers a pattern captures in a document; the claim must be there as written."""
    match = re.search(pattern, doc)
    assert match, f"claim not found in the prose: {pattern!r}"
    return match.groups()


def agrees(printed: str, value: float, slack: float = 0.0) -> None:
    """``printed`` is ``value`` to its printed digits (plus ``slack`` for Monte Carlo quantities)."""
    digits = len(printed.split(".")[1]) if "." in printed else 0
    tol = 0.5 * 10.0**-digits + slack + 1e-9
    assert abs(float(printed.replace(",", "")) - value) <= tol, f"prose says {printed}, report gives {value:.6g}"


def rmse(rep: dict, name: str) -> np.ndarray:
    return np.asarray(rep["filters"][name]["rmse"])


def ratio_oracle(rep: dict, name: str) -> np.ndarray:
    return rmse(rep, name) / rmse(rep, rep["reference"])


def pct(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """Percentage change of ``new`` over ``old``."""
    return 100 * (new / old - 1)


ALL_REPORTS = sorted(p.parent.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("results.json"))


@pytest.mark.parametrize("rel", ALL_REPORTS)
def test_report_is_self_consistent(rel):
    """Every committed report: pooled RMSE = sqrt(mean per-run MSE), ratios = RMSE / reference's RMSE."""
    rep = report(rel)
    if "studies" in rep:  # the combined report of several scenarios: the scenario reports' numbers and winners
        for scenario, study in rep["studies"].items():
            own = report(f"{rel.rsplit('/', 1)[0]}/{scenario}/report")
            for name, f in study["filters"].items():
                assert f["rmse"] == own["filters"][name]["rmse"], (scenario, name)
            for k, state in enumerate(rep["states"]):
                best = min(study["filters"], key=lambda n: study["filters"][n]["rmse"][k])
                assert rep["winners"][scenario]["per_state"][state] == best
        return
    assert rep["filters"], rel
    for name, f in rep["filters"].items():
        assert all(math.isfinite(v) for v in f["rmse"]), (rel, name)
        if "per_run_rmse" in f:
            per_run = np.asarray(f["per_run_rmse"])
            assert per_run.shape == (rep["runs"], len(rep["states"])), (rel, name)
            np.testing.assert_allclose(np.sqrt((per_run**2).mean(0)), f["rmse"], rtol=1e-6, err_msg=f"{rel} {name}")
        if rep.get("reference"):
            np.testing.assert_allclose(f["ratio_to_oracle"], ratio_oracle(rep, name), rtol=1e-6, err_msg=rel)


# ---------------------------------------------------------------- Experiment I (paper profile)


def seed_range(rep: dict, name: str, values) -> np.ndarray:
    """[[min, max] per state] of ``values(rep, row)`` over a learned filter's seed rows."""
    v = np.stack([values(rep, row) for row in seed_rows(rep, name)])
    return np.stack([v.min(0), v.max(0)], 1)


def agrees_range(printed: str, low_high) -> None:
    """``printed`` is "a–b" (the range, each end to its digits) or "a" (both ends round to it)."""
    ends = printed.split("–")
    if len(ends) == 1:
        ends = ends * 2
    agrees(ends[0], low_high[0]), agrees(ends[1], low_high[1])


RANGE = r"(\d+\.\d+(?:–\d+\.\d+)?)"


def paired(rep: dict, name: str, key: str = "ratio") -> np.ndarray:
    return np.asarray(rep["paired_with"]["filters"][name][key])


def test_experiment1_ratios_to_oracle():
    rep, doc = report("experiment1"), text("docs/results/README.md")
    assert all(e["seeds"] == [1, 2, 3] for e in rep["seeds"].values()) and len(rep["seeds"]) == 4
    for prose, name in [("PF (1,000 particles)", "PF"), ("UKF", "UKF"), ("EKF", "EKF")]:
        beta, r = quoted(doc, rf"[-,] {re.escape(prose)} {NUM} / {NUM}[;,.]")
        agrees(beta, ratio_oracle(rep, name)[0])
        agrees(r, ratio_oracle(rep, name)[1])
    for prose, name in [
        ("DAOF-v1 (N = 20)", "DAOF-v1"),
        ("KalmanNet", "KalmanNet"),
        ("SLF", "SLF"),
        ("DAOF-v2", "DAOF-v2"),
    ]:
        beta, r = quoted(doc, rf"- {re.escape(prose)} {RANGE} / {RANGE}[;,.]")
        ranges = seed_range(rep, name, ratio_oracle)
        agrees_range(beta, ranges[0]), agrees_range(r, ranges[1])
    assert "window_study" not in rep and not any("(N=" in n for n in rep["filters"])  # "no window study"
    (goal,) = quoted(doc, rf"The goal of ≤ {NUM} × PF-oracle is not met")
    for name in seed_rows(rep, "DAOF-v1"):
        assert (ratio_oracle(rep, name) > float(goal)).any()


def test_experiment1_daof_v1_and_kalmannet_below_ukf_on_every_seed():
    """The headline: DAOF-v1 (N = 20) and KalmanNet below the UKF on both states with each seed, by the
    quoted ranges and intervals; neither wins a state against the other."""
    rep, doc = report("experiment1"), text("docs/results/README.md")
    assert rep["paired_with"]["reference"] == "UKF"
    for name in ("DAOF-v1", "KalmanNet"):
        rows = seed_rows(rep, name)
        assert len(rows) == 3 and all((paired(rep, row) < 1).all() for row in rows)
        assert rep["seeds"][name]["seeds_better"] == 3
    beta, r = quoted(doc, rf"the ratio is {RANGE} on β and {RANGE} on r")
    ranges = seed_range(rep, "DAOF-v1", paired)
    agrees_range(beta, ranges[0]), agrees_range(r, ranges[1])
    beta, r = quoted(doc, rf"below the UKF on both states with every seed \({RANGE} / {RANGE}\)")
    ranges = seed_range(rep, "KalmanNet", paired)
    agrees_range(beta, ranges[0]), agrees_range(r, ranges[1])
    printed = quoted(doc, rf"seed 1: {NUM} \[{NUM}, {NUM}\] on β and {NUM} \[{NUM}, {NUM}\] on r")
    for state in (0, 1):
        for k, key in enumerate(("ratio", "low", "high")):
            agrees(printed[3 * state + k], paired(rep, "DAOF-v1 (seed 1)", key)[state])
    excluded = [sum(paired(rep, row, "high")[s] < 1 for row in seed_rows(rep, "DAOF-v1")) for s in (0, 1)]
    assert "exclude 1 on β for one seed and on r for two" in doc and excluded == [1, 2]
    # the tie, recomputed from the per-run RMSEs pooled over each filter's seeds
    lines = learned_winners(rep)
    assert any(line.startswith("- beta: no clear winner, KalmanNet 0.995 [0.981, 1.010] × DAOF-v1") for line in lines)
    assert any(
        line.startswith("- yaw_rate: no clear winner, DAOF-v1 0.999 [0.989, 1.009] × KalmanNet") for line in lines
    )
    assert "KalmanNet / DAOF-v1 is 0.995 [0.981, 1.010] on β and DAOF-v1 / KalmanNet 0.999 [0.989, 1.009] on r" in doc


def test_experiment1_paired_intervals_recomputed():
    """The report's paired intervals follow from its per-run RMSEs.

    The ratio and the runs won are exact; the interval ends to 2e-3 (reports made before scipy's bootstrap
    replaced the torch one drew another random stream).
    """
    rep = report("experiment1")
    ref = torch.tensor(rep["filters"]["UKF"]["per_run_rmse"])
    for name in ("DAOF-v1 (seed 1)", "KalmanNet (seed 2)", "DAOF-v2 (seed 3)"):
        again = paired_rmse_ratio(torch.tensor(rep["filters"][name]["per_run_rmse"]), ref, draws=PAIRED_DRAWS)
        stored = rep["paired_with"]["filters"][name]
        np.testing.assert_allclose(again["ratio"], stored["ratio"], rtol=1e-9, err_msg=name)
        for key in ("low", "high"):
            np.testing.assert_allclose(again[key], stored[key], atol=2e-3, err_msg=f"{name} {key}")
        assert again["better_runs"] == stored["better_runs"]


def test_experiment1_daof_v2_against_the_slf_per_seed():
    """DAOF-v2 below the SLF of its seed on r with every seed, on β with two of three; the bound of
    ≤ 1.15× the PF-oracle met on r, not on β; the ranges of its paired ratios to the UKF as printed."""
    rep, doc = report("experiment1"), text("docs/results/README.md")
    v2, slf = seed_rows(rep, "DAOF-v2"), seed_rows(rep, "SLF")
    below = np.array([rmse(rep, a) < rmse(rep, b) for a, b in zip(v2, slf, strict=True)])
    assert below[:, 1].all() and below[:, 0].sum() == 2
    assert "is below the SLF of its seed on r with every seed" in doc and "on β with two seeds of three" in doc
    worst = np.max([ratio_oracle(rep, row) for row in v2], 0)
    assert worst[1] <= 1.15 < worst[0]  # "met on r, not on β"
    v2_r, slf_r = quoted(doc, rf"\(DAOF-v2 / UKF {RANGE} on r against the SLF's {RANGE}\)")
    agrees_range(v2_r, seed_range(rep, "DAOF-v2", paired)[1]), agrees_range(slf_r, seed_range(rep, "SLF", paired)[1])


def test_experiment1_budget_and_costs():
    rep, doc = report("experiment1"), text("docs/results/README.md")
    frames, updates = quoted(doc, rf"It trains on 3,200 episodes of 500 steps \({NUM}M frames, ~{NUM} updates\)")
    train = rep["training"]["DAOF-v1 (seed 1)"]
    agrees(frames, train["frames"] / 1e6)
    assert 3200 * 500 == train["frames"]
    assert round(train["updates"], -2) == float(updates.replace(",", ""))
    cost = {n: f["cost_ms"] for n, f in rep["filters"].items()}
    printed = quoted(
        doc,
        rf"SLF {RANGE} ms, DAOF-v2 {RANGE} ms, EKF {NUM} ms; - UKF {NUM} ms, DAOF-v1 {RANGE} ms, "
        rf"KalmanNet {RANGE} ms; - PF {NUM} ms, PF-oracle {NUM} ms",
    )
    for text_, name in zip(printed, ["SLF", "DAOF-v2", "EKF", "UKF", "DAOF-v1", "KalmanNet", "PF", "PF-oracle"]):
        rows = seed_rows(rep, name)
        agrees_range(text_, (min(cost[r] for r in rows), max(cost[r] for r in rows)))
    own = text("docs/results/experiment1/README.md")
    kn, v1 = quoted(own, rf"KalmanNet costs {RANGE} ms per estimate here against DAOF-v1's {RANGE} ms")
    for text_, name in ((kn, "KalmanNet"), (v1, "DAOF-v1")):
        agrees_range(text_, (min(cost[r] for r in seed_rows(rep, name)), max(cost[r] for r in seed_rows(rep, name))))


def test_experiment1_report_table():
    """docs/results/experiment1/README.md: every row with its RMSE, ratios, interval, runs won and cost."""
    rep, doc = report("experiment1"), text("docs/results/experiment1/README.md")
    labels = {"PF-oracle": "PF-oracle (20,000 particles)", "PF": "PF (1,000)"}
    for name, f in rep["filters"].items():
        cell = rf"\| \**{re.escape(labels.get(name, name))}\** \| \**\[{NUM}, {NUM}\]\** \| \**\[{NUM}, {NUM}\]\** \|"
        got = quoted(doc, cell)
        for printed, value in zip(got, [*f["rmse"], *f["ratio_to_oracle"]], strict=True):
            agrees(printed, value)
        tail = (
            rf"{re.escape(labels.get(name, name))}\** \|[^|]*\|[^|]*\| \**([^|*]+)\** \| \**([^|*]+)\** \| \**{NUM} ms"
        )
        interval, won, ms = quoted(doc, tail)
        agrees(ms, f["cost_ms"])
        if name == "UKF":
            continue
        p = rep["paired_with"]["filters"][name]
        numbers = re.findall(NUM, interval)
        for printed, value in zip(
            numbers, [p["ratio"][0], p["low"][0], p["high"][0], p["ratio"][1], p["low"][1], p["high"][1]], strict=True
        ):
            agrees(printed, value)
        assert [int(w) for w in won.split(" / ")] == p["better_runs"]
    means = quoted(doc, rf"DAOF-v1 \[{NUM} ± {NUM}, {NUM} ± {NUM}\], KalmanNet \[{NUM} ± {NUM}, {NUM} ± {NUM}\]")
    for k, name in enumerate(("DAOF-v1", "KalmanNet")):
        e = rep["seeds"][name]
        for j, value in enumerate([e["rmse_mean"][0], e["rmse_std"][0], e["rmse_mean"][1], e["rmse_std"][1]]):
            agrees(means[4 * k + j], value)


# ---------------------------------------------------------------- Experiment II (paper profile)

EXP2_STATES = ["pitch", "roll", "yaw rate", "side slip", "Vx", "ax"]


def geometric_ratio(a: np.ndarray, b: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """Geometric mean of per-run RMSE ratios with a 95 % percentile bootstrap interval over runs."""
    from scipy.stats import bootstrap

    logs = np.log(a / b)
    ci = bootstrap((logs,), np.mean, n_resamples=4000, method="percentile", rng=np.random.default_rng(seed))
    return math.exp(logs.mean()), math.exp(ci.confidence_interval.low), math.exp(ci.confidence_interval.high)


def test_experiment2_ratios_and_intervals():
    rep, doc = report("experiment2"), text("docs/results/README.md")
    v2, slf = rmse(rep, "DAOF-v2"), rmse(rep, "SLF")
    pattern = " / ".join(rf"{NUM} \({s}(?:, level: per-run 95 % CI \[{NUM}, {NUM}\])?\)" for s in EXP2_STATES)
    printed = [p for p in quoted(doc, "DAOF-v2 / SLF = " + pattern) if p is not None]
    ratios = v2 / slf
    for k in range(6):
        agrees(printed[k + (2 if k > 2 else 0)], ratios[k])
    runs_v2, runs_slf = (np.asarray(rep["filters"][n]["per_run_rmse"]) for n in ("DAOF-v2", "SLF"))
    intervals = [geometric_ratio(runs_v2[:, k], runs_slf[:, k]) for k in range(6)]
    # bootstrap ends depend on the resampling stream: allowed one unit of the printed digit beyond rounding
    agrees(printed[3], intervals[2][1], slack=0.01), agrees(printed[4], intervals[2][2], slack=0.01)
    assert "the five leads with per-run confidence intervals below 1" in doc
    assert sum(r < 1 for r in ratios.round(2)) == 5 and sum(hi < 1 for _, _, hi in intervals) == 5
    (minutes,) = quoted(doc, rf"3.2 M training samples each; {NUM} min")
    agrees(minutes, rep["wall_time_s"] / 60)
    assert {t["frames"] for t in rep["training"].values()} == {3_200_000}


def test_experiment2_report_table():
    """The table of docs/results/experiment2/README.md: RMSE (the json's are in the paper's units), ratios, runs won."""
    rep, doc = report("experiment2"), text("docs/results/experiment2/README.md")
    row = r" \| ".join([r"\**" + NUM + r"\**"] * 6)
    for prose, name in [("SLF", "SLF"), (r"DAOF-v2 \(x̂ = π\(h\), reward-spread critic, target actor\)", "DAOF-v2")]:
        for printed, value in zip(quoted(doc, rf"\| {prose} \| {row} \|"), rmse(rep, name), strict=True):
            agrees(printed, value)
    a, b = (np.asarray(rep["filters"][n]["per_run_rmse"]) for n in ("DAOF-v2", "SLF"))
    for printed, value in zip(quoted(doc, rf"\| DAOF-v2 / SLF \| {row} \|"), rmse(rep, "DAOF-v2") / rmse(rep, "SLF")):
        agrees(printed, value)
    wins = quoted(doc, r"\| runs \(of 100\) where DAOF-v2 beats the SLF \| " + r" \| ".join([NUM] * 6) + r" \|")
    assert [int(w) for w in wins] == (a < b).sum(0).tolist()
    cis = quoted(doc, r"\[95 % bootstrap CI\] \| " + r" \| ".join([rf"{NUM} \[{NUM}, {NUM}\]"] * 6) + r" \|")
    for k in range(6):
        mean, low, high = geometric_ratio(a[:, k], b[:, k])
        agrees(cis[3 * k], mean), agrees(cis[3 * k + 1], low, slack=0.01), agrees(cis[3 * k + 2], high, slack=0.01)


# ---------------------------------------------------------------- optimality check (linear, paper profile)


def seed_rows(rep: dict, name: str) -> list[str]:
    """The report rows of a learned filter: "<name> (seed k)" for each training seed, or the row itself."""
    return list(learned_filters(rep["filters"]).get(name, {None: name}).values())


def test_linear_requirement_met_from_per_run_rmse():
    """ "DAOF-v1 ≤ 1.05× KF per state" on every seed: recomputed from the per-run RMSEs, not the stored ratios."""
    rep, doc = report("linear"), text("docs/results/README.md")
    pooled = {n: np.sqrt((np.asarray(f["per_run_rmse"]) ** 2).mean(0)) for n, f in rep["filters"].items()}

    def ratios(name):
        return np.stack([pooled[r] / pooled["KF"] for r in seed_rows(rep, name)])

    assert len(seed_rows(rep, "DAOF-v1")) == 3
    pos, vel, bound = quoted(
        doc, rf"DAOF-v1 is at most {NUM}× / {NUM}× the Kalman filter over its three seeds: the ≤ {NUM}×"
    )
    worst = ratios("DAOF-v1").max(0)
    agrees(pos, worst[0]), agrees(vel, worst[1])
    assert (worst <= float(bound)).all()
    requirements = [r for r in rep["requirements"] if r["requirement"].startswith("DAOF-v1 (seed ")]
    assert len(requirements) == 3 and all(r["met"] is True and "1.05" in r["requirement"] for r in requirements)
    stat_p, stat_v = quoted(doc, rf"The stationary Kalman filter, the optimum the paper names, is {NUM}× / {NUM}×")
    agrees(stat_p, (pooled["KF-stationary"] / pooled["KF"])[0])
    agrees(stat_v, (pooled["KF-stationary"] / pooled["KF"])[1])
    printed = quoted(
        doc, rf"learns the Kalman filter from the reward alone: {NUM}–{NUM}× /\s+{NUM}–{NUM}× over its three seeds"
    )
    v2 = ratios("DAOF-v2")
    for k, value in enumerate([v2[:, 0].min(), v2[:, 0].max(), v2[:, 1].min(), v2[:, 1].max()]):
        agrees(printed[k], value)
    assert f"the report written at {rep['commit']}, clean" in doc
    for name, prose in (("KalmanNet", "KalmanNet is at most"), ("SLF", "the SLF at most")):
        pos, vel = quoted(doc, rf"{prose} {NUM}× / {NUM}×")
        agrees(pos, ratios(name).max(0)[0]), agrees(vel, ratios(name).max(0)[1])


# ---------------------------------------------------------------- scenarios


def test_mismatch_claims():
    rep, doc, nominal = report("experiment1-mismatch"), text("docs/results/README.md"), report("experiment1")
    best = min(rep["filters"], key=lambda n: rmse(rep, n)[0])
    assert best == "PF-joint" == min(rep["filters"], key=lambda n: rmse(rep, n)[1])
    b, r = quoted(doc, rf"wins both states: \[{NUM}, {NUM}\]")
    agrees(b, rmse(rep, "PF-joint")[0]), agrees(r, rmse(rep, "PF-joint")[1])
    others = [n for n in rep["filters"] if n != "PF-joint"]
    assert min(others, key=lambda n: rmse(rep, n)[0]) == "SLF"
    assert min(others, key=lambda n: rmse(rep, n)[1]) == "PF-oracle"
    slf_b, oracle_b = quoted(doc, rf"the SLF wins on β \({NUM}; the PF-oracle with the nominal model {NUM}\)")
    agrees(slf_b, rmse(rep, "SLF")[0]), agrees(oracle_b, rmse(rep, "PF-oracle")[0])
    oracle_r, slf_r = quoted(doc, rf"the PF-oracle wins on r \({NUM}; the SLF {NUM}\)")
    agrees(oracle_r, rmse(rep, "PF-oracle")[1]), agrees(slf_r, rmse(rep, "SLF")[1])
    b, r = quoted(doc, rf"DAOF-v2 does not beat the model-based filters\*\* \(\[{NUM}, {NUM}\]\)")
    agrees(b, rmse(rep, "DAOF-v2")[0]), agrees(r, rmse(rep, "DAOF-v2")[1])
    assert all((rmse(rep, n) < rmse(rep, "DAOF-v2")).all() for n in ("EKF", "UKF", "PF", "PF-oracle"))
    room = rmse(rep, "PF-oracle") / rmse(rep, "PF-joint")
    b, r = quoted(doc, rf"PF-joint is {NUM}× / {NUM}× better than the nominal model")
    agrees(b, room[0]), agrees(r, room[1])
    # the increment form's gap on nominal is history (Experiment I's report of 1bbddfe; today's nominal row is
    # the paper's form): the two pages print the same range, and its low end exceeds the room on r
    old_report = "in Experiment I's report of 1bbddfe"
    (printed,) = quoted(doc, rf"its own gap on the nominal scenario \({RANGE}× on r over three seeds, {old_report}\)")
    assert float(printed.split("–")[0]) > room[1]
    scen = text("docs/scenarios.md")
    b, r = quoted(scen, rf"PF-joint is {NUM}× / {NUM}× better than the nominal-model PF-oracle")
    agrees(b, room[0]), agrees(r, room[1])
    (again,) = quoted(
        scen, rf"its own gap on the nominal scenario \({RANGE}× the PF-oracle over three seeds, {old_report}\)"
    )
    assert again == printed
    assert "has a gap on nominal's r below that room" in scen
    assert max(ratio_oracle(nominal, row)[1] for row in seed_rows(nominal, "DAOF-v2")) < room[1]


SCENARIO_ROWS = {
    "UKF": "UKF",
    "PF (1,000)": "PF",
    "PF-oracle (10,000)": "PF-oracle",
    "PF-joint (10,000)": "PF-joint",
    "SLF": "SLF",
    "DAOF-v2 (increment form)": "DAOF-v2",
    "DAOF-v1 (N = 20)": "DAOF-v1",
    "KalmanNet": "KalmanNet",
}


def test_scenario_tables():
    """docs/scenarios.md: the paper-profile mismatch table and the quick table of the three scenarios."""
    doc = text("docs/scenarios.md")
    mismatch = report("experiment1-mismatch")
    rows = {
        r"\*\*PF-joint \(20,000; infers μ and B: the scenario's Bayes filter\)\*\*": "PF-joint",
        r"PF-oracle \(20,000, nominal model\)": "PF-oracle",
        r"PF \(1,000\)": "PF",
        "UKF": "UKF",
        "EKF": "EKF",
        "SLF": "SLF",
        r"DAOF-v1 \(N = 20\)": "DAOF-v1",
        r"DAOF-v2 \(increment form\)": "DAOF-v2",
    }
    for prose, name in rows.items():
        for printed, value in zip(quoted(doc, rf"\| {prose} \| \**{NUM}\** \| \**{NUM}\** \|"), rmse(mismatch, name)):
            agrees(printed, value)
    pair = rf"\[{NUM}, {NUM}\]"
    quick = {sc: report(f"experiment1-scenarios-quick/{sc}/report") for sc in ("nominal", "mismatch", "outliers")}
    for prose, name in SCENARIO_ROWS.items():
        cells = rf"\| {re.escape(prose)} \| " + r" \| ".join(
            pair if name in quick[sc]["filters"] else "–" for sc in quick
        )
        values = [v for sc in quick if name in quick[sc]["filters"] for v in rmse(quick[sc], name)]
        for printed, value in zip(quoted(doc, cells + r" \|"), values, strict=True):
            agrees(printed, value)


def test_outliers_claims():
    rep, doc = report("experiment1-scenarios-quick/outliers/report"), text("docs/results/README.md")
    pf_b, pf_r, ukf_b, ukf_r = quoted(
        doc, rf"the PF wins on both states, \[{NUM}, {NUM}\] against the UKF's \[{NUM}, {NUM}\]"
    )
    agrees(pf_b, rmse(rep, "PF")[0]), agrees(pf_r, rmse(rep, "PF")[1])
    agrees(ukf_b, rmse(rep, "UKF")[0]), agrees(ukf_r, rmse(rep, "UKF")[1])
    # "the PF" wins: of the filters the report ranks (the 10,000-particle PF-oracle is the reference), on both
    for n in rep["filters"]:
        if n not in ("PF", "PF-oracle"):
            assert (rmse(rep, "PF") < rmse(rep, n)).all(), n
    assert report("experiment1-scenarios-quick/report")["winners"]["outliers"]["overall_without_oracle"] == "PF"
    assert (
        "At the quick budget KalmanNet and DAOF-v1 are below the UKF on both states, the SLF and DAOF-v2 above it"
        in doc
    )
    for n in ("KalmanNet", "DAOF-v1"):
        assert (paired(rep, n) < 1).all() and (paired(rep, n, "high") < 1).all(), n
    for n in ("SLF", "DAOF-v2"):
        assert (rmse(rep, n) > rmse(rep, "UKF")).all(), n


# ---------------------------------------------------------------- missing data (dropout, quick profile)

DROPOUT_ROWS = {
    "EKF": "EKF",
    "UKF": "UKF",
    "PF (1,000)": "PF",
    "PF-oracle (10,000)": "PF-oracle",
    "SLF (flags, trained through gaps)": "SLF",
    "DAOF-v2 (hold)": "DAOF-v2",
    "DAOF-v1 (prediction)": "DAOF-v1",
    "KalmanNet (innovation 0)": "KalmanNet",
}


def test_missing_data_table_and_percentages():
    base = "experiment1-scenarios-quick/{}/report"
    full, gaps = report(base.format("nominal")), report(base.format("nominal") + "/dropout")
    doc = text("docs/missing_data.md")
    pair = rf"\[{NUM}, {NUM}\]"
    for prose, name in DROPOUT_ROWS.items():
        got = quoted(doc, rf"\| {re.escape(prose)} \| {pair} \| {pair} \| \+{NUM} % / \+{NUM} % \|")
        for printed, value in zip(
            got, [*rmse(full, name), *rmse(gaps, name), *pct(rmse(gaps, name), rmse(full, name))]
        ):
            agrees(printed, value)
    a_y, yaw = quoted(doc, rf"measured missing: a_y {NUM} %, yaw rate {NUM} %")
    missing = gaps["dropout"]["missing_fraction"]
    agrees(a_y, 100 * missing[0]), agrees(yaw, 100 * missing[1])
    assert gaps["dropout"]["p"] == 0.1 and gaps["dropout"]["blackout"]["duration_s"] == 1.0
    mis_full, mis_gaps = report(base.format("mismatch")), report(base.format("mismatch") + "/dropout")
    b, r, db, dr = quoted(doc, rf"PF-joint stays the best on `mismatch` \({pair}, \+{NUM} % / \+{NUM} %\)")
    joint = rmse(mis_gaps, "PF-joint")
    agrees(b, joint[0]), agrees(r, joint[1])
    agrees(db, pct(joint, rmse(mis_full, "PF-joint"))[0]), agrees(dr, pct(joint, rmse(mis_full, "PF-joint"))[1])
    assert all((rmse(mis_gaps, n) >= joint).all() for n in mis_gaps["filters"])
    # "No filter produced a non-finite estimate, and no run diverged, in any of the three scenarios"
    for scenario in ("nominal", "mismatch", "outliers"):
        for f in report(base.format(scenario) + "/dropout")["filters"].values():
            assert f["diverged"] == 0 and all(math.isfinite(v) for v in f["rmse"])


def test_missing_data_readme_summary():
    doc = text("docs/results/README.md")
    full = report("experiment1-scenarios-quick/nominal/report")
    gaps = report("experiment1-scenarios-quick/nominal/report/dropout")
    p, blackout = quoted(doc, rf"Under the issue's dropout \({NUM} % gaps \+ {NUM} s yaw-rate blackout")
    agrees(p, 100 * gaps["dropout"]["p"]), agrees(blackout, gaps["dropout"]["blackout"]["duration_s"])
    lo, hi = quoted(doc, rf"The model-based filters, DAOF-v1 and KalmanNet lose {NUM}–{NUM} %")
    names = ("EKF", "UKF", "PF", "PF-oracle", "DAOF-v1", "KalmanNet")
    loss = np.stack([pct(rmse(gaps, n), rmse(full, n)) for n in names])
    agrees(lo, loss.min()), agrees(hi, loss.max())
    slf = pct(rmse(gaps, "SLF"), rmse(full, "SLF"))
    (slf_r,) = quoted(doc, rf"cuts its yaw-rate loss under the dropout from \+65 % to \+{NUM} %")
    agrees(slf_r, slf[1])
    (v2_r,) = quoted(doc, rf"DAOF-v2, which holds the last value, loses {NUM} % on yaw rate")
    agrees(v2_r, pct(rmse(gaps, "DAOF-v2"), rmse(full, "DAOF-v2"))[1])


# ---------------------------------------------------------------- Pendulum (no results.json: the page's own table)


def test_pendulum_table_is_consistent():
    """docs/pendulum.md: the per-seed returns give the quoted means, stds, differences and the verdict."""
    doc = text("docs/pendulum.md")
    seeds = {}
    for loss in ("DSAC-T", "SAC"):
        returns = [quoted(doc, rf"\| {loss} \| {s} \| −{NUM} \|")[0] for s in range(3)]
        seeds[loss] = -np.array([float(r) for r in returns])
        mean, std = quoted(doc, rf"\| \*\*{loss}\*\* \| mean ± std \(3 seeds\) \| \*\*−{NUM} ± {NUM}\*\*")
        # the seeds are printed to 0.1: the mean moves by <= 0.05 and the std by <= sqrt(3) * 0.05 / sqrt(2)
        agrees(mean, -seeds[loss].mean(), slack=0.05), agrees(std, seeds[loss].std(ddof=1), slack=0.062)
    assert (seeds["DSAC-T"] > -200).all()
    (diff,) = quoted(doc, rf"the difference of means, {NUM},")
    agrees(diff, seeds["DSAC-T"].mean() - seeds["SAC"].mean(), slack=0.1)
    paired = quoted(doc, rf"\(\+{NUM}, \+{NUM}, \+{NUM} for DSAC-T − SAC\)")
    for printed, value in zip(paired, seeds["DSAC-T"] - seeds["SAC"], strict=True):
        agrees(printed, value, slack=0.1)


def test_experiment2_against_the_paper():
    """The claim "DAOF-v2 10–85× ahead ..., against an SLF 12–120× less accurate than ours" (the page's paper rows)."""
    rep, doc = report("experiment2"), text("docs/results/README.md")
    page = text("docs/results/experiment2/README.md")
    row = r" \| ".join([rf"\*{NUM}\*"] * 6)
    paper_slf = np.array([float(v) for v in quoted(page, rf"\| \*paper, SLF\* \| {row} \|")])
    paper_v2 = np.array([float(v) for v in quoted(page, rf"\| \*paper, DAOF-v2\* \| {row} \|")])
    lo, hi, slf_lo, slf_hi = quoted(doc, rf"DAOF-v2 {NUM}–{NUM}× ahead on every state, against an SLF {NUM}–{NUM}×")
    ahead, ours = paper_slf / paper_v2, paper_slf / rmse(rep, "SLF")
    agrees(lo, ahead.min(), slack=0.5), agrees(hi, ahead.max(), slack=0.5)  # printed to 2 significant digits
    agrees(slf_lo, ours.min(), slack=0.5), agrees(slf_hi, ours.max(), slack=5)


def test_linear_report_table():
    """docs/results/linear/README.md: RMSE, ratio to the KF over all steps and cost of every row (every seed's);
    docs/linear_check.md: each filter's range over its seeds."""
    rep, doc = report("linear"), text("docs/results/linear/README.md")
    names = {
        "KF": "KF (time-varying gain from the prior: the optimum)",
        "KF-stationary": "KF-stationary (the steady-state gain: the optimum the paper names)",
        "PF": "PF (1,000)",
    }
    cell = r"\**\[" + NUM + ", " + NUM + r"\]\**"
    for name in rep["filters"]:
        prose = re.escape(names.get(name, name))
        calibration = rf"{NUM} / {NUM}; {NUM} / {NUM} %"  # NEES; ±2σ coverage per state
        got = quoted(doc, rf"\| \**{prose}\** \| {cell} \| \**{NUM} / {NUM}\** \| {calibration} \| {NUM} ms \|")
        row = rep["filters"][name]
        coverage = [100 * v for v in row["coverage_2sigma"]]
        values = [*rmse(rep, name), *ratio_oracle(rep, name), *row["nees"], *coverage, row["cost_ms"]]
        for printed, value in zip(got, values, strict=True):
            agrees(printed, value)
    check = text("docs/linear_check.md")
    rows = {"KalmanNet": "KalmanNet", "SLF, N = 20": "SLF", "DAOF-v2, N = 20": "DAOF-v2"}
    for prose, name in rows.items():
        printed = quoted(check, rf"\| {re.escape(prose)} \| {NUM}–{NUM} / {NUM}–{NUM} \|")
        r = np.stack([ratio_oracle(rep, row) for row in seed_rows(rep, name)])
        for k, value in enumerate([r[:, 0].min(), r[:, 0].max(), r[:, 1].min(), r[:, 1].max()]):
            agrees(printed[k], value)
    v1 = np.stack([ratio_oracle(rep, row) for row in seed_rows(rep, "DAOF-v1")])
    for printed, value in zip(quoted(check, rf"\| DAOF-v1, N = 20 \| {NUM} / {NUM} on every seed \|"), v1.max(0)):
        agrees(printed, value)
    assert np.allclose(v1.min(0), v1.max(0), atol=5e-4)


# ---------------------------------------------------------------- a system daof does not ship (UNGM)


def test_ungm_table_and_the_gap_daof_v1_closes():
    """docs/results/ungm/README.md: every row of its table, and the share of the UKF–reference gap DAOF-v1 closes."""
    rep, doc = report("ungm"), text("docs/results/ungm/README.md")
    pooled = {n: float(np.sqrt((np.asarray(f["per_run_rmse"]) ** 2).mean())) for n, f in rep["filters"].items()}
    reference = rep["reference"]
    for name in rep["filters"]:
        cell = rf"\| \**{re.escape(name)}(?: \([^)|]*\))?\** \|"  # the name, then its budget or particles
        pattern = rf"{cell} \**{NUM}\** \| \**{NUM}\** \|"
        value, ratio = quoted(doc, pattern)
        agrees(value, pooled[name], slack=1e-3 * pooled[name]), agrees(ratio, pooled[name] / pooled[reference])
        if name != "UKF":
            paired = rep["paired_with"]["filters"][name]
            row = rf"{cell}[^|]*\|[^|]*\| \**{NUM} \[{NUM}, {NUM}\]\** \| {NUM} / 100"
            for printed, key in zip(quoted(doc, row), ("ratio", "low", "high", "better_runs")):
                agrees(printed, paired[key][0])
    (share,) = quoted(doc, rf"DAOF-v1 closes {NUM} % of the gap between the UKF and the converged reference")
    closed = (pooled["UKF"] - pooled["DAOF-v1"]) / (pooled["UKF"] - pooled[reference])
    agrees(share, 100 * closed)
    assert closed >= 0.5 and rep["paired_with"]["filters"]["DAOF-v1"]["high"][0] < 1
    assert rep["reference_check"]["how"] == "converged"
    # DAOF-v2 a close second to the SLF, run by run; the learned filters' error std calibrated, the UKF's not
    assert "- x: **SLF**, 0.977 [0.969, 0.986] × DAOF-v2" in learned_winners(rep)
    assert "the SLF's RMSE is 0.977 [0.969, 0.986] × DAOF-v2's" in doc
    (gap,) = quoted(doc, rf"is {NUM} % behind plain regression on the window")
    agrees(gap, pct(np.asarray(pooled["DAOF-v2"]), np.asarray(pooled["SLF"])))
    learned = [row for seeds in learned_filters(rep["filters"]).values() for row in seeds.values()]
    nees = [rep["filters"][n]["nees"][0] for n in learned]
    cover = [100 * rep["filters"][n]["coverage_2sigma"][0] for n in learned]
    printed = quoted(
        doc,
        rf"calibrated \(NEES {NUM}–{NUM}, ±2σ coverage {NUM}–{NUM} %\); "
        rf"the UKF's is not \(NEES {NUM}, coverage {NUM} %\)",
    )
    for text_, value in zip(printed, [min(nees), max(nees), min(cover), max(cover)]):
        agrees(text_, value)
    agrees(printed[4], rep["filters"]["UKF"]["nees"][0])
    agrees(printed[5], 100 * rep["filters"]["UKF"]["coverage_2sigma"][0])


def test_experiment1_calibration_as_uncertainty_md_quotes_it():
    """docs/uncertainty.md: the NEES and ±2σ coverage ranges of the Experiment I report's learned rows."""
    rep, doc = report("experiment1"), text("docs/uncertainty.md")
    rows = [row for seeds in learned_filters(rep["filters"]).values() for row in seeds.values()]
    nees = [x for n in rows for x in rep["filters"][n]["nees"]]
    cover = [100 * x for n in rows for x in rep["filters"][n]["coverage_2sigma"]]
    count, *printed = quoted(
        doc, rf"over its {NUM} learned filter × seed rows NEES {NUM}–{NUM} and ±2σ coverage {NUM}–{NUM} %"
    )
    assert int(count) == len(rows) == 12
    for text_, value in zip(printed, [min(nees), max(nees), min(cover), max(cover)], strict=True):
        agrees(text_, value)
    assert all(0.8 <= x <= 1.25 for x in nees) and all(93 <= x <= 97 for x in cover)  # the targets, met
