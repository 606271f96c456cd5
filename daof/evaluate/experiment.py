"""Small pieces the experiment recipes share: the profile, what trained filters report, study caching.

An experiment recipe (``recipes/*/experiment.py``) trains its learned filters as ``TrainingJob``s,
loads their best checkpoints, runs the study and writes the report; these helpers keep the parts
that are the same for every experiment in one place.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from omegaconf import DictConfig

from daof.evaluate.jobs import TrainingJob

__all__ = ["checkpoint_fingerprint", "learning_curves", "select_profile", "training_costs"]


def select_profile(cfg: DictConfig) -> DictConfig:
    """``cfg.profiles[cfg.profile]``; an unknown profile name exits with the valid ones."""
    if cfg.profile not in cfg.profiles:
        raise SystemExit(f"unknown profile {cfg.profile!r}; valid: {list(cfg.profiles)}")
    return cfg.profiles[cfg.profile]


def learning_curves(filters: dict, names=None) -> dict[str, list[dict]]:
    """Validation history saved in each learned filter's checkpoint (name -> list of records)."""
    names = names if names is not None else list(filters)
    return {name: getattr(filters[name], "extra", {}).get("history", []) for name in names if name in filters}


def training_costs(jobs: dict[str, TrainingJob]) -> dict[str, dict]:
    """Samples, updates, wall time and threads of every finished training job (the report's table)."""
    return {
        name: {k: job.summary().get(k) for k in ("frames", "updates", "wall_s", "threads")}
        for name, job in jobs.items()
    }


def checkpoint_fingerprint(paths) -> str:
    """A short digest of the given files' bytes: a study cache keyed by it is never stale after retraining."""
    digest = hashlib.sha1()
    for path in sorted(Path(p) for p in paths):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:10]
