"""Fit a trained filter's uncertainty head: ``python -m daof.train.uncertainty RUN_DIR [options]``.

    python -m daof.train.uncertainty runs/veh2dof/nominal/daof-v1-N20-s1            # -> best.uncertainty.pt
    python -m daof.train.uncertainty RUN_DIR --checkpoint final.pt --runs 128 --epochs 40

The filter (``RUN_DIR/best.pt`` by default, on the run's system with its ``overrides``) is frozen. It
filters ``runs`` fresh episodes of its training distribution (complete data), simulated from a seed of
their own: ``HEAD_SEED + the run's training seed`` unless ``--seed`` says otherwise, never a validation
or evaluation seed. The head (``daof.filters.learned.uncertainty``) maps the filter's features at step
t to log σ²_t per state and is fitted by the Gaussian negative log-likelihood of the filter's errors,
½ Σ_i (log σ²_i + e_i² / σ²_i), with Adam; a share of the runs is held out and the epoch with the
lowest held-out NLL is kept. A few minutes at most on a CPU; it writes ``<checkpoint stem>.uncertainty.pt``
beside the checkpoint (or ``--out``) and prints the held-out NEES and ±2σ coverage per state.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from daof.envs.registry import make_system
from daof.evaluate.metrics import calibration
from daof.filters.learned import LearnedFilter, load_filter
from daof.filters.learned.uncertainty import UncertaintyHead, file_digest, head_path, load_head, save_head

__all__ = [
    "HEAD_SEED",
    "HeadSettings",
    "fit_head",
    "gaussian_nll",
    "head_arguments",
    "head_fitted",
    "main",
    "simulate_features",
]

#: the head's data seed is this plus the run's training seed: disjoint from the training batches
#: (seed · 1,000,003 + batch), the normaliser (7,000,001), validation (9100) and evaluation (20261122 + k)
HEAD_SEED = 424_242_000
#: seeds the head never trains on: the validation set and the evaluation seeds' range
RESERVED_SEEDS = (range(9100, 9101), range(20261122, 20261122 + 1000))


@dataclass
class HeadSettings:
    """How a head is fitted (stored in its file)."""

    runs: int = 256  # fresh episodes the frozen filter filters
    steps: int = 500  # their length (the study's)
    holdout: float = 0.125  # share of the runs held out to pick the best epoch
    epochs: int = 60
    batch_size: int = 4096
    lr: float = 1e-3
    num_cells: int = 64
    depth: int = 2

    def check(self) -> None:
        if self.runs < 2 or self.steps < 1 or self.epochs < 1 or self.batch_size < 1:
            raise ValueError(f"need runs >= 2, steps >= 1, epochs >= 1, batch_size >= 1; got {self}")
        held = round(self.runs * self.holdout)
        if not 0 < self.holdout < 1 or held < 1 or held >= self.runs:
            raise ValueError(f"holdout={self.holdout} must leave at least one run on each side of {self.runs} runs")


def check_seed(seed: int) -> int:
    """``seed``, refused in one line if it is a validation or evaluation seed."""
    if any(seed in reserved for reserved in RESERVED_SEEDS):
        raise ValueError(f"seed {seed} is a validation or evaluation seed; the head trains on data of its own")
    return seed


@torch.no_grad()
def simulate_features(filt: LearnedFilter, runs: int, steps: int, seed: int):
    """(features [runs, steps, k], errors x̂ − x [runs, steps, n]) of the frozen filter on fresh simulated data."""
    data = filt.system.simulate(runs, steps, seed)
    y, u_prev, u = filt.validate(data)
    estimates, features = filt.uncertainty_features(y, u_prev, u)
    return features, estimates - data["state"].to(estimates)


def gaussian_nll(log_variance: torch.Tensor, errors: torch.Tensor) -> torch.Tensor:
    """Mean over samples of ½ Σ_i (log σ²_i + e_i² / σ²_i) (the constant dropped)."""
    return 0.5 * (log_variance + errors.square() * (-log_variance).exp()).sum(-1).mean()


def fit_head(filt: LearnedFilter, settings: HeadSettings, seed: int, log=print) -> tuple[UncertaintyHead, dict]:
    """Fit a head to the frozen ``filt`` (module docstring) -> (head, record: held-out NLL, NEES, coverage).

    Deterministic: the head's initial weights and the batches' order come from ``seed`` too (the global
    random state is left as it was).
    """
    settings.check()
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return _fit(filt, settings, seed, log)


def _fit(filt: LearnedFilter, settings: HeadSettings, seed: int, log) -> tuple[UncertaintyHead, dict]:
    start = time.perf_counter()
    features, errors = simulate_features(filt, settings.runs, settings.steps, check_seed(seed))
    finite = torch.isfinite(errors).all(-1).all(-1) & torch.isfinite(features).all(-1).all(-1)
    if not finite.all():
        log(f"left out {int((~finite).sum())} runs with a non-finite estimate or feature")
        features, errors = features[finite], errors[finite]
    held = max(1, round(features.shape[0] * settings.holdout))
    train_x, train_e = features[held:].flatten(0, 1), errors[held:].flatten(0, 1)
    val_x, val_e = features[:held].flatten(0, 1), errors[:held].flatten(0, 1)
    head = UncertaintyHead(features.shape[-1], errors.shape[-1], settings.num_cells, settings.depth)
    head.fit_normalizer(train_x, train_e)
    with torch.no_grad():  # the untrained head claims the mean squared error everywhere: a constant σ
        constant = gaussian_nll(head(val_x), val_e).item()
    optim = torch.optim.Adam(head.parameters(), lr=settings.lr)
    best, best_state, history = float("inf"), None, []
    bar = tqdm(range(settings.epochs), desc=f"  {filt.name} head", unit="epoch", leave=False, disable=None)
    for _ in bar:
        head.train()
        for idx in torch.randperm(train_x.shape[0]).split(settings.batch_size):
            loss = gaussian_nll(head(train_x[idx]), train_e[idx])
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
        head.eval()
        with torch.no_grad():
            held_out = gaussian_nll(head(val_x), val_e).item()
        history.append(held_out)
        bar.set_postfix(held_out_nll=f"{held_out:.4g}")
        if held_out < best:
            best, best_state = held_out, copy.deepcopy(head.state_dict())
    head.load_state_dict(best_state)
    head.eval()
    with torch.no_grad():
        std = head.std(features[:held])
    check = calibration(errors[:held], torch.zeros_like(errors[:held]), std)
    record = {
        "seed": seed,
        "settings": asdict(settings),
        "held_out_runs": held,
        "best_epoch": history.index(best) + 1,
        "held_out_nll": history,
        "held_out_nll_constant": constant,
        "held_out_nees": check["nees"],
        "held_out_coverage": check["coverage"],
        "wall_s": round(time.perf_counter() - start, 1),
    }
    return head, record


def _run_config(run_dir: Path) -> dict:
    path = run_dir / "run_config.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def load_frozen(checkpoint: Path) -> tuple[LearnedFilter, dict]:
    """The filter at ``checkpoint`` on its run's system (with the run's ``overrides``), frozen; and the run's config."""
    config = _run_config(checkpoint.parent)
    system = None
    if config.get("system") and config.get("overrides"):
        system = make_system(config["system"], config.get("scenario", "nominal"), **config["overrides"])
    filt = load_filter(checkpoint, system)
    filt.attach_uncertainty(None)  # the head is fitted anew
    filt.requires_grad_(False)
    return filt, config


