"""Losses for training learned filters: DSAC-T (a TorchRL LossModule)."""

from daof.losses.dsac_t import DSACTLoss, clip_sampled_target, critic_surrogate

__all__ = ["DSACTLoss", "clip_sampled_target", "critic_surrogate"]
