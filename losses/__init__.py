"""Losses for training learned filters: DSAC-T (a TorchRL LossModule) and its target update."""

from daof.losses.dsac_t import DSACTLoss, clip_sampled_target, critic_surrogate
from daof.losses.target_update import ForeachSoftUpdate

__all__ = ["DSACTLoss", "ForeachSoftUpdate", "clip_sampled_target", "critic_surrogate"]
