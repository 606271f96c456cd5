"""What every filter-training run shares: the filter, validation, logging and checkpoints.

A subclass (DSAC-T for DAOF, regression for SLF) adds its optimisation state through
``extra_state`` / ``load_extra_state`` and calls ``after_batch`` once per collected batch, which
validates, logs, keeps the best validation filter and writes the resumable checkpoint.
"""

from __future__ import annotations

import json
import math
import time
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger
from tqdm import tqdm

from daof.envs.registry import make_system
from daof.filters import UKF
from daof.filters.learned import FilterConfig, LearnedFilter
from daof.train.checkpoint import RUN_CONFIG, atomic_save, capture_rng, load_checkpoint, restore_rng
from daof.train.validation import plot_learning_curve, rmse_per_state, write_curve_csv

__all__ = ["FilterTrainer"]


class FilterTrainer:
    """Base of the training runs; ``kind`` is the filter kind (``DAOF-v1``, ``DAOF-v2``, ``SLF``)."""

    #: config fields a resumed checkpoint must agree on
    identity_keys = ("system", "scenario", "window")

    def __init__(self, cfg: DictConfig, kind: str):
        self.cfg = cfg
        torch.set_num_threads(int(cfg.threads))
        torch.manual_seed(int(cfg.seed))
        self.out = Path(cfg.output_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        # what experiments compare before they reuse or resume this directory (daof.evaluate.jobs)
        resolved = OmegaConf.to_container(cfg, resolve=True)
        (self.out / RUN_CONFIG).write_text(json.dumps(resolved, indent=2))
        self.system = make_system(cfg.system, cfg.scenario, **(cfg.get("overrides") or {}))
        net = cfg.network
        self.filter = LearnedFilter(
            FilterConfig(
                kind=kind,
                system=cfg.system,
                scenario=cfg.scenario,
                window=int(cfg.window),
                include_controls=bool(cfg.include_controls),
                num_cells=int(net.num_cells),
                depth=int(net.depth),
                correction_sigmas=float(net.get("correction_sigmas", 4.0)),
                correction_bound=str(net.get("correction_bound", "kalman")),
                startup_input=bool(net.get("startup_input", True)),
                innovation_input=bool(net.get("innovation_input", True)),
                # DAOF-v1's alone: a config shared by v1 and v2 runs (the recipes') may set it
                reference_gain=bool(net.get("reference_gain", False)) and kind == "DAOF-v1",
                window_padding=str(net.get("window_padding", "same")),
                v2_action=str(net.get("v2_action", "estimate")),
                missing_mask=bool(net.get("missing_mask", False)),
            ),
            self.system,
        )
        self.filter.fit_normalizer(seed=int(cfg.seeds.normalizer))
        v = cfg.validation
        self.val_data = self.system.simulate(int(v.runs), int(v.steps), int(cfg.seeds.validation))
        self.frames = 0
        self.updates = 0
        self.wall = 0.0
        self.history: list[dict] = []
        self.best: dict = {"score": math.inf, "frames": 0}
        self.logger = None
        self._logger_state = None
        self._clock_start = None
        self._next_ckpt = int(cfg.checkpoint.every_frames)

    @property
    def training_gaps(self) -> tuple[float, float]:
        """(p_max, blackout_s) of the config's ``dropout`` (random sensor gaps to train through; ``daof.envs.gaps``).

        (0, 0) when the config has none: complete training data.
        """
        gaps = self.cfg.get("dropout")
        return (float(gaps.p_max), float(gaps.blackout_s)) if gaps is not None else (0.0, 0.0)

    def lr_factor(self) -> float:
        """Learning-rate factor on a cosine from 1 to ``optim.lr_final`` (default 1) over ``collector.total_frames``.

        A function of the frame count only, so a resumed run continues the same schedule.
        """
        final = float(self.cfg.optim.get("lr_final", 1.0))
        if not 0.0 < final <= 1.0:
            raise ValueError(f"optim.lr_final must be in (0, 1], got {final}")
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
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "filter": self.filter.state_dict(),
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

    def resume(self, path: str | Path) -> None:
        """Continue the run saved at ``path`` (refuses a checkpoint of another run)."""
        blob = load_checkpoint(path)
        saved = blob["config"]
        for key in self.identity_keys:
            if saved.get(key) != self.cfg.get(key):
                raise ValueError(
                    f"checkpoint {path} is for {key}={saved.get(key)!r}, this run has {self.cfg.get(key)!r}"
                )
        self.load_state_dict(blob)

    def save_checkpoint(self) -> Path:
        path = self.out / "checkpoint.pt"
        atomic_save(self.state_dict(), path)
        return path

    def deployed_weights(self) -> AbstractContextManager:
        """Inside it the filter holds the weights that are validated and saved (its own here)."""
        return nullcontext()

    def save_filter(self, name: str) -> Path:
        path = self.out / name
        meta = {"frames": self.frames, "updates": self.updates, "wall_s": self.wall, "history": self.history}
        with self.deployed_weights():
            self.filter.save(path, extra=meta)
        return path

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
        record["score"] = float((rmse / self.system.error_scale).mean()) if finite else float("inf")
        return record

    @torch.no_grad()
    def reference_rmse(self) -> dict[str, list[float]]:
        """A UKF's RMSE per state on the same validation set (systems with a model), for comparison."""
        if not self.system.has_model or not self.cfg.validation.get("ukf_reference", True):
            return {}
        return {"UKF": rmse_per_state(UKF(self.system).run(self.val_data), self.val_data["state"]).tolist()}

    def start(self, total: int) -> tqdm:
        """Open the logger and the progress bar; start the wall clock (continuing a resumed one)."""
        lc = self.cfg.logger
        if lc.backend:
            kwargs = {}
            if lc.backend == "wandb":
                kwargs["wandb_kwargs"] = {"mode": lc.mode, "project": lc.project, "dir": str(self.out)}
            self.logger = get_logger(
                lc.backend, str(self.out / "logs"), self.out.name, state_dict=self._logger_state, **kwargs
            )
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
            # the validation before the first update is the untrained network: on the curve, never the result
            if self.updates > 0 and record["score"] < self.best["score"]:
                self.best = {"score": record["score"], "frames": self.frames, "record": record}
                self.save_filter("best.pt")
            rmse = {k[5:]: f"{v:.4g}" for k, v in record.items() if k.startswith("rmse_")}
            bar.set_postfix(rmse, refresh=False)
        if self.logger is not None:
            for key, value in log.items():
                self.logger.log_scalar(key, value, step=self.frames)
        bar.update(new_frames)
        if self.frames >= self._next_ckpt or self.frames >= total:
            self.save_checkpoint()
            self._next_ckpt = self.frames + int(self.cfg.checkpoint.every_frames)

    def finish(self) -> dict:
        """Final filter, learning curve (CSV + PNG) and ``summary.json``."""
        self.save_filter("final.pt")
        if not (self.out / "best.pt").exists():
            self.save_filter("best.pt")
        write_curve_csv(self.history, self.out / "learning_curve.csv")
        cfg = self.cfg
        title = f"{self.filter.config.kind} on {cfg.system} ({cfg.scenario}), N={cfg.window}"
        references = self.reference_rmse()
        plot_learning_curve(self.history, self.system.state_names, self.out / "learning_curve.png", title, references)
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
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        return summary