def head_fitted(checkpoint: Path) -> bool:
    """Whether the head beside ``checkpoint`` (``head_path``) was fitted to that very file.

    An experiment fits a head where this is false (``daof.experiments.jobs.HeadJob``); a head is not
    refitted for other settings (delete its file, or run ``python -m daof.train.uncertainty``).
    """
    out = head_path(checkpoint)
    if not out.is_file():
        return False
    try:
        load_head(out, file_digest(checkpoint))
    except ValueError:
        return False  # fitted to an earlier best.pt, or not a head
    return True


def head_arguments(settings: HeadSettings) -> list[str]:
    """``settings`` as the options of ``python -m daof.train.uncertainty``."""
    return [f"{_option(key)}={value}" for key, value in asdict(settings).items()]


def _option(key: str) -> str:
    """The command-line option of a ``HeadSettings`` field."""
    return f"--{key.replace('_', '-')}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m daof.train.uncertainty", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a training run's directory")
    parser.add_argument("--checkpoint", default="best.pt", help="the filter file in RUN_DIR (default best.pt)")
    parser.add_argument("--out", type=Path, help="the head's file (default: <stem>.uncertainty.pt beside it)")
    parser.add_argument("--seed", type=int, default=None, help=f"data seed (default {HEAD_SEED} + the run's seed)")
    parser.add_argument("--threads", type=int, default=1)
    defaults = HeadSettings()
    for key, value in asdict(defaults).items():
        parser.add_argument(_option(key), type=type(value), default=value)
    args = parser.parse_args(argv)
    checkpoint = args.run_dir / args.checkpoint
    try:
        torch.set_num_threads(args.threads)
        filt, config = load_frozen(checkpoint)
        settings = HeadSettings(**{k: getattr(args, k) for k in asdict(defaults)})
        seed = args.seed if args.seed is not None else HEAD_SEED + int(config.get("seeds", {}).get("train", 0))
        print(f"{filt.name} ({checkpoint}): filtering {settings.runs} runs x {settings.steps} steps (seed {seed}) ...")
        head, record = fit_head(filt, settings, seed)
        out = args.out or head_path(checkpoint)
        save_head(head, out, file_digest(checkpoint), record)
    except (ValueError, OSError) as error:
        sys.exit(f"error: {error}")
    states = filt.system.state_names
    nees = ", ".join(f"{n} {v:.3f}" for n, v in zip(states, record["held_out_nees"]))
    cover = ", ".join(f"{n} {100 * v:.1f} %" for n, v in zip(states, record["held_out_coverage"]))
    print(f"held-out runs ({record['held_out_runs']}): NEES {nees}; ±2σ coverage {cover}")
    nll = min(record["held_out_nll"])
    print(f"held-out NLL {nll:.4g} per step (a constant σ per state: {record['held_out_nll_constant']:.4g})")
    print(f"head: {out}  (best epoch {record['best_epoch']} of {settings.epochs}, {record['wall_s']} s)")


if __name__ == "__main__":
    main()
