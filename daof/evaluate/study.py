"""Run the Monte Carlo study: simulate once, replay to every filter, collect the metrics.

The data set is generated once from the evaluation seed and every filter sees exactly the same
true states, measurements and controls. Each filter's result (metrics and estimates) is cached
in ``cache_dir`` as soon as it is finished (written atomically, so an interruption never leaves a
half-written entry), so an interrupted study restarts where it stopped.
With ``dropout`` (``daof.evaluate.dropout.Dropout``) the measurements of that data set get NaN
gaps before any filter sees them; the cache keeps those results apart from the complete-data ones.
A filter that gives an error std (``Filter.std_source``) also gets its calibration: NEES and ±2σ
coverage per state (``FilterResult.nees``, ``coverage_2sigma``), from the same pass as its estimates.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from tqdm import tqdm

from daof.envs.recorded import cache_key
from daof.envs.system import StochasticSystem
from daof.evaluate.dropout import Dropout
from daof.evaluate.metrics import DIVERGENCE_FACTOR, calibration, diverged_runs, per_run_rmse, pooled_rmse
from daof.evaluate.timing import cost_per_estimate, threads, throughput
from daof.io import atomic_save, safe_load

__all__ = ["FilterResult", "Study", "run_study"]

ORACLE = "PF-oracle"


@dataclass
class FilterResult:
    """One row of the study (the fields of results.json)."""

    rmse: list[float]
    per_run_rmse: list[list[float]]
    cost_ms: float | None
    threads: int
    throughput_per_s: float
    diverged: int = 0
    repairs: int = 0
    #: the runs counted in ``diverged`` (``_add_oracle_metrics``)
    diverged_runs: list[int] = field(default_factory=list)
    #: per state, the fraction of estimates at a bound of a learned filter's output; None: no bounds
    saturated: list[float] | None = None
    ratio_to_oracle: list[float] | None = None
    wall_s: float = 0.0
    extra: dict = field(default_factory=dict)
    #: where the filter's error std comes from (``Filter.std_source``); None: it gives none, and so the three below
    std_source: str | None = None
    #: per state, the mean of e²/σ² over every run and step (``metrics.calibration``; 1 when calibrated)
    nees: list[float] | None = None
    #: per state, the share of estimates with |e| ≤ 2σ (95.45 % when calibrated)
    coverage_2sigma: list[float] | None = None
    #: per state, the entries left out of both (non-finite error, σ non-finite or ≤ 0)
    std_excluded: list[int] | None = None


@dataclass
class Study:
    """The data, every filter's estimates and results, and what identifies the study."""

    system: StochasticSystem
    runs: int
    steps: int
    seed: int
    data: TensorDict
    results: dict[str, FilterResult]
    estimates: dict[str, torch.Tensor]
    #: ``Dropout.describe()`` plus the measured ``missing_fraction`` per channel; None: complete data
    dropout: dict | None = None
    #: the filter every ``ratio_to_oracle`` is relative to (PF-oracle, or the KF on the linear system);
    #: None when the study has no such filter
    reference: str | None = None
    #: how the reference was chosen and checked (``daof.experiments.reference.ReferenceChoice.to_json``)
    reference_check: dict | None = None

    def set_reference(self, name: str | None) -> None:
        """Make ``name`` the reference: every filter's ratios and diverged runs are taken relative to it again."""
        _add_oracle_metrics(self.results, name, self.estimates, self.system)
        self.reference = name if name in self.results else None

    def to_json(self) -> dict:
        s = self.system
        extra = {"dropout": self.dropout} if self.dropout is not None else {}
        if self.reference_check is not None:
            extra["reference_check"] = self.reference_check
        return {
            "system": s.name,
            "scenario": s.scenario,
            "runs": self.runs,
            "steps": self.steps,
            "seed": self.seed,
            "states": list(s.state_names),
            "units": list(s.state_units),
            "reference": self.reference,
            **extra,
            "filters": {name: asdict(r) for name, r in self.results.items()},
        }


def _cache_path(cache_dir: Path, name: str, dropout: dict | None = None) -> Path:
    stem = re.sub(r"[^A-Za-z0-9_.=-]+", "_", name)
    if dropout is not None:  # a file of its own, so complete and dropout studies can share cache_dir
        stem += "@dropout-" + hashlib.sha1(json.dumps(dropout, sort_keys=True).encode()).hexdigest()[:10]
    return cache_dir / (stem + ".pt")


