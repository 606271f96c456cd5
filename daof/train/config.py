"""The one typed training configuration: every key of a training run, its type and its default.

The dataclasses below are the only place a default lives (a learned filter's own options take
theirs from ``FilterConfig``, the checkpoint's record of a filter). They are registered with Hydra's
ConfigStore as ``train_schema``; the YAML files in ``daof/conf`` (one per filter kind, one per
system, and a few per system and filter) hold only what differs from them. Hydra refuses an
unknown key or a value of the wrong type before anything runs; ``check_config`` then refuses
impossible values (an unknown choice, a window < 1, a budget that trains nothing) in one line.

Why each default is what it is: ``docs/training.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from daof.config_checks import check_override_keys, one_line
from daof.device import resolve_device
from daof.filters.learned.config import RETIRED_OPTIONS, FilterConfig, retired_refusal

__all__ = [
    "ADDED_KEYS",
    "CONF_DIR",
    "FILTER_KINDS",
    "RETIRED_KEYS",
    "TrainConfig",
    "check_config",
    "compose_config",
    "register_configs",
    "retired_overrides",
]

#: the YAML side of the configuration (per filter kind, per system, per system and filter)
CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
#: config groups of ``train.yaml``: what ``filter=...`` and ``system=...`` choose
GROUPS = ("filter", "system", "tuning")

#: the system group's choice that stands for a system given by import path or entry point (``system=pkg.mod:Cls``)
USER_SYSTEM = "user_code"
#: filter kind -> the trainer that learns it
FILTER_KINDS = {"DAOF-v1": "dsac", "DAOF-v2": "dsac", "SLF": "supervised", "KalmanNet": "kalmannet"}


@dataclass
class Seeds:
    train: int = "${seed}"  # type: ignore[assignment]  # env episodes (DAOF) or simulated batches (SLF)
    validation: int = 9100  # the fixed validation set; disjoint from the evaluation seeds (20261122 + k)
    normalizer: int = 7000001  # the data that fits the input normalisation and DAOF-v1's schedules


@dataclass
class Network:
    num_cells: int = FilterConfig.num_cells  # hidden width of actor and critics (the paper: 3 x 256 GELU)
    depth: int = FilterConfig.depth
    # DAOF-v1's bound of an update: ± this · σ_t per state, σ_t = a UKF's √diag P⁺_t
    correction_sigmas: float = FilterConfig.correction_sigmas
    # DAOF-v1: the residual on a UKF's mean-gain update K̄_t ν_t | false: the paper's form f(x̂) + b_t ⊙ π(h),
    # bounded by correction_sigmas · the UKF's √diag P⁻_t
    reference_gain: bool = FilterConfig.reference_gain
    startup_input: bool = FilterConfig.startup_input  # closed-loop networks read ρ_t = max(0, 1 − (t−1)/50)
    critic_form: str = "mlp"  # mlp | quadratic (V(h) − Σ p_i(h)(a_i − m_i(h))²) | reward_quadratic (γ = 0)
    critic_scale: str = "window"  # the value distribution's σ from h | reward: the quadratic reward's own spread
    critic_init: str = "own"  # each critic keeps its own init | resampled: TorchRL's re-sampled copies
    window_init: str = "uniform"  # PyTorch's init | newest: older frames' first-layer weights start at 0
    missing_mask: bool = FilterConfig.missing_mask  # SLF: frames carry a 0/1 missing flag per measurement channel
    kalmannet_in_mult: int = FilterConfig.kalmannet_in_mult  # KalmanNet: width multiplier of its input layers
    kalmannet_out_mult: int = FilterConfig.kalmannet_out_mult  # KalmanNet: width multiplier of its gain layer


@dataclass
class Dropout:  # SLF: random sensor gaps in the training batches
    p_max: float = 0.0  # each training episode misses each entry with p ~ U[0, p_max]
    blackout_s: float = 0.0  # and half of them lose one random channel for U[0, blackout_s] s


@dataclass
class Collector:
    env_batch: int = 32  # parallel episodes (DAOF) or fresh episodes per batch (SLF, KalmanNet)
    steps_per_batch: int = 25  # DAOF: env steps per collected batch
    episode_steps: int = 500
    total_frames: int = MISSING  # the budget: transitions (DAOF), windows (SLF) or steps (KalmanNet); per system
    warmup_frames: int = 8000  # DAOF: transitions of the initial policy before learning starts
    feedback: str = "sample"  # DAOF: what enters h_{t+1}: the sampled action | mean (γ = 0 only)


@dataclass
class Reward:
    weights: str = "kalman"  # W_t from a UKF's start-up (daof/train/schedules.py) | constant
    baseline: str = "none"  # zero_action: the critic learns r(a) − r(0) (γ = 0, update-acting filters)


@dataclass
class Buffer:
    size: int = 200000


@dataclass
class Optim:
    batch_size: int = 256  # samples per gradient step (KalmanNet: sequences)
    utd: float = 0.125  # DAOF: gradient updates per collected frame
    lr_actor: float = 1.0e-4  # DAOF
    lr_critic: float = 1.0e-4  # DAOF
    lr_alpha: float = 1.0e-3  # DAOF
    lr: float = 3.0e-4  # SLF, KalmanNet
    epochs_per_batch: int = 1  # SLF, KalmanNet: passes over each batch
    bptt_steps: int = 100  # KalmanNet: steps per truncated-BPTT segment (≥ episode_steps: full BPTT)
    weight_decay: float = 0.0  # KalmanNet: Adam's L2 weight decay (the authors use one)
    max_grad_norm: float = 0.0  # KalmanNet: clip the gradient's norm to this (0: no clipping)
    lr_final: float = 0.1  # learning rates follow a cosine down to lr_final · lr over the budget (1: constant)


@dataclass
class Loss:
    gamma: float = 0.0  # the estimate does not move the state: the per-step MMSE estimate is optimal for every γ
    critic_per_state: bool = False  # one value distribution per state, each on its reward term −W_i e_i²
    tau: float = 0.005
    delay: int = 2  # actor, α and targets step every delay-th update
    alpha_init: float = math.e
    target_entropy: Any = "auto"  # auto: exploration_std error scales per state | a number
    exploration_std: float = 0.4
    actor_samples: int = 1  # actions drawn per state in the actor loss
    epsilon: float = 0.1  # DSAC-T's ε in 1/(σ² + ε)


@dataclass
class Validation:
    runs: int = 100
    steps: int = 500
    every_frames: int = 40000
    actor: str = "online"  # the actor validated and saved: online | target (DSAC-T's Polyak average)
    ukf_reference: bool = True  # the learning curve shows a UKF's validation RMSE (systems with a model)


@dataclass
class Checkpoint:
    every_frames: int = 160000


@dataclass
class Logger:
    backend: str = "csv"  # csv | wandb | "" (none)
    mode: str = "offline"  # wandb mode: offline runs can be uploaded later with `wandb sync`
    project: str = "daof"
    name: str | None = None  # wandb run name (null: "<kind> <system>/<scenario> N=<window> seed=<seed>")
    group: str | None = None  # wandb group (an experiment sets "<experiment>/<profile>")
    tags: list[str] = field(default_factory=list)  # wandb tags beside kind, system, scenario, N and seed


@dataclass
class TrainConfig:
    kind: str = MISSING  # DAOF-v1 | DAOF-v2 | SLF | KalmanNet (set by the filter group: filter=daof_v1|...)
    run_name: str = MISSING  # the run directory's stem (set by the filter group)
    system: str = MISSING  # a system of daof/conf/system, an import path pkg.mod:Cls or an entry point
    scenario: str = FilterConfig.scenario
    overrides: dict[str, Any] = field(default_factory=dict)  # system parameters; replay: a recorded episode bank
    window: int = FilterConfig.window  # N of h_t^N
    include_controls: bool = FilterConfig.include_controls  # frames carry (u_t, u_{t−1})
    seed: int = 1
    threads: int = 1  # torch threads (the MLPs are small: one thread per run is the efficient choice)
    device: str = "cpu"  # cpu | cuda | cuda:<k> | auto (a GPU if there is one): where training runs (daof.device)
    resume: str | None = None  # a checkpoint.pt of the same run to continue
    output_dir: str = "runs/${path_part:${system}}/${scenario}/${run_name}-N${window}-s${seed}"
    seeds: Seeds = field(default_factory=Seeds)
    network: Network = field(default_factory=Network)
    dropout: Dropout = field(default_factory=Dropout)
    collector: Collector = field(default_factory=Collector)
    reward: Reward = field(default_factory=Reward)
    buffer: Buffer = field(default_factory=Buffer)
    optim: Optim = field(default_factory=Optim)
    loss: Loss = field(default_factory=Loss)
    validation: Validation = field(default_factory=Validation)
    checkpoint: Checkpoint = field(default_factory=Checkpoint)
    logger: Logger = field(default_factory=Logger)


#: the allowed values of every enum-like key
CHOICES = {
    "kind": tuple(FILTER_KINDS),
    "network.critic_form": ("mlp", "quadratic", "reward_quadratic"),
    "network.critic_scale": ("window", "reward"),
    "network.critic_init": ("own", "resampled"),
    "network.window_init": ("uniform", "newest"),
    "collector.feedback": ("sample", "mean"),
    "reward.weights": ("kalman", "constant"),
    "reward.baseline": ("none", "zero_action"),
    "validation.actor": ("online", "target"),
    "logger.backend": ("csv", "wandb", ""),
    "logger.mode": ("offline", "online", "disabled"),
}

#: keys of retired filter options (``daof.filters.learned.RETIRED_OPTIONS``) an old command line may still
#: name: an override with the surviving value is dropped, any other refused in one line (``retired_overrides``)
RETIRED_KEYS = {"network.v2_action": "v2_action"}  # DAOF-v2's increment form, removed on 2026-12-07

#: keys added after runs were made, with the value every earlier run had: a config holding that value
#: compares equal to one written before the key existed (``comparable_config``), so finished runs stay reused
ADDED_KEYS = {"network.reference_gain": True}  # 2026-12-08: DAOF-v1's paper form, a report row of its own

#: keys that must be ≥ 1 (counts) or > 0 (sizes and rates)
AT_LEAST_ONE = (
    "window", "threads", "network.num_cells", "network.depth", "collector.env_batch", "collector.steps_per_batch",
    "collector.episode_steps", "collector.total_frames", "buffer.size", "optim.batch_size", "optim.epochs_per_batch",
    "loss.delay", "loss.actor_samples", "validation.runs", "validation.steps", "validation.every_frames",
    "checkpoint.every_frames", "optim.bptt_steps", "network.kalmannet_in_mult", "network.kalmannet_out_mult",
)  # fmt: skip
POSITIVE = (
    "network.correction_sigmas", "optim.lr_actor", "optim.lr_critic", "optim.lr_alpha", "optim.lr",
    "loss.tau", "loss.alpha_init", "loss.exploration_std", "loss.epsilon",
)  # fmt: skip


def _get(cfg: DictConfig, dotted: str):
    node = cfg
    for part in dotted.split("."):
        node = node[part]
    return node


def check_config(cfg: DictConfig) -> None:
    """Refuse an impossible training config before any work, with one line naming the key (``ValueError``)."""
    from daof.envs import make_system  # the system's own check names its valid scenarios and parameters

    for key, valid in CHOICES.items():
        if _get(cfg, key) not in valid:
            raise ValueError(f"{key}={_get(cfg, key)!r} is not valid; valid: {list(valid)}")
    for key in AT_LEAST_ONE:
        if _get(cfg, key) < 1:
            raise ValueError(f"{key} must be >= 1, got {_get(cfg, key)}")
    for key in POSITIVE:
        if not _get(cfg, key) > 0:
            raise ValueError(f"{key} must be > 0, got {_get(cfg, key)}")
    if not 0.0 < cfg.optim.lr_final <= 1.0:
        raise ValueError(f"optim.lr_final must be in (0, 1], got {cfg.optim.lr_final}")
    if not 0.0 <= cfg.loss.gamma < 1.0:
        raise ValueError(f"loss.gamma must be in [0, 1), got {cfg.loss.gamma}")
    if not (0.0 <= cfg.dropout.p_max <= 1.0 and cfg.dropout.blackout_s >= 0.0):
        raise ValueError(f"dropout needs p_max in [0, 1] and blackout_s >= 0, got {dict(cfg.dropout)}")
    if cfg.optim.weight_decay < 0 or cfg.optim.max_grad_norm < 0:
        raise ValueError(f"optim.weight_decay and optim.max_grad_norm must be >= 0, got {dict(cfg.optim)}")
    if FILTER_KINDS[cfg.kind] != "supervised":
        who = "DAOF" if FILTER_KINDS[cfg.kind] == "dsac" else cfg.kind
        if cfg.network.missing_mask or cfg.dropout.p_max > 0 or cfg.dropout.blackout_s > 0:
            raise ValueError(f"network.missing_mask and dropout are the SLF's: {who} trains on complete data")
    if FILTER_KINDS[cfg.kind] == "dsac":
        if cfg.optim.utd <= 0:
            raise ValueError(f"optim.utd must be > 0 (gradient updates per frame), got {cfg.optim.utd}")
        if cfg.collector.total_frames <= cfg.collector.warmup_frames:
            raise ValueError(
                f"collector.total_frames={cfg.collector.total_frames} trains nothing: it must exceed "
                f"collector.warmup_frames={cfg.collector.warmup_frames}"
            )
        per_batch = cfg.collector.env_batch * cfg.collector.steps_per_batch
        if round(per_batch * cfg.optim.utd) < 1:
            raise ValueError(
                f"optim.utd={cfg.optim.utd} makes no update per collected batch of {per_batch} frames "
                "(collector.env_batch · collector.steps_per_batch)"
            )
    resolve_device(cfg.device)  # a GPU that is not there: one line, before any work
    try:
        overrides = {k: v for k, v in (cfg.overrides or {}).items() if k != "replay"}
        make_system(cfg.system, cfg.scenario, **overrides)
    except (TypeError, ValueError) as error:
        raise ValueError(str(error).splitlines()[0]) from None


def path_part(name: str) -> str:
    """``name`` as one directory name on every OS: a system's import path ``pkg.mod:Cls`` -> ``pkg.mod.Cls``."""
    return str(name).replace(":", ".")


