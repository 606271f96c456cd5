"""Systems (pure torch) and their TorchRL filtering environments."""

from daof.envs.linear import LinearOscillator, LinearParams
from daof.envs.registry import SYSTEMS, make_system, register_system
from daof.envs.system import StochasticSystem
from daof.envs.vehicle2dof import Vehicle2DOF, Vehicle2DOFParams
from daof.envs.vehicle14dof import Vehicle14DOF, Vehicle14DOFParams

register_system("veh2dof", Vehicle2DOF, Vehicle2DOFParams)
register_system("linear", LinearOscillator, LinearParams)
register_system("veh14dof", Vehicle14DOF, Vehicle14DOFParams)

from daof.envs import gym_env  # noqa: E402, F401  (registers gymnasium id daof/Veh2DOF-v0)

__all__ = ["SYSTEMS", "StochasticSystem", "make_system", "register_system", "make_env"]


def make_env(*args, **kwargs):
    """Build the batched filtering env with its history window (see ``daof.envs.filtering_env``)."""
    from daof.envs.filtering_env import make_env as _make_env

    return _make_env(*args, **kwargs)
