"""README.md's results are the committed reports': the generated tables match results.json, and
the README's sentences about them hold."""

import json
import subprocess
import sys
from pathlib import Path

import torch

from daof.evaluate.metrics import paired_rmse_ratio
from daof.evaluate.summary import (
    BEGIN,
    END,
    Headline,
    headline_table,
    learned_filters,
    learned_winners,
    summary_markdown,
)

ROOT = Path(__file__).resolve().parents[1]


def _results(report: str) -> dict:
    return json.loads((ROOT / "docs/results" / report / "results.json").read_text())


def _paired(results: dict, name: str, reference: str) -> dict:
    f = results["filters"]
    runs = (torch.tensor(f[n]["per_run_rmse"], dtype=torch.float64) for n in (name, reference))
    return paired_rmse_ratio(*runs)


def test_the_readme_holds_the_generated_summary():
    readme = (ROOT / "README.md").read_text()
    block = readme[readme.index(BEGIN) : readme.index(END) + len(END)]
    assert block == summary_markdown(ROOT), "run scripts/results_summary.py"


def test_the_summary_script_checks_the_readme():
    done = subprocess.run([sys.executable, str(ROOT / "scripts/results_summary.py"), "--check"], capture_output=True)
    assert done.returncode == 0, done.stderr.decode()


def test_experiment1_daof_v1_and_kalmannet_tie_and_beat_the_ukf_as_the_readme_says():
    r = _results("experiment1")
    f = r["filters"]
    seeds = {name: list(rows.values()) for name, rows in learned_filters(f).items()}
    assert set(seeds) == {"DAOF-v1", "KalmanNet", "SLF", "DAOF-v2"} and all(
        len(rows) == 3 for rows in seeds.values()
    )  # "three training seeds per learned filter"
    readme = " ".join((ROOT / "README.md").read_text().split())
    lines = learned_winners(r)  # "tie": the pooled intervals both reach 1, printed as in the README
    assert "- beta: no clear winner, KalmanNet 0.995 [0.981, 1.010] × DAOF-v1; lower on 2 of 3 seeds" in lines
    assert "- yaw_rate: no clear winner, DAOF-v1 0.999 [0.989, 1.009] × KalmanNet; lower on 2 of 3 seeds" in lines
    assert "KalmanNet / DAOF-v1 is 0.995 [0.981, 1.010] on β and DAOF-v1 / KalmanNet 0.999 [0.989, 1.009]" in readme
    margins = []
    for row in seeds["DAOF-v1"] + seeds["KalmanNet"]:
        c = _paired(r, row, "UKF")
        assert all(x < 1 for x in c["ratio"])  # "each beats the UKF on both states with every seed"
        margins += [100 * (1 - x) for x in c["ratio"]]
        assert all(1.0 < x < 1.1 for x in f[row]["ratio_to_oracle"])  # "a few per cent above the PF-oracle"
    assert 1 <= round(min(margins)) and round(max(margins)) <= 4  # "by 1–4 %"
    cost = {name: [f[n]["cost_ms"] for n in rows] for name, rows in seeds.items()}
    times = [kn / v1 for kn, v1 in zip(cost["KalmanNet"], cost["DAOF-v1"], strict=True)]  # seed by seed
    assert 2 <= round(min(times)) and round(max(times)) <= 3  # "KalmanNet costs 2–3× more per estimate"
    ukf = f["UKF"]["rmse"]
    for name in ("SLF", "DAOF-v2"):  # "behind the model-based filters with every seed"
        assert all(f[row]["rmse"][j] > ukf[j] for row in seeds[name] for j in range(2))


def test_experiment2_daof_v2_leads_the_slf_on_five_states():
    c = _paired(_results("experiment2"), "DAOF-v2", "SLF")
    assert sum(h < 1 for h in c["high"]) == 5 and c["low"][2] < 1 < c["high"][2]


def _ratios(results: dict, name: str) -> list[list[float]]:
    """The ratio to the reference of every seed of a learned filter ("<name> (seed k)" rows)."""
    rows = learned_filters(results["filters"])[name].values()
    return [results["filters"][n]["ratio_to_oracle"] for n in rows]


def test_linear_check_numbers_in_the_readme():
    r = _results("linear")
    assert len(_ratios(r, "DAOF-v1")) == 3  # "on each of three training seeds"
    for seed in _ratios(r, "DAOF-v1"):
        assert all(abs(x - 1.0) < 1e-4 for x in seed)  # "the Kalman filter itself"
    v2 = [x for s in _ratios(r, "DAOF-v2") for x in s]  # "within 1.5–2.1 % of the Kalman filter"
    assert [round(100 * (min(v2) - 1), 1), round(100 * (max(v2) - 1), 1)] == [1.5, 2.1]
    slf = [x for s in _ratios(r, "SLF") for x in s]  # "closer than the SLF's regression"
    assert max(v2) < min(slf)
    learned = [n for n in r["filters"] if n.split(" (")[0] in ("SLF", "DAOF-v1", "DAOF-v2", "KalmanNet")]
    nees = [v for n in learned for v in r["filters"][n]["nees"]]  # "NEES 0.98–1.04"
    cover = [100 * v for n in learned for v in r["filters"][n]["coverage_2sigma"]]  # "94.9–95.6 %"
    assert [round(min(nees), 2), round(max(nees), 2)] == [0.98, 1.04]
    assert [round(min(cover), 1), round(max(cover), 1)] == [94.9, 95.6]
    assert all(0.995 <= x <= 1.005 for s in _ratios(r, "KalmanNet") for x in s)  # "within 0.5 %"
    assert {round(100 * (x - 1)) for s in _ratios(r, "SLF") for x in s} <= {7, 8, 9}  # "7–9 % above it"


