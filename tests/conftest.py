"""Shared test set-up: quiet, single-threaded, offline."""

import os

import daof.envs as envs
import pytest
import torch

os.environ.setdefault("WANDB_MODE", "disabled")
#: every figure the tests render must pass daof.evaluate.figures.layout_problems
os.environ["DAOF_STRICT_FIGURES"] = "1"


@pytest.fixture(autouse=True)
def _single_thread():
    """Small tensors: one thread is faster and keeps timing noise out of CI."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


@pytest.fixture(scope="session")
def veh():
    """The veh2dof system (nominal)."""
    return envs.make_system("veh2dof")


@pytest.fixture(scope="session")
def lin():
    """The linear-Gaussian oscillator."""
    return envs.make_system("linear")


@pytest.fixture(scope="session")
def local_ray():
    """A local Ray of two CPUs for the whole session (a start costs seconds); ``run_jobs`` runs its tasks there."""
    ray = pytest.importorskip("ray")
    from daof.experiments.ray_jobs import start_ray

    start_ray(num_cpus=2)
    yield
    ray.shutdown()