def register_configs() -> None:
    """Register the schema with Hydra's ConfigStore (``defaults: [train_schema, ...]`` in ``daof/conf``)
    and the ``path_part`` resolver of its default ``output_dir``."""
    OmegaConf.register_new_resolver("path_part", path_part, replace=True)
    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
    # the system group's choice for a system of the user's code: no file of its own, the filter's budget
    ConfigStore.instance().store(group="system", name=USER_SYSTEM, node={}, package="_global_")


def _system_of_user_code(overrides: list[str]) -> tuple[list[str], str | None]:
    """``system=pkg.module:Class`` (or a ``daof.systems`` entry point): the overrides with the system group's
    empty ``USER_SYSTEM`` choice instead, and the system's name (None for a system of ``daof/conf/system``)."""
    from daof.envs.registry import is_import_path, system_entry_point

    chosen = [o for o in overrides if o.split("=", 1)[0] == "system"]
    name = chosen[-1].split("=", 1)[1] if chosen else None
    if name is None or (CONF_DIR / "system" / f"{name}.yaml").is_file():
        return overrides, None
    if not (is_import_path(name) or system_entry_point(name) is not None):
        return overrides, None  # a file of daof/conf/system, or an unknown name that Hydra refuses
    return [f"system={USER_SYSTEM}" if o in chosen else o for o in overrides], name


