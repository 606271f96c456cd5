"""``Vehicle14DOF``: the 14-DOF car as a ``StochasticSystem`` data source (spec §0, §9).

The internal episode state (28 ODE states, PI integral, held GNSS fix, the disturbance acting
over the next filter step) differs from the six estimated states, so ``reset_episode`` and
``advance`` are overridden with the base-class contract: ``sim`` is a TensorDict [runs] with
``t``, ``params`` and the internal tensors; ``advance`` returns (new ``sim``, ``obs``) with the
true states, the 16 measurement channels and empty controls at t + 1. There is no model for
filters (``has_model = False``): ``f`` and ``g`` keep raising ``NotImplementedError``.
"""

from __future__ import annotations

import torch
from daof.envs.noise import GaussianMixtureNoise, GaussianNoise
from daof.envs.system import StochasticSystem
from daof.envs.vehicle14dof.dynamics import N_STATE, rhs
from daof.envs.vehicle14dof.integrate import drive_inputs, integrate_substeps, make_substep
from daof.envs.vehicle14dof.manoeuvre import sample_manoeuvre
from daof.envs.vehicle14dof.params import DEG, KMH, Constants, Vehicle14DOFParams
from daof.envs.vehicle14dof.sensors import (
    MEASUREMENT_NAMES,
    MEASUREMENT_UNITS,
    ChannelLaplaceNoise,
    clean_channels,
    laplace_scale,
    measure,
    sample_biases,
)
from tensordict import TensorDict

__all__ = ["Vehicle14DOF", "initial_state", "truth"]

G = 9.81


def initial_state(V0: torch.Tensor, c: Constants) -> torch.Tensor:
    """§5.11: all zero except u = V0 and free-rolling wheel speeds; [runs, 28]."""
    x = torch.zeros(V0.shape[0], N_STATE, dtype=c.dtype, device=c.device)
    x[:, 14] = V0
    x[:, 24:28] = c.free_rolling_omega(V0)
    return x


def truth(x: torch.Tensor, a_x: torch.Tensor) -> torch.Tensor:
    """The §9 estimated states (θ, φ, r, β = atan2(v, u), V_x = u, a_x = u̇ − r v), SI, [runs, 6]."""
    beta = torch.atan2(x[:, 15], x[:, 14])
    return torch.stack([x[:, 4], x[:, 3], x[:, 19], beta, x[:, 14], a_x], -1)


#: the prior's std where a state is exactly 0 at t = 0, in report units [°, °, °/s, °, km/h, g]
PRIOR_STD_FLOOR = torch.tensor([0.001, 0.002, 0.005, 0.002, 0.003, 0.0001])


