"""What every filter-training run shares: the filter, validation, logging and checkpoints.

A subclass (DSAC-T for DAOF, regression for SLF) adds its optimisation state through
``extra_state`` / ``load_extra_state`` and calls ``after_batch`` once per collected batch, which
validates, logs, keeps the best validation filter and writes the resumable checkpoint.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger
from tqdm import tqdm

from daof.dashboard import log_training_end, training_identity
from daof.device import resolve_device
from daof.envs.registry import make_system
from daof.filters import UKF
from daof.filters.learned import FilterConfig, LearnedFilter
from daof.filters.learned.config import RETIRED_OPTIONS, retired_refusal
from daof.fingerprint import classical_fingerprint, data_fingerprint
from daof.io import atomic_write_text, writable_directory
from daof.train.checkpoint import RUN_CONFIG, atomic_save, capture_rng, load_checkpoint, restore_rng
from daof.train.config import ADDED_KEYS, RETIRED_KEYS
from daof.train.lock import lock_run_directory
from daof.train.validation import plot_learning_curve, rmse_per_state, write_curve_csv

__all__ = ["PROGRESS", "RUN_CONFIG", "FilterTrainer", "comparable_config"]

#: a running training's progress file (``FilterTrainer._write_progress``), read by ``daof.experiments``
PROGRESS = "progress.json"
#: beside the run directories: the UKF's validation RMSE, shared by the runs of one validation set
REFERENCE_CACHE = ".validation-references"

#: the files a training run writes into its directory
RUN_FILES = (RUN_CONFIG, "best.pt", "final.pt", "checkpoint.pt", "summary.json", "learning_curve.csv",
             "learning_curve.png")  # fmt: skip
#: config keys a run may change when it is resumed
RESUMABLE_CHANGES = (
    "resume", "output_dir", "threads", "device", "collector.total_frames", "checkpoint.every_frames",
    "logger.backend", "logger.mode", "logger.project", "logger.name", "logger.group", "logger.tags",
)  # fmt: skip


def comparable_config(config: dict) -> dict:
    """A resolved config as flat ``a.b`` keys, without the keys a resumed run may change.

    A config written before an option was retired (``daof.train.config.RETIRED_KEYS``) compares without
    it where it holds the surviving value or its kind never read it (``network.v2_action: estimate``);
    another value stays, so that run is another config (a DAOF-v2 of the removed increment form). A key
    added since (``ADDED_KEYS``) compares without it where it holds the value every earlier run had.
    """

    def flat(node, prefix=""):
        for key, value in node.items():
            if isinstance(value, dict) and value:
                yield from flat(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}", value

    flat_config = {k: v for k, v in flat(config) if k not in RESUMABLE_CHANGES}
    for key, option in RETIRED_KEYS.items():
        kinds, surviving = RETIRED_OPTIONS[option]
        if key in flat_config and (flat_config[key] == surviving or config.get("kind") not in kinds):
            del flat_config[key]
    for key, earlier in ADDED_KEYS.items():
        if flat_config.get(key, earlier) == earlier:
            flat_config.pop(key, None)
    return flat_config


#: what every training checkpoint holds (a trainer's own entries are checked as it restores them)
CHECKPOINT_ENTRIES = ("config", "filter", "rng", "training")
TRAINING_ENTRIES = ("frames", "updates", "wall", "history", "best", "next_ckpt")


def _check_resumable(blob: dict, path) -> None:
    """One line if a checkpoint lacks what every resume reads (a config that is no mapping, a missing entry)."""
    missing = [k for k in CHECKPOINT_ENTRIES if k not in blob]
    missing += [
        f"training/{k}"
        for k in TRAINING_ENTRIES
        if not isinstance(blob.get("training"), dict) or k not in blob["training"]
    ]
    if missing:
        raise ValueError(f"checkpoint {path} cannot be resumed: it has no {', '.join(missing)}")
    if not isinstance(blob["config"], dict):
        raise ValueError(
            f"checkpoint {path} cannot be resumed: its config is a {type(blob['config']).__name__}, not a mapping"
        )


class FilterTrainer:
    """Base of the training runs of the filter kinds in ``kinds`` (``cfg.kind`` says which one)."""

    #: whether the untrained filter is already a filter worth keeping (DAOF-v1 starts at its reference update)
    starts_as_a_filter = False

    #: the filter kinds this trainer learns
    kinds: tuple[str, ...] = ()

    def __init__(self, cfg: DictConfig):
        if cfg.kind not in self.kinds:
            raise ValueError(f"{type(self).__name__} trains {' or '.join(self.kinds)}, not {cfg.kind!r}")
        self.cfg = cfg
        #: where the networks, env, replay buffer and validation run (``cfg.device``); the normaliser,
        #: the validation set and DAOF-v1's schedules are made on the CPU, so they are the same on every device
        self.device = resolve_device(cfg.device)
        torch.set_num_threads(int(cfg.threads))
        torch.manual_seed(int(cfg.seed))
        self.out = Path(cfg.output_dir)
        writable_directory(self.out, "run directory")
        self._lock = None
        self._resumed = False
        self.system = make_system(cfg.system, cfg.scenario, **cfg.overrides)
        self.filter = LearnedFilter(FilterConfig.from_training(cfg), self.system)
        self.filter.fit_normalizer(seed=int(cfg.seeds.normalizer))
        self.filter.to(self.device)
        v = cfg.validation
        self.val_data = self.system.simulate(int(v.runs), int(v.steps), int(cfg.seeds.validation)).to(self.device)
        self.frames = 0
        self.updates = 0
        self.wall = 0.0
        self.history: list[dict] = []
        self.best: dict = {"score": math.inf, "frames": 0}
        #: the best filter's weights and metadata, kept in the checkpoint so that ``best.pt`` matches it on resume
        self._best_filter: dict | None = None
        self.logger = None
        self._progress_written = -math.inf
        self._logger_state = None
        self._clock_start = None
        self._next_ckpt = int(cfg.checkpoint.every_frames)

    def _set_aside_previous_run(self) -> None:
        """A fresh run in a directory that holds another run moves that run's files to ``<dir>/previous-<k>``.

        So a directory never mixes the files of two runs (a ``best.pt`` of one under the config of another).
        """
        old = [p for p in self.out.iterdir() if p.name in RUN_FILES or p.name in ("logs", "train_logs")]
        if not any(p.name in RUN_FILES for p in old):
            return
        k = 1
        while (target := self.out / f"previous-{k}").exists():
            k += 1
        target.mkdir()
        for path in old:
            shutil.move(str(path), str(target / path.name))
        print(f"{self.out} held another run: moved it to {target}")

    @property
    def training_gaps(self) -> tuple[float, float]:
        """(p_max, blackout_s) of the config's ``dropout`` (random sensor gaps to train through; ``daof.envs.gaps``).

        (0, 0) when the config has none: complete training data.
        """
        gaps = self.cfg.dropout
        return float(gaps.p_max), float(gaps.blackout_s)

    def lr_factor(self) -> float:
        """Learning-rate factor on a cosine from 1 to ``optim.lr_final`` over ``collector.total_frames``.

        A closed-form function of the frame count, so a resumed run (or one whose budget grew)
        continues the same schedule. Kept instead of ``torch.optim.lr_scheduler.CosineAnnealingLR``:
        that one counts scheduler steps, not frames, and its chainable update drifts from the closed
        form (1.5e-14 relative over 2,000 steps, measured 2026-12-07), which would change every
        trained number in its last bits.
        """
        final = float(self.cfg.optim.lr_final)
        progress = min(self.frames / int(self.cfg.collector.total_frames), 1.0)
        return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * progress))

    # ----------------------------------------------------------------- subclass hooks
    def extra_state(self) -> dict:
        """Optimisation state of the subclass (optimisers, loss, buffers, generators)."""
        return {}

    def load_extra_state(self, blob: dict) -> None:
        """Inverse of ``extra_state``."""

    def generators(self) -> dict[str, torch.Generator]:
        """Named generators whose states a checkpoint keeps (besides the global ones)."""
        return {}

    # ----------------------------------------------------------------- checkpoint
    def state_dict(self) -> dict:
        return {
            "training": {
                "frames": self.frames,
                "updates": self.updates,
                "wall": self.wall,
                "history": self.history,
                "best": self.best,
                "next_ckpt": self._next_ckpt,
            },
            "best_filter": self._best_filter,
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "filter": self.filter.state_dict(),
            "filter_config": dict(vars(self.filter.config)),  # what load_filter rebuilds the filter from
            "rng": capture_rng(self.generators()),
            "logger": self.logger.state_dict() if self.logger is not None else None,
            **self.extra_state(),
        }

    def load_state_dict(self, blob: dict) -> None:
        self.filter.load_state_dict(blob["filter"])
        self.load_extra_state(blob)
        restore_rng(blob["rng"], self.generators())
        t = blob["training"]
        self.frames, self.updates, self.wall = t["frames"], t["updates"], t["wall"]
        self.history, self.best = list(t["history"]), dict(t["best"])
        self._next_ckpt = t["next_ckpt"]
        self._logger_state = blob.get("logger")
        self._best_filter = blob.get("best_filter")
        self._restore_best_file()

    def resume(self, path: str | Path) -> None:
        """Continue the run saved at ``path``; a checkpoint of another config is refused (``ValueError``).

        Only what may change between a run and its continuation may differ: the budget
        (``collector.total_frames``), where it is written, the thread count and the logger.
        """
        blob = load_checkpoint(path)
        _check_resumable(blob, path)
        saved = comparable_config(blob["config"])
        for key, option in RETIRED_KEYS.items():  # a run of a filter that no longer exists
            if key in saved:
                refusal = retired_refusal(option, saved[key], blob["config"].get("kind"), name=key)
                raise ValueError(f"checkpoint {path} cannot be resumed: {refusal}")
        now = comparable_config(OmegaConf.to_container(self.cfg, resolve=True))
        if saved != now:
            diff = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
            key = diff[0]
            if key not in now:
                raise ValueError(f"checkpoint {path} has config key {key!r}, which this version does not know")
            if key not in saved:
                raise ValueError(f"checkpoint {path} has no config key {key!r}: incomplete or from another version")
            raise ValueError(f"checkpoint {path} is for {key}={saved.get(key)!r}, this run has {now.get(key)!r}")
        self._lock = lock_run_directory(self.out)  # before the files it restores are touched
        self._resumed = True
        try:
            self.load_state_dict(blob)
        except (KeyError, TypeError, AttributeError, IndexError, RuntimeError) as error:
            self._release_directory()
            what = f"no {error.args[0]!r} entry" if isinstance(error, KeyError) else str(error).strip().splitlines()[0]
            raise ValueError(
                f"checkpoint {path} cannot be resumed: incomplete or from another version ({what})"
            ) from None

    def save_checkpoint(self) -> Path:
        path = self.out / "checkpoint.pt"
        atomic_save(self.state_dict(), path)
        return path

    def deployed_weights(self) -> AbstractContextManager:
        """Inside it the filter holds the weights that are validated and saved (its own here)."""
        return nullcontext()

    def save_filter(self, name: str) -> Path:
        path = self.out / name
        meta = {"frames": self.frames, "updates": self.updates, "wall_s": self.wall, "history": list(self.history)}
        with self.deployed_weights():
            self.filter.save(path, extra=meta)
            if name == "best.pt":
                weights = {k: v.detach().clone() for k, v in self.filter.state_dict().items()}
                self._best_filter = {"state_dict": weights, "extra": meta}
        return path

    def _restore_best_file(self) -> None:
        """After a resume ``best.pt`` is the checkpoint's best, not one a discarded stretch of training wrote."""
        path = self.out / "best.pt"
        if self._best_filter is None:
            path.unlink(missing_ok=True)
            return
        current = {k: v.detach().clone() for k, v in self.filter.state_dict().items()}
        self.filter.load_state_dict(self._best_filter["state_dict"])
        self.filter.save(path, extra=self._best_filter["extra"])
        self.filter.load_state_dict(current)

    # ----------------------------------------------------------------- validation and logging
    @torch.no_grad()
    def validate(self) -> dict:
        """Deterministic closed-loop RMSE per state on the fixed validation set."""
        was_training = self.filter.training
        self.filter.eval()
        with self.deployed_weights():
            est = self.filter.run(self.val_data)
        self.filter.train(was_training)
        rmse = rmse_per_state(est, self.val_data["state"])
        record = {"frames": self.frames, "updates": self.updates, "wall_s": round(self.wall, 2)}
        for name, value in zip(self.system.state_names, rmse.tolist()):
            record[f"rmse_{name}"] = value if math.isfinite(value) else float("inf")
        # one number to rank checkpoints: mean RMSE relative to the system's error scale
        finite = bool(torch.isfinite(rmse).all())
        record["score"] = float((rmse / self.filter.error_scale.to(rmse)).mean()) if finite else float("inf")
        return record

    @torch.no_grad()
    def reference_rmse(self) -> dict[str, list[float]]:
        """A UKF's RMSE per state on the same validation set (systems with a model), for comparison.

        Kept in ``<run directory's parent>/.validation-references/``, keyed by the validation data and the
        UKF's code and settings: the runs beside this one (an experiment's other filters and seeds) reuse
        it instead of filtering the set again (49 s on veh2dof's 100 × 500 steps, measured on an AMD EPYC core).
        """
        if not self.system.has_model or not self.cfg.validation.ukf_reference:
            return {}
        ukf = UKF(self.system)
        key = f"{data_fingerprint(self.val_data)}-{classical_fingerprint(ukf, self.system)}"
        cached = self.out.parent / REFERENCE_CACHE / f"ukf-{key}.json"
        if cached.is_file():
            try:
                return {"UKF": json.loads(cached.read_text())}
            except ValueError:
                pass  # cut short: computed again
        rmse = rmse_per_state(ukf.run(self.val_data), self.val_data["state"]).tolist()
        cached.parent.mkdir(exist_ok=True)
        atomic_write_text(cached, json.dumps(rmse))
        return {"UKF": rmse}

    def _claim_directory(self) -> None:
        """Lock the run directory, move another run's files aside (a fresh run) and record the config.

        ``run_config.json`` is what experiments compare before they reuse or resume a directory
        (``daof.experiments.jobs``).
        """
        if self._lock is None:
            self._lock = lock_run_directory(self.out)
        if not self._resumed:
            self._set_aside_previous_run()
        resolved = OmegaConf.to_container(self.cfg, resolve=True)
        atomic_write_text(self.out / RUN_CONFIG, json.dumps(resolved, indent=2))

    def _release_directory(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def start(self, total: int) -> tqdm:
        """Claim the directory, open the logger and the progress bar, start the wall clock (a resumed run's goes on)."""
        self._claim_directory()
        lc = self.cfg.logger
        if lc.backend:
            kwargs = {}
            name = self.out.name
            if lc.backend == "wandb":
                identity = training_identity(self.cfg)
                name = identity.pop("name")
                config = OmegaConf.to_container(self.cfg, resolve=True)
                kwargs["wandb_kwargs"] = {
                    **{"mode": lc.mode, "project": lc.project, "dir": str(self.out), "config": config},
                    **identity,
                }
            self.logger = get_logger(lc.backend, str(self.out / "logs"), name, state_dict=self._logger_state, **kwargs)
        self._clock_start = time.perf_counter() - self.wall
        desc = f"{self.filter.config.kind} {self.cfg.system} N={self.cfg.window}"
        return tqdm(total=total, initial=self.frames, desc=desc, unit="fr", mininterval=2.0)

    def after_batch(self, bar: tqdm, new_frames: int, log: dict, total: int) -> None:
        """Validate when due, log, keep the best filter, checkpoint when due, move the bar."""
        self.wall = time.perf_counter() - self._clock_start
        every = int(self.cfg.validation.every_frames)
        if self.frames >= len(self.history) * every or self.frames >= total:
            with timeit("validate"):
                record = self.validate()
            self.history.append(record)
            log.update({f"val/{k}": v for k, v in record.items() if k.startswith("rmse")})
            # the validation before the first update is the untrained network: on the curve, and the result
            # only where it is already a filter (DAOF-v1's reference update), which training may not beat
            if (self.updates > 0 or self.starts_as_a_filter) and record["score"] < self.best["score"]:
                self.best = {"score": record["score"], "frames": self.frames, "record": record}
                self.save_filter("best.pt")
            rmse = {k[5:]: f"{v:.4g}" for k, v in record.items() if k.startswith("rmse_")}
            bar.set_postfix(rmse, refresh=False)
        if self.logger is not None:
            for key, value in log.items():
                self.logger.log_scalar(key, value, step=self.frames)
        bar.update(new_frames)
        self._write_progress(total)
        if self.frames >= self._next_ckpt or self.frames >= total:
            self.save_checkpoint()
            self._next_ckpt = self.frames + int(self.cfg.checkpoint.every_frames)

    def _write_progress(self, total: int, every_s: float = 5.0) -> None:
        """``progress.json`` (frames, budget, wall time, latest validation RMSE) for whoever watches the run."""
        now = time.monotonic()
        if now - self._progress_written < every_s and self.frames < total:
            return
        self._progress_written = now
        latest = self.history[-1] if self.history else {}
        progress = {
            "frames": self.frames,
            "total": total,
            "wall_s": round(self.wall, 1),
            "rmse": {k[5:]: v for k, v in latest.items() if k.startswith("rmse_")},
        }
        atomic_write_text(self.out / PROGRESS, json.dumps(progress))

    def finish(self) -> dict:
        """Final filter, learning curve (CSV + PNG) and ``summary.json``."""
        self.save_filter("final.pt")
        if not (self.out / "best.pt").exists():
            self.save_filter("best.pt")
        write_curve_csv(self.history, self.out / "learning_curve.csv")
        cfg = self.cfg
        title = f"{self.filter.config.kind} on {cfg.system} ({cfg.scenario}), N={cfg.window}"
        references = self.reference_rmse()
        curve = self.out / "learning_curve.png"
        plot_learning_curve(
            self.history, self.system.state_names, curve, title, references, name=self.filter.config.kind
        )
        summary = {
            "kind": self.filter.config.kind,
            "system": cfg.system,
            "scenario": cfg.scenario,
            "window": int(cfg.window),
            "frames": self.frames,
            "updates": self.updates,
            "wall_s": round(self.wall, 1),
            "threads": torch.get_num_threads(),
            "best": self.best,
            "final": self.history[-1] if self.history else None,
            "validation_references": references,
            "timing_s": {k: v for k, v in timeit.todict().items()},
        }
        atomic_write_text(self.out / "summary.json", json.dumps(summary, indent=2, default=str))
        if cfg.logger.backend == "wandb" and self.logger is not None:
            log_training_end(self.logger, self.history, self.system.state_names, curve, summary)
        self._release_directory()
        return summary