def _group_error(error: Exception) -> str | None:
    """One line for an unknown choice of a config group (``system=foo``), or None."""
    text = str(error)
    for group in GROUPS[:2]:
        if f"Could not find '{group}/" in text:
            choice = text.split(f"'{group}/", 1)[1].split("'", 1)[0]
            valid = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))
            more = " or an import path 'package.module:Class'" if group == "system" else ""
            return f"unknown {group} {choice!r}; valid: {', '.join(valid)}{more}"
    return None


def retired_overrides(overrides: list[str]) -> list[str]:
    """``overrides`` without those of a ``RETIRED_KEYS`` key that hold its surviving value (or delete it);
    one with another value is a ``ValueError`` line naming the removal and its log entry."""
    kept = []
    for item in overrides:
        key, _, value = item.partition("=")
        option = RETIRED_KEYS.get(key.lstrip("+~"))
        if option is None:
            kept.append(item)
            continue
        kinds, surviving = RETIRED_OPTIONS[option]
        value = value.strip().strip("'\"")  # a string option (its surviving value is a string)
        if not key.startswith("~") and value != surviving:
            raise ValueError(retired_refusal(option, value, kinds[0], name=key.lstrip("+")))
    return kept


def compose_config(overrides: list[str] = ()) -> DictConfig:
    """The resolved-on-access training config for command-line style ``overrides`` (``["filter=slf", ...]``).

    Every problem Hydra or the schema finds (an unknown key or choice, a wrong type, an impossible
    value) is one ``ValueError`` line, raised before any work.
    """
    overrides = retired_overrides(list(overrides))
    check_override_keys(TrainConfig, overrides, "config", "python -m daof.train --cfg lists every key", GROUPS)
    # system parameters are free-form: ``overrides.mu=0.8`` adds or replaces one
    overrides = ["++" + o.lstrip("+") if o.lstrip("+~").startswith("overrides.") else o for o in overrides]
    overrides, system = _system_of_user_code(overrides)
    register_configs()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="train", overrides=overrides)
        if system is not None:
            cfg.system = system
        OmegaConf.resolve(cfg)
    except (HydraException, OmegaConfBaseException) as error:
        raise ValueError(_group_error(error) or one_line(error)) from None
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise ValueError(f"config key(s) {missing} have no value")
    check_config(cfg)
    return cfg
