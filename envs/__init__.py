"""Systems (pure torch) and their TorchRL filtering environments."""

from envs.linear import LinearOscillator, LinearParams
from envs.registry import SYSTEMS, make_system, register_system
from envs.system import StochasticSystem
from envs.vehicle2dof import Vehicle2DOF, Vehicle2DOFParams

register_system("veh2dof", Vehicle2DOF, Vehicle2DOFParams)
register_system("linear", LinearOscillator, LinearParams)

__all__ = ["SYSTEMS", "StochasticSystem", "make_system", "register_system", "make_env"]


def make_env(*args, **kwargs):
    """Build the batched filtering env with its history window (see ``envs.filtering_env``)."""
    from envs.filtering_env import make_env as _make_env

    return _make_env(*args, **kwargs)
