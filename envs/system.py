"""StochasticSystem: a discrete-time nonlinear system with noise, pure torch, no RL.

Time convention (shared by ``simulate``, the env and every filter):

* x_0 ~ prior is never measured; every filter starts from x̂_0 = prior mean (and P_0 = prior
  covariance where it uses one).
* For t = 1..T: x_t = f_true(x_{t-1}, u_{t-1}) + ξ_{t-1},  y_t = g_true(x_t, u_t) + ζ_t.
* A filter's estimate x̂_t may use y_1..y_t and u_0..u_t.

``f``/``g`` are the *nominal* model that model-based filters may call. The true per-episode
dynamics may differ (scenario ``mismatch``): they read per-run parameters from ``params``.

One episode's simulator state lives in a TensorDict ``sim`` of batch ``[runs]`` with at least
``x`` (internal state), ``u`` (current control), ``t`` (step index) and ``params`` (per-run
episode parameters), so that an env can reset a subset of runs by masked assignment.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from daof.envs.checks import as_seed
from daof.envs.noise import GaussianNoise, Noise
from tensordict import TensorDict

__all__ = ["StochasticSystem"]


class StochasticSystem:
    """Base class. Subclasses set the attributes below and implement the model methods."""

    name: str = "system"
    scenario: str = "nominal"
    scenarios: tuple[str, ...] = ("nominal",)
    dt: float
    #: the unit of ``dt`` in reports and figures; "step" for a discrete-time model (its dt is 1)
    time_unit: str = "s"
    state_names: tuple[str, ...]
    state_units: tuple[str, ...]
    measurement_names: tuple[str, ...]
    measurement_units: tuple[str, ...]
    control_names: tuple[str, ...] = ()
    prior: GaussianNoise
    process_noise: Noise
    measurement_noise: Noise
    #: whether filters may call f and g (False for simulator-only systems such as veh14dof)
    has_model: bool = True
    #: observations also carry ``missing`` (0/1 per measurement channel): ``daof.envs.gaps.GappySystem``
    reports_missing: bool = False

    # ----------------------------------------------------------------- scales from data
    def scales(self):
        """Output range and error scale per state from the system's simulated data (``daof.envs.scales``)."""
        from daof.envs.scales import data_scales

        return data_scales(self)

    def _scale(self, name: str, field: str) -> torch.Tensor:
        """An override set on this system (``system.state_low = ...``), else the data's value."""
        value = self.__dict__.get(name)
        if value is not None:
            return value
        value = getattr(self.scales(), field)
        for where in self.__dict__.get("_moves", ()):  # where ``to`` has put the system's tensors
            value = value.to(where)
        return value

    @property
    def state_low(self) -> torch.Tensor:
        """Lower end of the output range per state: the env's action spec, where learned estimates stop."""
        return self._scale("_state_low", "low")

    @state_low.setter
    def state_low(self, value) -> None:
        self._state_low = None if value is None else torch.as_tensor(value, dtype=torch.float32)

    @property
    def state_high(self) -> torch.Tensor:
        """Upper end of the output range per state."""
        return self._scale("_state_high", "high")

    @state_high.setter
    def state_high(self, value) -> None:
        self._state_high = None if value is None else torch.as_tensor(value, dtype=torch.float32)

    @property
    def error_scale(self) -> torch.Tensor:
        """Typical error of a decent filter per state; the env's default reward weights are 1/(n·s²)."""
        return self._scale("_error_scale", "error")

    @error_scale.setter
    def error_scale(self, value) -> None:
        self._error_scale = None if value is None else torch.as_tensor(value, dtype=torch.float32)

    # ----------------------------------------------------------------- dimensions
    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def measurement_dim(self) -> int:
        return len(self.measurement_names)

    @property
    def control_dim(self) -> int:
        return len(self.control_names)

    # ----------------------------------------------------------------- nominal model
    def f(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Noise-free nominal transition x_{t+1} = f(x_t, u_t), batched over leading dims."""
        raise NotImplementedError(f"{self.name} offers no transition model to filters")

    def g(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Noise-free nominal measurement y_t = g(x_t, u_t), batched over leading dims."""
        raise NotImplementedError(f"{self.name} offers no measurement model to filters")

    # ----------------------------------------------------------------- the model in numpy
    def f_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``f`` on float64 numpy arrays, batched over leading dims: the model of the filterpy filters.

        By default the torch ``f`` of a float64 CPU copy of the system (made at the first call, and
        again after ``to``). A system whose own numpy code is faster overrides ``f_numpy`` and
        ``g_numpy`` (see ``has_numpy_model``).
        """
        return self._torch_in_numpy("f", x, u)

    def g_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``g`` on float64 numpy arrays, batched over leading dims (default: the torch ``g``, as ``f_numpy``)."""
        return self._torch_in_numpy("g", x, u)

    @property
    def has_numpy_model(self) -> bool:
        """Whether ``f_numpy`` and ``g_numpy`` are numpy code of the system's own rather than the torch wrapper.

        Such code must also take complex arrays (the Kalman filters take complex-step Jacobians of
        it). Only where the class that writes ``f_numpy`` (``g_numpy``) also owns the ``f`` (``g``)
        it transcribes: a subclass that changes ``f`` or ``g`` but not its numpy twin inherits numpy
        code that no longer fits it, so users of the pair (``daof.filters.kalman.make_model``) take the
        torch model when this is False.
        """
        mro = type(self).__mro__

        def owner(name: str) -> type:
            return next(cls for cls in mro if name in vars(cls))

        return all(
            owner(f"{fn}_numpy") is not StochasticSystem and issubclass(owner(f"{fn}_numpy"), owner(fn))
            for fn in ("f", "g")
        )

    def _torch_in_numpy(self, fn: str, x, u) -> np.ndarray:
        twin = self.__dict__.get("_float64_twin")
        if twin is None:
            # StochasticSystem.to hands its argument to Tensor.to, which also accepts a dtype
            twin = self._float64_twin = copy.deepcopy(self).to("cpu").to(torch.float64)
        x, u = (torch.from_numpy(np.asarray(v, np.float64)) for v in (x, u))
        with torch.no_grad():
            return getattr(twin, fn)(x, u).numpy()

    # ----------------------------------------------------------------- divergence
    #: an estimate more than this many widths (high − low) of the plausible range beyond either end
    #: of it has diverged: the range widened by its own width on each side, three times as wide
    divergence_margin: float = 1.0

    def divergence_limits(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(low, high) per state beyond which an estimate has diverged: ``state_low/high`` ∓ margin · width."""
        low, high = self.state_low.double(), self.state_high.double()
        width = high - low
        return low - self.divergence_margin * width, high + self.divergence_margin * width

    def diverged_runs(self, estimates: torch.Tensor) -> torch.Tensor:
        """Runs [runs] (bool) of ``estimates [runs, steps, n]`` with a non-finite estimate or one past the limits."""
        low, high = (v.to(estimates.device) for v in self.divergence_limits())
        x = estimates.double()
        inside = (x >= low) & (x <= high)  # False for NaN
        return ~inside.flatten(1).all(-1)

    # ----------------------------------------------------------------- uncertain model parameters
    def uncertain_parameters(self) -> dict[str, tuple[float, float]]:
        """Model parameters the scenario draws per run, as ``name -> (low, high)`` of a uniform prior.

        Empty when the nominal model is the true one. A filter may infer these (``JointParameterPF``)
        through ``f_with`` and ``g_with``.
        """
        return {}

    def f_with(self, x: torch.Tensor, u: torch.Tensor, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``f`` with the ``uncertain_parameters`` set to ``params`` (each broadcastable to ``x[..., 0]``)."""
        raise NotImplementedError(f"{self.name} has no uncertain model parameters")

    def g_with(self, x: torch.Tensor, u: torch.Tensor, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``g`` with the ``uncertain_parameters`` set to ``params`` (each broadcastable to ``x[..., 0]``)."""
        raise NotImplementedError(f"{self.name} has no uncertain model parameters")

    # ----------------------------------------------------------------- episode simulation
    def sample_params(self, runs: int, generator: torch.Generator, device) -> TensorDict:
        """Per-run episode parameters (control schedule, true model parameters)."""
        return TensorDict({}, batch_size=[runs], device=device)

    def control(self, t: torch.Tensor, params: TensorDict) -> torch.Tensor:
        """Known control u_t for integer steps ``t`` ([runs]) -> [runs, control_dim]."""
        return torch.zeros(*t.shape, self.control_dim, device=t.device)

    def transition(self, x, u, params: TensorDict, generator) -> torch.Tensor:
        """True noisy transition x_{t+1} = f_true(x_t, u_t) + ξ_t."""
        return self.f(x, u) + self.process_noise.sample(x.shape[:-1], generator)

    def measure(self, x, u, params: TensorDict, generator) -> torch.Tensor:
        """True noisy measurement y_t = g_true(x_t, u_t) + ζ_t."""
        return self.g(x, u) + self.measurement_noise.sample(x.shape[:-1], generator)

    def truth(self, x: torch.Tensor) -> torch.Tensor:
        """Estimated-state vector from the internal state (identity unless overridden)."""
        return x

    def reset_episode(self, runs: int, generator: torch.Generator, device="cpu") -> TensorDict:
        """Draw ``runs`` new episodes at t = 0: parameters, x_0 ~ prior, u_0."""
        params = self.sample_params(runs, generator, device)
        t = torch.zeros(runs, dtype=torch.long, device=device)
        x0 = self.prior.sample((runs,), generator)
        return TensorDict(
            {"x": x0, "t": t, "u": self.control(t, params), "params": params},
            batch_size=[runs],
            device=device,
        )

    def advance(self, sim: TensorDict, generator: torch.Generator) -> tuple[TensorDict, TensorDict]:
        """One step t -> t+1. Returns the new ``sim`` and what is observed at t+1.

        The observation TensorDict holds ``state`` (truth, hidden from filters), ``measurement``
        y_{t+1}, ``control`` u_{t+1} and ``prev_control`` u_t.
        """
        params = sim["params"]
        x_next = self.transition(sim["x"], sim["u"], params, generator)
        t_next = sim["t"] + 1
        u_next = self.control(t_next, params)
        y_next = self.measure(x_next, u_next, params, generator)
        new_sim = TensorDict({"x": x_next, "t": t_next, "u": u_next, "params": params}, batch_size=sim.batch_size)
        obs = TensorDict(
            {
                "state": self.truth(x_next),
                "measurement": y_next,
                "control": u_next,
                "prev_control": sim["u"],
            },
            batch_size=sim.batch_size,
        )
        return new_sim, obs

    @torch.no_grad()
    def simulate(self, runs: int, steps: int, seed: int, device="cpu") -> TensorDict:
        """Simulate ``runs`` independent episodes of ``steps`` measured steps (t = 1..steps).

        Returns a TensorDict of batch ``[runs, steps]`` with ``state``, ``measurement``,
        ``control`` and ``prev_control``; the same seed gives the same data.
        """
        if runs < 1 or steps < 1:
            raise ValueError(f"simulate needs runs >= 1 and steps >= 1, got runs={runs}, steps={steps}")
        generator = torch.Generator(device=device).manual_seed(as_seed(seed))
        sim = self.reset_episode(runs, generator, device)
        frames = []
        for _ in range(steps):
            sim, obs = self.advance(sim, generator)
            frames.append(obs)
        return torch.stack(frames, dim=1)

    # ----------------------------------------------------------------- helpers
    def to(self, device) -> StochasticSystem:
        """Move noises and tensor attributes to ``device`` (in place)."""
        self.__dict__.pop("_float64_twin", None)  # the model's numpy wrapper makes a new one
        self._moves = [*self.__dict__.get("_moves", ()), device]  # the data scales follow (``_scale``)
        for noise in (self.prior, self.process_noise, self.measurement_noise):
            noise.to(device)
        for name, value in vars(self).items():
            if isinstance(value, torch.Tensor):
                setattr(self, name, value.to(device))
        return self

    def describe(self) -> dict:
        """Plain-data description (for reports and checkpoints)."""
        return {
            "name": self.name,
            "scenario": self.scenario,
            "dt": self.dt,
            "states": list(self.state_names),
            "units": list(self.state_units),
            "measurements": list(self.measurement_names),
            "controls": list(self.control_names),
        }


class SystemWrapper(StochasticSystem):
    """A system that serves ``base``'s episodes differently (replayed, with gaps, ...).

    Names, prior, noises, bounds and the model (``f``, ``g``, ``truth``) are the base system's;
    any other attribute (``report_scale``, parameters) is read from it. Subclasses override how
    episodes are drawn and advanced.
    """

    #: attributes copied from the base system (the rest is looked up on it)
    COPIED = (
        "name",
        "scenario",
        "scenarios",
        "dt",
        "state_names",
        "state_units",
        "measurement_names",
        "measurement_units",
        "control_names",
        "prior",
        "process_noise",
        "measurement_noise",
        "has_model",
    )

    def __init__(self, base: StochasticSystem):
        self.base = base
        for attr in self.COPIED:
            setattr(self, attr, getattr(base, attr))

    def __getattr__(self, name):
        # only called for attributes not found normally: the base system's (report_scale, p, ...)
        if name == "base" or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.base, name)

    def f(self, x, u):
        return self.base.f(x, u)

    def g(self, x, u):
        return self.base.g(x, u)

    def f_numpy(self, x, u):
        return self.base.f_numpy(x, u)

    def g_numpy(self, x, u):
        return self.base.g_numpy(x, u)

    @property
    def has_numpy_model(self) -> bool:
        return self.base.has_numpy_model and StochasticSystem.has_numpy_model.fget(self)

    def truth(self, x):
        return self.base.truth(x)

    def scales(self):
        return self.base.scales()

    def _scale(self, name: str, field: str) -> torch.Tensor:
        value = self.__dict__.get(name)
        return value if value is not None else self.base._scale(name, field)

    def to(self, device) -> SystemWrapper:
        self.base.to(device)
        return self