def _with_progress(filt, data: TensorDict, label: str, fn):
    """``fn(filt, data)`` with a bar on a terminal (tqdm's disable=None: quiet elsewhere), fed by the filter's steps."""
    with tqdm(total=data.numel(), desc=f"  {label}", unit="step", unit_scale=True, leave=False, disable=None) as bar:
        filt.progress = bar.update
        try:
            return fn(filt, data)
        finally:
            filt.progress = None


def _calibration_fields(filt, estimates: torch.Tensor, std: torch.Tensor | None, truth: torch.Tensor) -> dict:
    """The FilterResult fields of the filter's std; none for a filter without one."""
    if std is None:
        return {}
    c = calibration(estimates, truth.to(estimates.device), std)
    return {
        "std_source": filt.std_source,
        "nees": c["nees"],
        "coverage_2sigma": c["coverage"],
        "std_excluded": c["excluded"],
    }


def _evaluate_one(
    filt, data: TensorDict, timing_threads: int, measure_cost: bool, name: str = "", calibrate: bool = True
) -> tuple[FilterResult, torch.Tensor]:
    # one pass gives the estimates and, with ``calibrate``, the std beside them (``run_with_std``'s
    # estimates are ``run``'s): the throughput then includes reading the std out
    rate, estimates, std, wall = _with_progress(filt, data, name, lambda f, d: throughput(f, d, with_std=calibrate))
    truth = data["state"]
    # the stats of the study's run: timing at batch 1 below runs the filter again
    stats = dict(getattr(filt, "stats", {}) or {})
    cost = None
    if measure_cost:
        with threads(timing_threads):
            cost = cost_per_estimate(filt, data)
    saturated = stats.get("saturated")
    std_fields = _calibration_fields(filt, estimates, std, truth)
    result = FilterResult(
        rmse=pooled_rmse(estimates, truth).tolist(),
        per_run_rmse=per_run_rmse(estimates, truth).tolist(),
        cost_ms=cost,
        threads=timing_threads,
        throughput_per_s=rate,
        repairs=int(stats.get("repairs", 0)),
        saturated=[float(v) for v in saturated] if saturated is not None else None,
        wall_s=wall,
        extra={k: v for k, v in stats.items() if k != "repairs" and isinstance(v, (int, float, str))},
        **std_fields,
    )
    return result, estimates.float()