def test_ungm_numbers_in_the_readme():
    r = _results("ungm")
    f, ukf = r["filters"], r["filters"]["UKF"]["rmse"][0]
    assert 1.9 < ukf / f["PF-oracle"]["rmse"][0] < 2.1  # "the UKF is 2× a converged particle filter"
    assert r["reference_check"]["how"] == "converged"
    beats = {n for n in ("SLF", "DAOF-v2", "DAOF-v1", "KalmanNet") if _paired(r, n, "UKF")["high"][0] < 1}
    assert beats == {"SLF", "DAOF-v2", "DAOF-v1"}  # "every learned filter but KalmanNet beats the UKF"
    assert min(f, key=lambda n: f[n]["rmse"][0] if n in beats else float("inf")) == "SLF"  # "the SLF most"
    closed = (ukf - f["DAOF-v1"]["rmse"][0]) / (ukf - f["PF-oracle"]["rmse"][0])
    assert closed > 0.5  # "closes more than half of the UKF's gap"


def _toy_results(per_run: dict) -> dict:
    """A results.json of two states whose filters have the given per-run RMSEs [runs, 2]."""
    filters = {n: {"per_run_rmse": r.tolist(), "rmse": r.pow(2).mean(0).sqrt().tolist()} for n, r in per_run.items()}
    return {"states": ["a", "b"], "filters": filters}


def test_learned_winners_names_the_best_learned_filter_per_state_over_its_seeds():
    g = torch.Generator().manual_seed(0)
    base = 1 + torch.rand(40, 2, generator=g)
    per_run = {
        "UKF": 0.5 * base,  # not learned: never a winner
        "DAOF-v1 (seed 1)": base * torch.tensor([0.90, 1.0]),
        "DAOF-v1 (seed 2)": base * torch.tensor([0.80, 1.0]),
        "SLF (seed 1)": base * torch.tensor([1.00, 1.001]),
        "SLF (seed 2)": base * torch.stack([torch.full((40,), 0.85), 1 + 0.1 * torch.randn(40, generator=g)], 1),
        "DAOF-v1 (N=5)": 0.1 * base,  # the window study: not compared
    }
    lines = learned_winners(_toy_results(per_run))
    a, b = (line for line in lines if line.startswith("- "))
    ratio = ((0.9**2 + 0.8**2) / (1 + 0.85**2)) ** 0.5  # over seeds, pooled: 0.917
    assert a == f"- a: **DAOF-v1**, {ratio:.3f} [{ratio:.3f}, {ratio:.3f}] × SLF; lower on 2 of 2 seeds"
    rmse_b = {n: r[:, 1].pow(2).mean().sqrt() for n, r in per_run.items()}
    lower = sum(rmse_b[f"DAOF-v1 (seed {k})"] < rmse_b[f"SLF (seed {k})"] for k in (1, 2))
    assert b.startswith("- b: no clear winner, DAOF-v1 ") and b.endswith(f"× SLF; lower on {lower} of 2 seeds")
    assert learned_winners(_toy_results({"UKF": base, "SLF": base})) == []


def test_a_filter_trained_on_several_seeds_is_one_row_of_the_summary(tmp_path):
    g = torch.Generator().manual_seed(1)
    base = 1 + torch.rand(30, 2, generator=g)
    per_run = {"UKF": base, **{f"SLF (seed {k})": base * (0.9 + 0.05 * k) for k in (1, 2, 3)}, "SLF (N=5)": base}
    results = {**_toy_results(per_run), "runs": 30, "steps": 10, "profile": "toy", "reference": "UKF"}
    for name, row in results["filters"].items():
        row["cost_ms"] = {"UKF": 0.2, "SLF (seed 1)": 0.1, "SLF (seed 2)": 0.2, "SLF (seed 3)": 0.3}.get(name)
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "results.json").write_text(json.dumps(results))
    rows = [line for line in headline_table(tmp_path, Headline("toy", "r")) if line.startswith("| ")][1:]
    pooled = ((0.95**2 + 1.0**2 + 1.05**2) / 3) ** 0.5
    assert [r.split(" | ")[0] for r in rows] == ["| UKF", "| SLF (3 seeds)", "| SLF (N=5)"]
    assert rows[1].split(" | ")[1] == f"{pooled:.3f} [{pooled:.3f}, {pooled:.3f}] (seeds 0.950–1.050)"
    assert rows[1].endswith(" | 0.200 |") and rows[2].endswith(" | – |")
