"""The numpy model a system offers the filterpy filters (``f_numpy``, ``g_numpy``, ``has_numpy_model``).

The EKF/UKF pick it from the system, never by its name: a system's own numpy code where the class
that writes it also owns the torch ``f``/``g`` it transcribes, the torch model otherwise.
"""

import numpy as np
import pytest
import torch
from daof.envs import make_system
from daof.envs.gaps import GappySystem
from daof.envs.system import StochasticSystem
from daof.envs.vehicle2dof import Vehicle2DOF

from daof.filters.kalman import NumpyModel, TorchModel, make_model


class YawRateOnly(Vehicle2DOF):
    """A subclass that changes ``g`` but not ``g_numpy``: its numpy code no longer fits it."""

    measurement_names = ("yaw_rate",)

    def g(self, x, u):
        return super().g(x, u)[..., 1:]


def points(rng, n=5):
    return rng.normal(0, [0.05, 0.3], (n, 2)), rng.normal(0, [0.05], (n, 1))


@pytest.mark.parametrize("name", ["veh2dof", "linear"])
def test_the_numpy_model_equals_the_torch_model_and_the_default_wrapper(name):
    system = make_system(name)
    x, u = points(np.random.default_rng(0))
    with torch.no_grad():
        torch_f = system.f(torch.from_numpy(x).float(), torch.from_numpy(u).float()).double().numpy()
    for fn in ("f", "g"):
        own = getattr(system, f"{fn}_numpy")(x, u)
        wrapped = getattr(StochasticSystem, f"{fn}_numpy")(system, x, u)  # the torch code in float64
        assert own.dtype == wrapped.dtype == np.float64 and own.shape == wrapped.shape
        np.testing.assert_allclose(own, wrapped, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(system.f_numpy(x, u), torch_f, rtol=1e-5, atol=1e-7)


def test_which_systems_have_a_numpy_model():
    veh, lin = make_system("veh2dof"), make_system("linear")
    assert veh.has_numpy_model and lin.has_numpy_model
    assert GappySystem(veh, 0.1, 0.0, 50).has_numpy_model
    assert make_system("veh2dof", replay={"runs": 2, "steps": 5}).has_numpy_model
    assert not YawRateOnly().has_numpy_model
    assert not GappySystem(YawRateOnly(), 0.1, 0.0, 50).has_numpy_model
    assert not make_system("veh14dof").has_numpy_model
    assert isinstance(make_model(veh), NumpyModel) and isinstance(make_model(lin, "numpy"), NumpyModel)
    assert isinstance(make_model(veh, "torch"), TorchModel)
    assert isinstance(make_model(YawRateOnly()), TorchModel)
    with pytest.raises(ValueError, match="no numpy model"):
        make_model(YawRateOnly(), "numpy")


def test_a_subclass_without_its_own_numpy_code_gets_its_own_torch_model():
    system = YawRateOnly()
    x, u = points(np.random.default_rng(1), n=3)
    model = make_model(system)
    assert model.g(x[0], u[0]).shape == (1,) and model.H(x[0], u[0]).shape == (1, 2)
    np.testing.assert_allclose(model.g(x, u), Vehicle2DOF().g_numpy(x, u)[:, 1:], rtol=1e-12)


def test_the_linear_numpy_model_follows_replaced_matrices():
    system = make_system("linear")
    x, u = np.array([0.3, -1.0]), np.array([0.5])
    np.testing.assert_array_equal(system.g_numpy(x, u), x @ system.C.double().numpy().T)
    system.C = torch.eye(2)
    np.testing.assert_array_equal(system.g_numpy(x, u), x)
    np.testing.assert_allclose(make_model(system).H(x, u), np.eye(2), atol=1e-15)


def test_the_default_wrapper_copies_the_system_again_after_to():
    system = make_system("veh2dof")
    x, u = points(np.random.default_rng(2))
    first = StochasticSystem.f_numpy(system, x, u)
    twin = system._float64_twin
    assert twin is not system and twin.prior.mean.dtype == torch.float64
    system.to("cpu")
    assert "_float64_twin" not in vars(system)
    np.testing.assert_array_equal(StochasticSystem.f_numpy(system, x, u), first)