def run_study(
    system: StochasticSystem,
    filters: dict,
    runs: int,
    steps: int,
    seed: int,
    timing_threads: int = 1,
    measure_cost: bool = True,
    cache_dir: str | Path | None = None,
    log=print,
    dropout: Dropout | None = None,
    versions: dict[str, str] | None = None,
    reference: str = ORACLE,
    device: torch.device | str = "cpu",
    calibrate: bool = True,
) -> Study:
    """Evaluate every filter in ``filters`` (name -> object with ``run(data)``) on one data set.

    ``dropout``: filter the same simulated data with the measurement gaps it describes instead.
    ``versions``: per filter name, a string that identifies its weights (e.g. a checkpoint digest);
    it is part of the cache key, so a retrained filter is evaluated again instead of reused.
    ``reference``: the filter the ratios and the diverged-run threshold are relative to (the
    protocol's PF-oracle; the exact Kalman filter ``"KF"`` on the linear system).
    ``device``: where the learned filters (``torch.nn.Module``s, already there) filter; the data is
    simulated on the CPU and moved there once, their estimates come back.
    ``calibrate``: for every filter with an error std (``Filter.std_source``), also its NEES and ±2σ
    coverage per state (``metrics.calibration``), from the same pass (``run_with_std``).
    """
    data = system.simulate(runs, steps, seed)
    # the system's parameters are part of the key: a study of another μ never reuses this one's results
    key = {k: v for k, v in cache_key(system, runs, steps, seed).items() if k not in ("format", "device")}
    dropout_info = None
    if dropout is not None:
        data = dropout.apply(data, system)
        key["dropout"] = dropout.describe()
        missing = torch.isnan(data["measurement"]).double().mean((0, 1)).tolist()
        dropout_info = {**key["dropout"], "missing_fraction": missing}
        log(f"dropout {key['dropout']}: missing fraction per channel " + ", ".join(f"{m:.3f}" for m in missing))
    cache = Path(cache_dir) if cache_dir is not None else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    results: dict[str, FilterResult] = {}
    estimates: dict[str, torch.Tensor] = {}
    moved = None  # the data on ``device``, made once
    for i, (name, filt) in enumerate(filters.items(), 1):
        path = _cache_path(cache, name, key.get("dropout")) if cache is not None else None
        filter_key = {**key, "version": (versions or {}).get(name)}
        source = getattr(filt, "std_source", None) if calibrate else None
        if source is not None:  # a result without the std's metrics is not reused for one with them
            filter_key["std"] = source
        blob = _read_cache(path, log) if path is not None else None
        if blob is not None and blob["key"] == filter_key:
            results[name], estimates[name] = FilterResult(**blob["result"]), blob["estimates"]
            log(f"[{i}/{len(filters)}] {name}: reused finished result ({path})")
            continue
        log(f"[{i}/{len(filters)}] {name}: filtering {runs} runs x {steps} steps ...")
        on_device = isinstance(filt, torch.nn.Module) and torch.device(device) != data.device
        if on_device and moved is None:
            moved = data.to(device)
        result, est = _evaluate_one(filt, moved if on_device else data, timing_threads, measure_cost, name, calibrate)
        est = est.to(data.device)
        results[name], estimates[name] = result, est
        rmse = ", ".join(f"{v:.4g}" for v in result.rmse)
        cost = f", cost {result.cost_ms:.3f} ms/estimate" if result.cost_ms is not None else ""
        calibrated = ""
        if result.nees is not None:
            nees = ", ".join(f"{v:.3g}" for v in result.nees)
            cover = ", ".join(f"{100 * v:.1f} %" for v in result.coverage_2sigma)
            calibrated = f"; NEES [{nees}], ±2σ coverage [{cover}] ({result.std_source})"
        log(f"[{i}/{len(filters)}] {name}: RMSE [{rmse}]{cost}, {result.wall_s:.1f} s{calibrated}")
        if path is not None:
            atomic_save({"key": filter_key, "result": asdict(result), "estimates": est}, path)
    _add_oracle_metrics(results, reference, estimates, system)
    ref = reference if reference in results else None
    return Study(system, runs, steps, seed, data, results, estimates, dropout=dropout_info, reference=ref)


def _read_cache(path: Path, log) -> dict | None:
    """A cached result, or None if there is none or it cannot be read (it is then computed again)."""
    if not path.is_file():
        return None
    try:
        blob = safe_load(path, map_location=None)  # plain data only: a crafted entry is refused, never run
    except ValueError as error:  # truncated, foreign or crafted file
        log(f"unreadable cache entry: {error}; computing it again")
        return None
    return blob if isinstance(blob, dict) and {"key", "result", "estimates"} <= blob.keys() else None


def _add_oracle_metrics(
    results: dict[str, FilterResult],
    reference: str = ORACLE,
    estimates: dict[str, torch.Tensor] | None = None,
    system: StochasticSystem | None = None,
) -> None:
    """Ratio to the reference (PF-oracle) per state, and every filter's diverged runs.

    A run has diverged when an estimate is non-finite or outside the system's
    ``divergence_limits`` (with ``estimates`` and ``system``), or when its RMSE on some state is
    above ``DIVERGENCE_FACTOR`` (10)× the reference's RMSE on the same run.
    """
    oracle = results.get(reference)
    oracle_rmse = torch.tensor(oracle.rmse, dtype=torch.float64) if oracle is not None else None
    oracle_runs = torch.tensor(oracle.per_run_rmse, dtype=torch.float64) if oracle is not None else None
    for name, r in results.items():
        run_rmse = torch.tensor(r.per_run_rmse, dtype=torch.float64)
        implausible = None
        if estimates is not None and system is not None and name in estimates:
            implausible = system.diverged_runs(estimates[name])
        mask = diverged_runs(run_rmse, oracle_runs, DIVERGENCE_FACTOR, implausible)
        r.diverged, r.diverged_runs = int(mask.sum()), mask.nonzero().flatten().tolist()
        r.ratio_to_oracle = None
        if oracle_rmse is not None:
            r.ratio_to_oracle = (torch.tensor(r.rmse, dtype=torch.float64) / oracle_rmse).tolist()
