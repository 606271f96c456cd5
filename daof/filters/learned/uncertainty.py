"""A learned filter's uncertainty head: what the filter read at step t -> the log variance of its error per state.

The head is a small MLP trained after the filter, with the filter frozen, by the Gaussian negative
log-likelihood of the filter's own errors (``daof.train.uncertainty``). Its input is the filter's
``uncertainty_features``: the window h_t the filter reads (KalmanNet: its innovation, update and GRU
states), its estimate x̂_t and the start-up feature ρ_t. It lives in a file of its own beside the
filter's checkpoint (``best.pt`` -> ``best.uncertainty.pt``, ``head_path``) that names the digest of the
checkpoint it was fitted to; ``load_filter`` attaches it when the digests agree. So ``best.pt``, its
``state_dict`` and its export stay the filter alone.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from torch import nn
from torchrl.modules import MLP

from daof.io import atomic_save, safe_load

__all__ = ["HEAD_SUFFIX", "LOG_VARIANCE_RANGE", "UncertaintyHead", "file_digest", "head_path", "load_head", "save_head"]

#: the head's file beside a filter checkpoint ``<stem>.pt``: ``<stem>.uncertainty.pt``
HEAD_SUFFIX = ".uncertainty.pt"
#: the network's output is clamped to ± this around the fitted offset (e^±20 in variance: never inf or 0)
LOG_VARIANCE_RANGE = 20.0


def head_path(filter_path: str | Path) -> Path:
    """Where the head of the filter saved at ``filter_path`` lives: ``best.pt`` -> ``best.uncertainty.pt``."""
    path = Path(filter_path)
    return path.with_name(path.stem + HEAD_SUFFIX)


def file_digest(path: str | Path) -> str:
    """A short digest of a file's bytes (which filter checkpoint a head was fitted to)."""
    return hashlib.sha1(Path(path).read_bytes()).hexdigest()[:12]


class UncertaintyHead(nn.Module):
    """Features [..., in_features] -> log σ² [..., state_dim]: a normalised MLP plus a per-state offset.

    ``fit_normalizer`` sets the input's mean and std and the offset (log of the mean squared error per
    state) from training data; the last layer starts at zero, so an untrained head claims the filter's
    mean squared error everywhere.
    """

    def __init__(self, in_features: int, state_dim: int, num_cells: int = 64, depth: int = 2):
        super().__init__()
        if in_features < 1 or state_dim < 1:
            raise ValueError(f"a head needs in_features >= 1 and state_dim >= 1, got {in_features}, {state_dim}")
        self.in_features, self.state_dim, self.num_cells, self.depth = in_features, state_dim, num_cells, depth
        self.register_buffer("input_loc", torch.zeros(in_features))
        self.register_buffer("input_scale", torch.ones(in_features))
        self.register_buffer("log_variance_offset", torch.zeros(state_dim))
        self.mlp = MLP(
            in_features=in_features, out_features=state_dim, depth=depth, num_cells=num_cells, activation_class=nn.GELU
        )
        last = [m for m in self.mlp if isinstance(m, nn.Linear)][-1]
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    @property
    def settings(self) -> dict:
        keys = ("in_features", "state_dim", "num_cells", "depth")
        return {key: getattr(self, key) for key in keys}

    @torch.no_grad()
    def fit_normalizer(self, features: torch.Tensor, errors: torch.Tensor) -> None:
        """Input mean/std from ``features`` [M, in_features], the offset from ``errors`` [M, state_dim]."""
        self.input_loc.copy_(features.mean(0))
        self.input_scale.copy_(features.std(0).clamp_min(1e-6))
        self.log_variance_offset.copy_(errors.double().square().mean(0).clamp_min(1e-30).log().float())

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """log σ² of the filter's error per state."""
        out = self.mlp((features - self.input_loc) / self.input_scale)
        return self.log_variance_offset + out.clamp(-LOG_VARIANCE_RANGE, LOG_VARIANCE_RANGE)

    def std(self, features: torch.Tensor) -> torch.Tensor:
        """σ per state: exp(log σ² / 2)."""
        return (0.5 * self(features)).exp()


def save_head(head: UncertaintyHead, path: str | Path, filter_digest: str, extra: dict | None = None) -> None:
    """The head, the digest of the checkpoint it belongs to and ``extra`` (how it was fitted), atomically."""
    blob = {"settings": head.settings, "state_dict": head.state_dict(), "filter_digest": filter_digest}
    atomic_save({**blob, "extra": extra or {}}, path)


def load_head(path: str | Path, filter_digest: str | None = None) -> UncertaintyHead:
    """The head saved at ``path``; with ``filter_digest``, refuse (``ValueError``) one fitted to another checkpoint."""
    blob = safe_load(path)
    if not isinstance(blob, dict) or not {"settings", "state_dict", "filter_digest"} <= blob.keys():
        raise ValueError(f"{path} is not an uncertainty head")
    if filter_digest is not None and blob["filter_digest"] != filter_digest:
        raise ValueError(
            f"{path} was fitted to another filter checkpoint (digest {blob['filter_digest']}, this one "
            f"{filter_digest}): fit it again (python -m daof.train.uncertainty)"
        )
    head = UncertaintyHead(**blob["settings"])
    head.load_state_dict(blob["state_dict"])
    head.extra = blob.get("extra", {})
    head.filter_digest = blob["filter_digest"]
    return head.eval()
