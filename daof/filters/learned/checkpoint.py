"""``load_filter``: a learned filter from a saved file (``best.pt``, ``final.pt``) or a training ``checkpoint.pt``.

Files are read with ``daof.io.safe_load`` (``torch.load(weights_only=True)``): tensors and plain
data only, never code; a bad file is one ``ValueError`` line naming it. A learned filter's uncertainty
head, saved beside its file (``best.uncertainty.pt``), loads with it (``daof.filters.learned.uncertainty``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

from daof.envs.registry import make_system
from daof.envs.system import StochasticSystem
from daof.filters.learned.base import LearnedFilter
from daof.filters.learned.config import FilterConfig
from daof.filters.learned.uncertainty import file_digest, head_path, load_head
from daof.io import safe_load

__all__ = ["load_filter"]

#: the entries of a filter file or training checkpoint that are mappings when present
_MAPPINGS = ("config", "state_dict", "extra", "filter", "filter_config", "training")


def _filter_config(fields: dict, path: Path) -> FilterConfig:
    """A stored filter config; one written before options were retired loads if it holds their surviving values."""
    try:
        return FilterConfig.from_dict(fields)
    except TypeError as error:  # a field this version does not know
        raise ValueError(f"checkpoint {path} has a filter config this version cannot read ({error})") from None
    except ValueError as error:  # a retired option with a value that no longer exists (or an invalid one)
        raise ValueError(f"checkpoint {path}: {error}") from None


def _contents(blob, path: Path) -> tuple[FilterConfig, dict, dict, dict]:
    """(config, state dict, extra, system overrides) of a filter file or a training checkpoint."""
    if isinstance(blob, dict):
        for key in _MAPPINGS:
            if not isinstance(blob.get(key) or {}, dict):
                kind = type(blob[key]).__name__
                raise ValueError(f"{path} is not a learned-filter checkpoint: its {key!r} is a {kind}")
    if isinstance(blob, dict) and {"config", "state_dict"} <= blob.keys():  # LearnedFilter.save
        config = _filter_config({"gelu_approximate": "none", **blob["config"]}, path)  # older ones: exact GELU
        return config, blob["state_dict"], blob.get("extra", {}), {}
    if isinstance(blob, dict) and {"config", "filter", "training"} <= blob.keys():  # FilterTrainer.save_checkpoint
        training, run = blob["training"], blob["config"]
        extra = {"frames": training.get("frames"), "updates": training.get("updates")}
        extra |= {"wall_s": training.get("wall"), "history": training.get("history", [])}
        # the model's parameters; a replayed episode bank does not change the model
        overrides = {k: v for k, v in (run.get("overrides") or {}).items() if k != "replay"}
        if blob.get("filter_config"):  # the filter's own config, as the trainer built it
            config = _filter_config(blob["filter_config"], path)
        else:  # older checkpoints: from the training config
            try:
                config = FilterConfig.from_training(run, blob["filter"])
            except ValueError as error:
                raise ValueError(f"checkpoint {path}: {error}") from None
        return config, blob["filter"], extra, overrides
    raise ValueError(f"{path} is not a learned-filter checkpoint")


def load_filter(path: str | Path, system: StochasticSystem | None = None, expect: dict | None = None):
    """The learned filter saved at ``path``: by ``LearnedFilter.save`` or a training ``checkpoint.pt``.

    ``expect`` checks config fields (system, window, …); ``system`` is the system to filter (by
    default the checkpoint's: its name, scenario and, for a training checkpoint, parameter overrides).
    Every refusal is one line naming the file: ``FileNotFoundError`` if there is none, else ``ValueError``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no filter checkpoint at {path}")
    config, state, extra, overrides = _contents(safe_load(path), path)
    for key, value in (expect or {}).items():
        if getattr(config, key) != value:
            raise ValueError(f"checkpoint {path} has {key}={getattr(config, key)!r}, expected {value!r}")
    if system is not None and system.name != config.system:
        raise ValueError(f"checkpoint {path} is a filter for {config.system!r}, not for {system.name!r}")
    if system is None and overrides:
        system = make_system(config.system, config.scenario, **overrides)
    module = LearnedFilter(config, system)
    if "error_scale" not in state:  # saved before the scales came from data: the system's, as it trained
        state = {**state, "error_scale": module.error_scale}
    try:
        module.load_state_dict(state)
    except RuntimeError as error:  # saved by another version of the filter (other inputs or sizes)
        first = str(error).strip().splitlines()[-1].strip()
        raise ValueError(f"checkpoint {path} does not fit this filter's layout ({first})") from None
    module.extra = extra
    module.path = path
    _attach_head(module, path)
    return module.eval()


def _attach_head(module: LearnedFilter, path: Path) -> None:
    """The uncertainty head beside ``path`` (``head_path``), if there is one fitted to this very file.

    A head fitted to another version of the checkpoint is left off with a warning: the filter loads,
    without a std.
    """
    where = head_path(path)
    if not where.is_file():
        return
    try:
        module.attach_uncertainty(load_head(where, file_digest(path)))
    except ValueError as error:
        warnings.warn(f"{error}; the filter loads without its uncertainty head", stacklevel=3)
