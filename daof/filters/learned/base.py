"""What every learned filter shares: the network, its normaliser, the window, ``run`` and the checkpoint.

``LearnedFilter`` is a ``Filter`` (``run(data)``) and an ``nn.Module`` holding a ``PolicyNet``
(window normaliser -> MLP -> (loc, log σ)). Its deterministic estimate is the squashed loc: by
default the estimate itself, squashed onto the plausible state range. ``UpdateFilter`` is the base
of the filters whose action is a bounded update b_t ⊙ a of a prediction instead (DAOF-v1). The
filters themselves (``daof_v1``, ``daof_v2``, ``slf``) say what differs:
the prediction, the bound, the window's layout, the extra inputs.

Each filter's window is described by its ``layout`` (a ``daof.envs.history.FrameLayout``): the env
builds the same window with ``make_env(..., layout=filter.layout)``, ``run`` builds it from
simulated data step by step exactly as the env does, and ``check_env`` refuses an env whose window
is another. ``filter_module()`` is what a user runs in an env; DSAC-T's training views of the
network are in ``daof.train.policies``.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from daof.envs.gaps import MISSING_KEY
from daof.envs.history import HISTORY_KEY, FrameLayout
from daof.envs.registry import make_system
from daof.envs.system import StochasticSystem
from daof.filters.base import Filter
from daof.filters.learned.config import MISSING_FILLS
from daof.filters.learned.network import SCHEDULE_STEPS, PolicyNet, hold_last_value, schedule_row, startup_feature
from daof.filters.learned.uncertainty import UncertaintyHead
from daof.io import atomic_save

if TYPE_CHECKING:
    from daof.filters.learned.config import FilterConfig

__all__ = ["KINDS", "LearnedFilter", "UpdateFilter", "filter_class", "plain_data", "register"]

#: filter kind -> its class (``register``)
KINDS: dict[str, type[LearnedFilter]] = {}

#: an estimate within this fraction of the output range's width of one of its ends sits at a bound
#: (a clamp gives the end exactly; tanh is within 1e-6 of ±1 from |loc| ≈ 7.3 on)
SATURATION_TOLERANCE = 1e-6


def register(cls: type[LearnedFilter]) -> type[LearnedFilter]:
    """Class decorator: ``cls`` is the filter of ``cls.kind``."""
    KINDS[cls.kind] = cls
    return cls


def filter_class(config: FilterConfig) -> type[LearnedFilter]:
    """The class a config makes (``ValueError`` for an unknown kind)."""
    if config.kind not in KINDS:
        raise ValueError(f"unknown filter kind {config.kind!r}; valid: {sorted(KINDS)}")
    return KINDS[config.kind]


def plain_data(value, where: str = "extra"):
    """``value`` as tensors and plain Python data only (what ``torch.load(weights_only=True)`` reads back).

    Numbers and strings of other types (numpy scalars, enums) become int/float/bool/str; anything
    else is a ``ValueError`` naming where it sits.
    """
    if value is None or type(value) in (bool, int, float, str) or isinstance(value, torch.Tensor):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    if isinstance(value, str):
        return str(value)
    if isinstance(value, Mapping):
        return {plain_data(k, where): plain_data(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        items = [plain_data(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    if hasattr(value, "item") and getattr(value, "shape", None) == ():  # a numpy scalar (np.bool_ too)
        return plain_data(value.item(), where)
    raise ValueError(f"a filter checkpoint holds tensors and plain data only; {where} is a {type(value).__name__}")


class LearnedFilter(nn.Module, Filter):
    """A learned filter on one system with one window length; the base of ``DAOFv1``, ``DAOFv2`` and ``SLF``.

    ``LearnedFilter(config, system)`` builds the class of ``config`` (``filter_class``), so code
    written before the classes were split keeps working; ``make_filter`` is the same.
    """

    #: the kind a subclass implements ("DAOF-v1", "DAOF-v2", "SLF")
    kind: str = ""
    #: frames carry the fed-back estimate x̂_{t−1} (all but the SLF)
    closed_loop: bool = True
    #: the action is a bounded update of a prediction (``UpdateFilter``), not the estimate itself
    acts_by_update: bool = False
    #: the actor's output key: the estimate itself
    action_key: str = "action"
    #: the values ``missing_fill`` may take, the first is the default
    missing_fills: tuple[str, ...] = ("hold",)
    #: the policy reads the scaled innovation ν_t (DAOF-v1)
    innovation_input: bool = False

    def __new__(cls, config: FilterConfig | None = None, system: StochasticSystem | None = None):
        if config is None:  # copies and unpickling: the class is already the right one
            return super().__new__(cls)
        target = filter_class(config)
        if not issubclass(target, cls):
            raise ValueError(f"a {config.kind} config makes a {target.__name__}, not a {cls.__name__}")
        return super().__new__(target)

    #: whether ``FilterConfig.reference_gain`` means anything to this kind (DAOF-v1's reference update)
    takes_reference_gain = False

    @classmethod
    def check_config(cls, config: FilterConfig) -> None:
        """Refuse the options this class cannot honour (``FilterConfig`` calls it on construction)."""
        if not config.reference_gain and not cls.takes_reference_gain:
            raise ValueError(f"reference_gain=False is DAOF-v1's paper form; a {config.kind} has no reference update")

    def __init__(self, config: FilterConfig, system: StochasticSystem | None = None):
        self._bind(config, system)
        s = self.system
        #: the window this filter reads: an env must build the same (``check_env``)
        self.layout = FrameLayout.for_system(
            s,
            config.window,
            closed_loop=self.closed_loop,
            include_controls=config.include_controls,
            missing_flags=config.missing_mask,
        )
        self.uses_controls = self.layout.uses_controls
        self.startup_input = config.startup_input and self.closed_loop
        # the network first: its weights draw from the global RNG
        self.policy = PolicyNet(
            self.layout.width,
            s.state_dim,
            config.num_cells,
            config.depth,
            self.startup_input,
            self._innovation_feature(),
            s.measurement_dim,
            config.gelu_approximate,
        )
        self._register_action_buffers()
        low, high = self._action_bounds()
        self.register_buffer("low", low.float())
        self.register_buffer("high", high.float())
        self._register_state_range()
        self.missing_fill = self.missing_fills[0]

    def _bind(self, config: FilterConfig, system: StochasticSystem | None) -> None:
        """What every learned filter starts with: the module, its system (checked), its config."""
        nn.Module.__init__(self)
        Filter.__init__(self, system or make_system(config.system, config.scenario))
        self.config = config
        self.name = config.kind
        self._check_system()

    def _register_state_range(self) -> None:
        """The system's scales, kept with the weights: every estimate stays in its output range (the
        env's action spec) and ``error_scale`` sized the training (``daof.envs.scales``)."""
        self.register_buffer("state_low", self.system.state_low.clone().float())
        self.register_buffer("state_high", self.system.state_high.clone().float())
        self.register_buffer("error_scale", self.system.error_scale.clone().float())

    # ----------------------------------------------------------------- subclass hooks
    def _check_system(self) -> None:
        """Refuse a system this filter cannot run on."""

    def _innovation_feature(self):
        """The function of the window the policy also reads (ν_t), or None."""
        return None

    def _register_action_buffers(self) -> None:
        """Buffers of the action's scale (registered right after the network, before the bounds)."""

    def _action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The actor's action range: here the plausible state range (the action is the estimate)."""
        return self.system.state_low.clone(), self.system.state_high.clone()

    def _output_affine(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(mid, half) the deterministic action maps tanh(loc) with, or None for tanh(loc) itself."""
        return self.squash_affine()

    def _gap_fill(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """A function (t, x̂_{t−1}, frame part) -> frame part that rewrites missing channels, or None (hold)."""
        return None

    def _frame(self, prev_estimate: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
        """A frame from the fed-back estimate and the rest of the frame (the layout puts x̂_{t−1} first)."""
        return torch.cat([prev_estimate, measured], -1)

    # ----------------------------------------------------------------- missing measurements
    @property
    def missing_fill(self) -> str:
        """What a missing (NaN) measurement channel reads as (docs/missing_data.md).

        "hold": its last present value (``hold_last_value``); "prediction" (DAOF-v1 only): the
        predicted measurement g(f(x̂_{t−1}, u_{t−1}), u_t), so the channel's innovation is 0, as a
        Kalman filter skips the update of a missing channel.
        """
        return self._missing_fill

    @missing_fill.setter
    def missing_fill(self, value: str) -> None:
        if value not in MISSING_FILLS:
            raise ValueError(f"missing_fill must be one of {MISSING_FILLS}, got {value!r}")
        if value not in self.missing_fills:
            able = "/".join(kind for kind, cls in KINDS.items() if value in cls.missing_fills)
            raise ValueError(f"missing_fill={value!r} needs a model predictor: {able} only, not {self.config.kind}")
        self._missing_fill = value

    # ----------------------------------------------------------------- shapes
    @property
    def frame_dim(self) -> int:
        return self.layout.frame_dim

    @property
    def input_key(self) -> str:
        """The env key of the window."""
        return HISTORY_KEY

    @property
    def policy_in_keys(self) -> list[str]:
        """What the policy network reads: the window, and t where it uses the start-up feature."""
        return [HISTORY_KEY, "step"] if self.startup_input else [HISTORY_KEY]

    @property
    def module_in_keys(self) -> list[str] | dict[str, str]:
        """What ``filter_module`` reads (``estimate``'s argument -> env key)."""
        return dict(zip(["window", "step"], self.policy_in_keys))

    @property
    def action_scale(self) -> torch.Tensor:
        """What one unit of the actor's action is in state units, once the filter has settled.

        The estimate itself here (DAOF-v2, SLF); an update filter's is its settled bound. DSAC-T's
        entropy target uses it.
        """
        return torch.ones_like(self.low)

    # ----------------------------------------------------------------- normalisation
    @torch.no_grad()
    def fit_normalizer(self, runs: int = 64, steps: int = 500, seed: int = 7_000_001) -> None:
        """Per-channel input loc/scale from simulated training data (stored in the checkpoint)."""
        data = self.system.simulate(runs, steps, seed, device=self.low.device)
        source = {"prev_estimate": "state"}  # the fed-back estimate is normalised like the state
        parts = [data[source.get(key, key)] for key in self.layout.keys if key != MISSING_KEY]
        flat = torch.cat(parts, -1).flatten(0, 1)
        loc, scale = flat.mean(0), flat.std(0).clamp_min(1e-6)
        if self.layout.missing_flags:  # the 0/1 missing flags enter as they are
            m = self.layout.widths[MISSING_KEY]
            loc, scale = torch.cat([loc, loc.new_zeros(m)]), torch.cat([scale, scale.new_ones(m)])
        self.policy.input_loc.copy_(loc.repeat(self.config.window))
        self.policy.input_scale.copy_(scale.repeat(self.config.window))

    @torch.no_grad()
    def set_schedules(self, schedule: dict[str, torch.Tensor]) -> None:
        """Per-step tables from a Kalman-type filter's ``covariance_schedule`` (DAOF-v1's; a no-op here)."""

    # ----------------------------------------------------------------- the deterministic filter
    def estimate(self, window, prev_estimate=None, prev_control=None, step=None) -> torch.Tensor:
        """Deterministic estimate x̂_t (the squashed loc; an update filter scales it by b_t and adds its prediction)."""
        return self._fast_estimate(self._inference_layers(), window, prev_estimate, prev_control, step)

    forward = estimate

    def squash_affine(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mid, half) of the actor's bounds: a = mid + half · tanh(u)."""
        return (self.high + self.low) / 2, (self.high - self.low) / 2

    def squash(self, loc: torch.Tensor) -> torch.Tensor:
        """The deterministic action of a pre-squash loc: mid + half · tanh(loc) on the actor's bounds."""
        return torch.addcmul(*self.squash_affine(), torch.tanh(loc))

    def filter_module(self, env=None) -> TensorDictModule:
        """The deterministic filter as a TensorDictModule: reads ``module_in_keys``, writes ``action``.

        With ``env``, first checks that the env's window is this filter's (``check_env``).
        """
        if env is not None:
            self.check_env(env)
        return TensorDictModule(self, in_keys=self.module_in_keys, out_keys=["action"])

    def check_env(self, env) -> None:
        """Refuse, with one line, an env whose window is not this filter's (N, fields, controls, flags)."""
        theirs = FrameLayout.of_env(env)
        if theirs != self.layout:
            raise ValueError(
                f"{self.name} reads windows of {self.layout.describe()}, the env builds {theirs.describe()}: "
                "build it with make_env(..., layout=filter.layout)"
            )

    # ----------------------------------------------------------------- offline filtering
    def _record(self, estimates: torch.Tensor) -> None:
        """``Filter``'s stats, then ``stats["saturated"]``, the share per state at a bound (``saturation``)."""
        super()._record(estimates)
        self.stats["saturated"] = self.saturation(estimates).tolist()

    def saturation(self, estimates: torch.Tensor) -> torch.Tensor:
        """Per state [n], the share of ``estimates [..., n]`` at an end of the output range (the plausible state range).

        An update filter clamps its estimate there, the others squash onto it; within
        ``SATURATION_TOLERANCE`` of the range's width counts as at the end.
        """
        low, high = self.state_low.to(estimates), self.state_high.to(estimates)
        tolerance = SATURATION_TOLERANCE * (high - low)
        at_bound = (estimates <= low + tolerance) | (estimates >= high - tolerance)
        return at_bound.reshape(-1, estimates.shape[-1]).double().mean(0)

    def validate(self, data) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``Filter.validate``, then cast to the network's dtype (float32): float64 data is accepted.

        Estimates come back in the network's dtype, as the classical filters return their ``dtype``
        whatever the data's. A finite value too large for that dtype is refused in one line.
        """
        checked = super().validate(data)
        dtype = self.state_low.dtype
        cast = tuple(v.to(dtype) for v in checked)
        for key, before, after in zip(("measurement", "prev_control", "control"), checked, cast):
            overflow = torch.isfinite(before) & ~torch.isfinite(after)
            if before.dtype != dtype and overflow.any():
                where = overflow.nonzero()[0].tolist()
                raise ValueError(
                    f"{self.name}: {key!r} at [run, step, channel] = {where} is {before[tuple(where)].item():g}, "
                    f"beyond the {dtype} range of the network"
                )
        return cast

    def open_loop_frames(self, y, u, u_prev) -> torch.Tensor:
        """Per-step frames without the fed-back estimate: [y_t, (u_t, u_{t−1}), (missing flags)].

        A missing measurement (NaN) holds the channel's last value; before the first value of a
        channel it is the channel's training mean (see ``hold_last_value``). With ``missing_mask``
        the frame ends with the channels' missing flags: [y_t, (u_t, u_{t−1}), 1{y_t missing}].
        """
        measured = self.layout.without("prev_estimate")
        y_mean = self.policy.input_loc[self.layout.offset("measurement")]
        values = {"measurement": hold_last_value(y, y_mean), "control": u, "prev_control": u_prev}
        if measured.missing_flags:
            values[MISSING_KEY] = torch.isnan(y).to(values["measurement"].dtype)
        return measured.frame(values)

    def _inference_layers(self) -> list[tuple[torch.Tensor, ...]]:
        """The policy's (weight, bias) per layer, for the deterministic filter only.

        The input normalisation is folded into the first layer and only the loc rows of the last
        are kept (with the squash onto the action bounds, ``_output_affine``), so one filter
        step costs four ``linear`` calls and three GELUs. The first entry
        also holds the weight columns of ν_t and of ρ_t (each None where unused); they enter as a
        per-step bias. Rebuilt on every ``run`` (cheap), so it always
        matches the current weights.
        """
        policy = self.policy
        linears = [m for m in policy.mlp if isinstance(m, nn.Linear)]
        first, last, n = linears[0], linears[-1], self.system.state_dim
        width, m = policy.input_loc.numel(), policy.innovation_dim
        w0 = first.weight[:, :width] / policy.input_scale
        w_nu = first.weight[:, width : width + m] if m else None
        w_rho = first.weight[:, width + m] if self.startup_input else None
        layers = [(w0, first.bias - w0 @ policy.input_loc, w_nu, w_rho)]
        layers += [(m.weight, m.bias) for m in linears[1:-1]]
        return layers + [(last.weight[:n], last.bias[:n], self._output_affine())]

    def _network(self, layers, window, step=None, nu=None) -> torch.Tensor:
        """The squashed loc of the policy on pre-folded layers: mid + half · tanh(loc) (tanh(loc) for updates)."""
        (w0, b0, w_nu, w_rho), *hidden = layers[:-1]
        # ν_t and ρ_t times their weight columns are a per-step bias of the first layer
        if w_nu is not None:
            b0 = b0 + (nu / schedule_row(self.policy.innovation_scale, step)) @ w_nu.T
        rho = startup_feature(step) if w_rho is not None and step is not None else 0.0
        if not isinstance(rho, float) or rho > 0.0:  # a settled streaming step skips it (+0 is exact)
            b0 = b0 + rho * w_rho
        gelu = self.policy.gelu_approximate
        h = nn.functional.gelu(nn.functional.linear(window, w0, b0), approximate=gelu)
        for weight, bias in hidden:
            h = nn.functional.gelu(nn.functional.linear(h, weight, bias), approximate=gelu)
        weight, bias, squash = layers[-1]
        out = torch.tanh(nn.functional.linear(h, weight, bias))  # tanh of the pre-squash loc
        if squash is not None:
            out = torch.addcmul(squash[0], squash[1], out)
        return out

    def _fast_estimate(self, layers, window, prev_estimate=None, prev_control=None, step=None) -> torch.Tensor:
        """``estimate`` on pre-folded layers (``_stream`` folds them once per trajectory)."""
        return self._network(layers, window, step)

    @torch.inference_mode()
    def _run(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Filter [runs, steps] data -> [runs, steps, n] (``Filter.run`` validates the input).

        Closed loop: step by step, the window built exactly as the env's CatTensors + CatFrames do
        (the first frame behind the layout's padding after the reset), so ``run`` and an env
        rollout give the same estimates.
        """
        return self._stream(y, u_prev, u)

    def _stream(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Step-by-step filtering (closed loop; for the SLF the streaming form of its windows)."""
        out = [estimate for _, _, estimate in self.stream_steps(y, u_prev, u)]
        return torch.stack(out, 1) if out else torch.empty(y.shape[0], 0, self.system.state_dim, device=y.device)

    def stream_steps(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """Yield (h_t, x̂_{t−1}, x̂_t) for t = 1..T of step-by-step filtering of validated [runs, steps] data."""
        layers = self._inference_layers()
        measured = self.open_loop_frames(y, u, u_prev)  # [runs, steps, F − n]: y_t first
        fill = self._gap_fill(y, u_prev, u)
        prev = self.system.prior.mean.to(y.device).expand(y.shape[0], -1).clone()
        layout = self.layout
        window = None
        for t in self._steps(*y.shape[:2]):
            present = measured[:, t] if fill is None else fill(t, prev, measured[:, t])
            frame = self._frame(prev, present)
            # slide the window by one frame; right after the reset it is frame 1 behind N − 1 pads
            window = layout.first_window(frame) if window is None else layout.slide(window, frame)
            estimate = self._fast_estimate(layers, window, prev, u_prev[:, t], t + 1)
            yield window, prev, estimate
            prev = estimate

    def run_streaming(self, data) -> torch.Tensor:
        """``run`` one step at a time, as a deployed filter would (the SLF's cost is timed this way)."""
        y, u_prev, u = self.validate(data)
        with torch.inference_mode():
            return self._stream(y, u_prev, u)

    # ----------------------------------------------------------------- uncertainty
    @property
    def uncertainty(self) -> UncertaintyHead | None:
        """The uncertainty head ``run_with_std`` reads σ from (``daof.filters.learned.uncertainty``), or None.

        Kept out of the filter's modules: ``state_dict``, ``save`` and the export are the filter alone.
        """
        return self.__dict__.get("_uncertainty")

    def attach_uncertainty(self, head: UncertaintyHead | None) -> None:
        """Give the filter a fitted head (None removes it); refused if it does not fit the filter's features."""
        if head is not None and (head.state_dim != self.system.state_dim or head.in_features != self.feature_width):
            raise ValueError(
                f"{self.name}: the head maps {head.in_features} features to {head.state_dim} states; this filter has "
                f"{self.feature_width} features and {self.system.state_dim} states"
            )
        self.__dict__["_uncertainty"] = head

    @property
    def std_source(self) -> str | None:
        return "uncertainty head" if self.uncertainty is not None else None

    @property
    def feature_width(self) -> int:
        """Width of ``uncertainty_features``: the window, the estimate and ρ_t."""
        return self.layout.width + self.system.state_dim + 1

    def uncertainty_features(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        """(estimates, features) [runs, steps, n] and [runs, steps, ``feature_width``] of validated data.

        The features of step t are what the filter read and made: the window h_t, x̂_t and ρ_t. The
        estimates are ``run``'s. No gradient is taken (the filter is frozen).
        """
        estimates, windows = [], []
        for window, _, estimate in self.stream_steps(y, u_prev, u):
            estimates.append(estimate)
            windows.append(window)
        estimates = torch.stack(estimates, 1)
        return estimates, torch.cat([torch.stack(windows, 1), estimates, self._startup_column(y)], -1)

    @staticmethod
    def _startup_column(y: torch.Tensor) -> torch.Tensor:
        """ρ_t for t = 1..T as [runs, steps, 1]."""
        steps = torch.arange(1, y.shape[1] + 1, device=y.device).unsqueeze(-1)
        return startup_feature(steps).to(y.dtype).expand(y.shape[0], -1, -1)

    @torch.inference_mode()
    def _run_with_std(self, y: torch.Tensor, u_prev: torch.Tensor, u: torch.Tensor):
        head = self.uncertainty.to(y.device)
        estimates, features = self.uncertainty_features(y, u_prev, u)
        return estimates, head.std(features)

    # ----------------------------------------------------------------- checkpoint
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """One file of tensors and plain data: config, weights and normalisation (plus ``extra`` metadata).

        Written atomically (``daof.io.atomic_save``): a failed write leaves the old file and no
        temporary one. ``load_filter`` reads it back with ``torch.load(weights_only=True)``.
        """
        blob = {"config": asdict(self.config), "state_dict": self.state_dict(), "extra": plain_data(extra or {})}
        atomic_save(blob, path)


class UpdateFilter(LearnedFilter):
    """A filter whose action a ∈ [−1, 1]ⁿ is an update: x̂_t = p_t (+ K̄_t ν_t) + b_t ⊙ a, kept in the state range.

    p_t is ``predict(x̂_{t−1}, u_{t−1})``; b_t the per-step bound ``correction_scale`` (its
    initial value from ``_initial_bound``, then fitted: DAOF-v1's by ``set_schedules``). The
    deterministic filter also reads x̂_{t−1}, u_{t−1} and t. DAOF-v1 is the only one since DAOF-v2's
    increment form was removed (docs/log/2026-12-07-daof-v2-increment-form-removed.md).
    """

    acts_by_update = True
    action_key = "correction"

    def predict(self, prev_estimate: torch.Tensor, prev_control: torch.Tensor) -> torch.Tensor:
        """The prediction p_t the update is added to."""
        raise NotImplementedError

    def _initial_bound(self) -> torch.Tensor:
        """b before it is fitted, per state (the buffer needs a value when it is registered)."""
        raise NotImplementedError

    def _innovation_for(self, window: torch.Tensor, prediction: torch.Tensor) -> torch.Tensor | None:
        """ν_t where the network or the reference update reads it, else None."""
        return None

    def reference_update(self, window: torch.Tensor, prediction: torch.Tensor, step, nu=None) -> torch.Tensor | None:
        """A reference update added before the learned one (DAOF-v1's K̄_t ν_t), or None."""
        return None

    def _register_action_buffers(self) -> None:
        # the action is the update in units of its bound b_t (one row per start-up step)
        n = self.system.state_dim
        self.register_buffer("correction_scale", self._initial_bound().float().expand(SCHEDULE_STEPS, n).clone())

    def _action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        n = self.system.state_dim
        return -torch.ones(n), torch.ones(n)

    def _output_affine(self) -> None:
        return None  # the bounds are ±1: a = tanh(u)

    @property
    def action_scale(self) -> torch.Tensor:
        """One unit of the action is the settled bound b (the schedule's last entry)."""
        return self.correction_scale[-1]

    @property
    def module_in_keys(self) -> list[str]:
        return [HISTORY_KEY, "prev_estimate", "prev_control", "step"]

    def bound_at(self, step) -> torch.Tensor:
        """The bound b_t for ``step`` t ≥ 1 (an int, a [..., 1] integer tensor, or None: settled)."""
        return schedule_row(self.correction_scale, step)

    def update_estimate(self, correction, prev_estimate, prev_control, step, window=None, prediction=None, nu=None):
        """x̂_t = p_t (+ K̄_t ν_t) + b_t ⊙ correction, kept in the plausible state range.

        Without the clamp an untrained update can push the predictor outside the region where
        the vehicle model is stable, and the estimate then runs away for the rest of the episode.
        ``window`` (h_t) or ``nu`` (ν_t) is needed with a reference update only.
        """
        if prediction is None:
            prediction = self.predict(prev_estimate, prev_control)
        estimate = torch.addcmul(prediction, self.bound_at(step), correction)
        reference = self.reference_update(window, prediction, step, nu)
        if reference is not None:
            estimate = estimate + reference
        return torch.clamp(estimate, self.state_low, self.state_high)

    _add_prediction = update_estimate  # the name before the split (daof.train.baseline)

    def _fast_estimate(self, layers, window, prev_estimate=None, prev_control=None, step=None) -> torch.Tensor:
        prediction = self.predict(prev_estimate, prev_control)
        nu = self._innovation_for(window, prediction)
        out = self._network(layers, window, step, nu)
        return self.update_estimate(out, prev_estimate, prev_control, step, window, prediction, nu)