class Vehicle14DOF(StochasticSystem):
    """14-DOF passenger car in the randomised "large curvature turning" manoeuvre."""

    name = "veh14dof"
    scenarios = ("nominal",)
    has_model = False
    state_names = ("pitch", "roll", "yaw_rate", "side_slip", "vx", "ax")
    state_units = ("rad", "rad", "rad/s", "rad", "m/s", "m/s^2")
    #: the paper's reporting units; multiply a state (or error) by ``report_scale`` to get them
    report_units = ("deg", "deg", "deg/s", "deg", "km/h", "g")
    measurement_names = MEASUREMENT_NAMES
    measurement_units = MEASUREMENT_UNITS
    control_names = ()

    def __init__(self, scenario: str = "nominal", params: Vehicle14DOFParams | None = None):
        self.scenario = scenario
        self.p = p = params or Vehicle14DOFParams()
        self.dtype = p.torch_dtype
        self.dt = p.dt
        self.n_sub = round(p.dt / p.h)
        if self.n_sub < 1 or abs(self.n_sub * p.h - p.dt) > 1e-9:
            raise ValueError(f"the filter step dt={p.dt} must be a whole number of RK4 steps h={p.h}")
        self._consts: dict[str, Constants] = {}
        self._substeps: dict[str, object] = {}
        self.report_scale = torch.tensor([1 / DEG, 1 / DEG, 1 / DEG, 1 / DEG, 1 / KMH, 1 / G])
        w = p.dist_weights
        self.process_noise = GaussianMixtureNoise(w, (0.0, 0.0), p.dist_std_ratio, p.dist_scale, joint=p.dist_joint)
        b = laplace_scale(p)
        self._laplace = ChannelLaplaceNoise(b)
        self.measurement_noise = ChannelLaplaceNoise([*b, 0.0])
        self.prior = self._derive_prior()

    # ----------------------------------------------------------------- helpers
    def constants(self, device) -> Constants:
        """Derived parameters in the internal dtype on ``device`` (built once per device)."""
        key = str(torch.device(device))
        if key not in self._consts:
            self._consts[key] = Constants(self.p, self.dtype, device)
        return self._consts[key]

    def substep(self, device):
        """The RK4 step function for ``device`` (compiled once if ``params.compile``)."""
        key = str(torch.device(device))
        if key not in self._substeps:
            self._substeps[key] = make_substep(self.constants(device), self.p.h, self.p.compile)
        return self._substeps[key]

    def to(self, device):
        super().to(device)
        self._laplace.to(device)
        return self

    def _derive_prior(self) -> GaussianNoise:
        """Mean and std of the six states at t = 0 over V0 ~ U[60, 80] km/h (§5.11, driver on).

        Evaluated on a fine V0 grid (the midpoint rule for the uniform law); states that are
        exactly 0 at t = 0 get the floor ``PRIOR_STD_FLOOR`` so the covariance is definite.
        """
        c = Constants(self.p, torch.float64, "cpu")
        lo, hi = self.p.v0_kmh
        V0 = (lo + (hi - lo) * (torch.arange(200, dtype=torch.float64) + 0.5) / 200) * KMH
        x = initial_state(V0, c)
        zeros = torch.zeros(200, dtype=torch.float64)
        man = TensorDict({"v_ref": V0, "amplitude": zeros, "t1": zeros + 1, "t2": zeros + 2}, [200])
        delta_sw, T_d, T_b, _ = drive_inputs(x, zeros, zeros, man, c, self.p.h)
        _, aux = rhs(x, delta_sw, T_d, T_b, torch.zeros(200, 2, dtype=torch.float64), c, with_aux=True)
        s = truth(x, aux.a_x)
        std = torch.maximum(s.std(0, correction=0), PRIOR_STD_FLOOR.double() / self.report_scale.double())
        return GaussianNoise.diagonal(s.mean(0).float(), std.float())

    def time(self, t: torch.Tensor) -> torch.Tensor:
        """Simulated time t·Δt [s] of integer steps ``t``, the product taken in the internal dtype.

        (``t * dt`` on a long tensor is a float32 product: a float64 run would get a float32 time base.)
        """
        return t.to(self.dtype) * self.dt

    def _observe(self, x, integ, t, man, dist, c: Constants):
        """Truth and clean channels at step t; the inputs are those of the next RK4 step (k1)."""
        delta_sw, T_d, T_b, _ = drive_inputs(x, integ, self.time(t), man, c, self.p.h)
        _, aux = rhs(x, delta_sw, T_d, T_b, dist, c, with_aux=True)
        return truth(x, aux.a_x), clean_channels(x, delta_sw, aux, c)

    # ----------------------------------------------------------------- episodes
    def sample_params(self, runs, generator, device):
        man = sample_manoeuvre(runs, generator, self.p, device, self.dtype)
        biases = sample_biases(runs, generator, self.p, device, self.dtype)
        return TensorDict({"manoeuvre": man, "sensor": biases}, batch_size=[runs], device=device)

    def _disturbance(self, runs, generator, device) -> torch.Tensor:
        """(F_d, M_d) at P [runs, 2], redrawn every filter step (§0): one mixture component per draw,
        shared by the force and the moment (``params.dist_joint``)."""
        return self.process_noise.sample((runs,), generator).to(device=device, dtype=self.dtype)

    def _noise(self, runs, generator, device) -> torch.Tensor:
        return self._laplace.sample((runs,), generator).to(device=device, dtype=self.dtype)

    def reset_episode(self, runs, generator, device="cpu") -> TensorDict:
        """New episodes at t = 0: manoeuvre, sensor biases, x_0 of §5.11, a first GNSS fix."""
        self.process_noise.to(device)
        self._laplace.to(device)
        c = self.constants(device)
        params = self.sample_params(runs, generator, device)
        x = initial_state(params["manoeuvre", "v_ref"], c)
        integ = torch.zeros(runs, dtype=self.dtype, device=device)
        t = torch.zeros(runs, dtype=torch.long, device=device)
        dist = self._disturbance(runs, generator, device)
        _, clean = self._observe(x, integ, t, params["manoeuvre"], dist, c)
        gnss0 = clean[:, 11:15] + self._noise(runs, generator, device)[:, 11:15]
        return TensorDict(
            {"x": x, "integral": integ, "t": t, "disturbance": dist, "gnss": gnss0, "params": params},
            batch_size=[runs],
            device=device,
        )

    def advance(self, sim: TensorDict, generator: torch.Generator):
        """One filter step t -> t + 1 (20 RK4 steps); returns (new sim, obs at t + 1)."""
        runs, device = sim.batch_size[0], sim["x"].device
        c = self.constants(device)
        man = sim["params", "manoeuvre"]
        x, integ = integrate_substeps(
            sim["x"],
            sim["integral"],
            self.time(sim["t"]),
            self.n_sub,
            man,
            sim["disturbance"],
            c,
            self.p.h,
            self.substep(device),
        )
        t = sim["t"] + 1
        dist = self._disturbance(runs, generator, device)
        state, clean = self._observe(x, integ, t, man, dist, c)
        y, held = measure(clean, t, sim["gnss"], sim["params", "sensor"], self._noise(runs, generator, device), self.p)
        new_sim = TensorDict(
            {"x": x, "integral": integ, "t": t, "disturbance": dist, "gnss": held, "params": sim["params"]},
            batch_size=sim.batch_size,
        )
        empty = torch.zeros(runs, 0, device=device)
        obs = TensorDict(
            {"state": state.float(), "measurement": y.float(), "control": empty, "prev_control": empty.clone()},
            batch_size=sim.batch_size,
        )
        return new_sim, obs

    def describe(self) -> dict:
        info = super().describe()
        info.update(report_units=list(self.report_units), report_scale=self.report_scale.tolist())
        info["rk4_step"] = self.p.h
        info["dtype"] = self.p.dtype
        return info
