"""The network every learned filter runs, and the per-step features it reads.

``PolicyNet``: window (+ ν_t, ρ_t) -> per-channel normalisation -> MLP -> (loc, σ) of the
pre-squash Gaussian. ``startup_feature`` is ρ_t; ``schedule_row`` reads the per-step tables
(bounds, gains, scales) that hold their last row once the filter has settled.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP

__all__ = ["SCHEDULE_STEPS", "PolicyNet", "hold_last_value", "schedule_row", "startup_feature"]

#: length of the per-step tables (DAOF-v1's bound schedule b_t, ...); later steps use the last entry
SCHEDULE_STEPS = 50


def schedule_row(table: torch.Tensor, step) -> torch.Tensor:
    """Row t of a per-step table [S, k] for t ≥ 1 (an int, a [..., 1] integer tensor, or None: settled).

    Steps after S use the last row.
    """
    if step is None:
        return table[-1]
    if isinstance(step, int):
        return table[min(max(step, 1), len(table)) - 1]
    return table[step.squeeze(-1).clamp(1, len(table)) - 1]


def startup_feature(step) -> torch.Tensor:
    """ρ_t = max(0, 1 − (t − 1)/SCHEDULE_STEPS) for t ≥ 1 ([..., 1] integer tensor -> float [..., 1]).

    1 at the first measurement, 0 once the filter has settled (an int t gives a float). After a
    reset the window is N copies of the first frame and, past t = N, says nothing of t; the
    start-up (where the prior's error is pulled in) needs other updates than the settled filter,
    so the networks read ρ_t.
    """
    if isinstance(step, int):  # the streaming filter's hot path
        return min(max(1.0 - (step - 1) / SCHEDULE_STEPS, 0.0), 1.0)
    # in float64 like the int path, then rounded: ``run`` and an env rollout agree to the bit
    return (1.0 - (step.double() - 1.0) / SCHEDULE_STEPS).clamp(0.0, 1.0).float()


def hold_last_value(y: torch.Tensor, fill: torch.Tensor) -> torch.Tensor:
    """[runs, steps, m] with NaN gaps -> each NaN replaced by its channel's last present value.

    Leading gaps (nothing seen yet) take ``fill`` [m]. Learned filters are trained on complete data;
    holding the last value is their treatment of sensor dropouts (docs/missing_data.md).
    """
    missing = torch.isnan(y)
    if not missing.any():
        return y
    steps = torch.arange(y.shape[1], device=y.device).view(1, -1, 1).expand_as(y)
    last = torch.where(missing, -1, steps).cummax(1).values  # index of the last present value, −1 if none
    held = torch.gather(y, 1, last.clamp_min(0))
    return torch.where(last < 0, fill.to(y), held)


class PolicyNet(nn.Module):
    """Raw window (+ ν_t, ρ_t) -> per-channel normalisation -> MLP -> (loc, σ) of the pre-squash Gaussian.

    σ = exp(clamp(log σ, −20, 0.5)) as in DSAC-T. The normalisation is buffers fitted on training
    data, so it travels with the weights. ``innovation`` (a function of the window, or None) adds
    the newest innovation ν_t divided by its std at step t (``innovation_scale``, one row per
    step); ``startup_input`` adds ρ_t (``startup_feature``). The MLP's input is [window, ν_t, ρ_t].
    """

    def __init__(
        self,
        in_features: int,
        out_dim: int,
        num_cells: int,
        depth: int,
        startup_input: bool = False,
        innovation=None,
        innovation_dim: int = 0,
        gelu_approximate: str = "none",
    ):
        super().__init__()
        self.register_buffer("input_loc", torch.zeros(in_features))
        self.register_buffer("input_scale", torch.ones(in_features))
        self.innovation = innovation
        self.innovation_dim = innovation_dim if innovation else 0
        self.register_buffer("innovation_scale", torch.ones(SCHEDULE_STEPS, self.innovation_dim))
        self.startup_input = startup_input
        #: width of ``features``: the MLP's input
        self.feature_dim = in_features + self.innovation_dim + int(startup_input)
        self.gelu_approximate = gelu_approximate
        self.mlp = MLP(
            in_features=self.feature_dim,
            out_features=2 * out_dim,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.GELU,
            activation_kwargs={"approximate": gelu_approximate},
        )

    def normalize(self, window: torch.Tensor) -> torch.Tensor:
        return (window - self.input_loc) / self.input_scale

    def features(self, window: torch.Tensor, step=None) -> torch.Tensor:
        """The MLP's input: the normalised window, then ν_t and ρ_t where used."""
        parts = [self.normalize(window)]
        if self.innovation is not None:
            parts.append(self.innovation(window) / schedule_row(self.innovation_scale, step))
        if self.startup_input:
            parts.append(startup_feature(step))
        return torch.cat(parts, -1) if len(parts) > 1 else parts[0]

    def forward(self, window: torch.Tensor, step=None):
        loc, log_std = self.mlp(self.features(window, step)).chunk(2, -1)
        return loc, log_std.clamp(-20.0, 0.5).exp()
