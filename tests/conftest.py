"""Shared test set-up: quiet, single-threaded, offline."""

import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "disabled")


@pytest.fixture(autouse=True)
def _single_thread():
    """Small tensors: one thread is faster and keeps timing noise out of CI."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)
