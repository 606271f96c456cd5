"""The study's reference, checked: the first candidate that is exact or converged, else the best filter.

The candidates are the experiment's ``reference`` list, in order, among the classical filters that
run on the scenario. An ``exact`` one (the Kalman filter of a linear-Gaussian system) is the
posterior mean itself and is taken as it is. A particle filter is run again with twice its
particles (``convergence_check.seed``) on the same data; it has converged when its RMSE moves by
less than ``convergence_check.limit_percent`` on every state, and is then taken. A candidate marked
``fallback`` runs only when the ones before it fail (it then joins the study's rows). When none is
exact or converged, the ratios are to the best filter of the study (``best_filter``), never to an
unconverged one, and the report says so.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from daof.evaluate.study import Study, run_study
from daof.fingerprint import classical_fingerprint

__all__ = ["Candidate", "ReferenceChoice", "best_filter", "choose_reference", "doubled_change"]


@dataclass
class Candidate:
    """One reference candidate and what its check found."""

    name: str
    exact: bool = False
    particles: int | None = None  # a particle filter's count (doubled by the check)
    change_percent: list[float] | None = None  # RMSE change per state with twice the particles
    converged: bool = False


@dataclass
class ReferenceChoice:
    """Which filter the ratios are relative to and why (``how``: exact | converged | best | none)."""

    name: str | None
    how: str
    limit_percent: float
    seed: int
    candidates: list[Candidate] = field(default_factory=list)

    def lines(self) -> list[str]:
        """The report's plain lines: every candidate's check, then what the ratios are relative to."""
        out = []
        for c in self.candidates:
            if c.exact:
                out.append(
                    f"Reference: {c.name}, exact (the Kalman filter of a linear-Gaussian system is the posterior "
                    "mean): it needs no convergence check."
                )
                continue
            change = ", ".join(f"{v:.2f} %" for v in c.change_percent)
            verdict = "converged" if c.converged else "not converged"
            out.append(
                f"{'Reference: ' if c.converged else ''}{c.name} ({c.particles} particles), convergence check: with "
                f"{2 * c.particles} particles (seed {self.seed}) its RMSE changes by {change} per state "
                f"(converged: < {self.limit_percent:g} % on every state): {verdict}."
            )
        if self.how == "best":
            failed = ", ".join(c.name for c in self.candidates) or "none runs on this scenario"
            out.append(
                f"No reference candidate converged ({failed}): the ratios are to the best filter of this study, "
                f"{self.name} (lowest mean over states of RMSE / the lowest RMSE on that state, the unconverged "
                "candidates left out), not to an optimum."
            )
        return out

    def to_json(self) -> dict:
        return asdict(self)


def best_filter(study: Study, exclude=()) -> str | None:
    """The filter with the lowest mean over states of RMSE / the lowest RMSE on that state among the
    filters considered (those not in ``exclude`` with a finite RMSE on every state); None if there is none."""
    names = [n for n, r in study.results.items() if n not in exclude and all(math.isfinite(v) for v in r.rmse)]
    if not names:
        return None
    rmse = torch.tensor([study.results[n].rmse for n in names], dtype=torch.float64)
    score = (rmse / rmse.min(0).values).mean(1)
    return names[int(score.argmin())]


def doubled_change(study: Study, name: str, filt, seed: int, cache_dir: Path, log=print) -> list[float]:
    """``filt`` (study row ``name``) with twice its particles on the study's data: |ΔRMSE| / RMSE per state, in %."""
    doubled = type(filt)(study.system, 2 * filt.num_particles, seed=seed)
    label = f"{name} (N={doubled.num_particles})"
    again = run_study(
        study.system,
        {label: doubled},
        study.runs,
        study.steps,
        study.seed,
        measure_cost=False,
        cache_dir=cache_dir,
        log=log,
        versions={label: classical_fingerprint(doubled, study.system)},
        reference=None,
        calibrate=False,  # the check compares RMSEs only: no second pass for the particle spread
    )
    base = torch.tensor(study.results[name].rmse, dtype=torch.float64)
    twice = torch.tensor(again.results[label].rmse, dtype=torch.float64)
    return ((twice - base).abs() / base * 100).tolist()


def choose_reference(
    study: Study,
    candidates: list[str],
    filters: dict,
    exact: set[str],
    *,
    limit_percent: float,
    seed: int,
    cache_dir: Path,
    timing_threads: int = 1,
    log=print,
) -> ReferenceChoice:
    """Check the ``candidates`` in order and make the chosen one the study's reference (``Study.set_reference``).

    ``filters``: name -> the classical filter of every candidate that runs on this scenario; one that
    is not yet a row of the study (a fallback) is run and joins it. ``exact``: the candidates that need
    no check. With no candidates at all the study keeps no reference.
    """
    choice = ReferenceChoice(None, "none", limit_percent, seed)
    if not candidates:
        study.set_reference(None)
        return _keep(study, choice)
    for name in (c for c in candidates if c in filters):
        if name in exact:
            choice.candidates.append(Candidate(name, exact=True, converged=True))
            choice.name, choice.how = name, "exact"
            break
        if name not in study.results:  # a fallback: run now, a row of the study from here on
            log(f"reference: {name} runs because the candidates before it did not converge")
            extra = run_study(
                study.system,
                {name: filters[name]},
                study.runs,
                study.steps,
                study.seed,
                timing_threads,
                cache_dir=cache_dir,
                log=log,
                versions={name: classical_fingerprint(filters[name], study.system)},
                reference=None,
            )
            study.results[name], study.estimates[name] = extra.results[name], extra.estimates[name]
        change = doubled_change(study, name, filters[name], seed, cache_dir, log)
        converged = all(v < limit_percent for v in change)
        choice.candidates.append(Candidate(name, False, filters[name].num_particles, change, converged))
        if converged:
            choice.name, choice.how = name, "converged"
            break
    if choice.name is None:
        choice.name, choice.how = best_filter(study, exclude={c.name for c in choice.candidates}), "best"
    study.set_reference(choice.name)
    return _keep(study, choice)


def _keep(study: Study, choice: ReferenceChoice) -> ReferenceChoice:
    study.reference_check = choice.to_json()
    return choice
