"""``StreamingStep``: one step of a learned filter as a pure function of tensors, for export.

(y_t, u_t, u_{t−1}, h_{t−1}, x̂_{t−1}, t) -> (x̂_t, [σ_t,] h_t): the caller carries the window h and, for
the closed-loop filters, the estimate; nothing else is remembered between steps. The step reuses
the filter's own deterministic path (``_inference_layers``, ``_fast_estimate``) and does what its
``stream_steps`` loop does around it: a missing (NaN) channel reads as its last present value
(the newest frame of h_{t−1}; the channel's training mean at t = 1), or for DAOF-v1 with
``missing_fill="prediction"`` as its predicted measurement; at t = 1 the window is the first frame
behind N − 1 copies of it. DAOF-v1's model f, g and its per-step tables (K̄_t, b_t, √diag S_t) are
constants of the step, indexed by t. A filter with an uncertainty head (``filt.uncertainty``) also
outputs σ_t, its error std per state, from the head on the same features ``run_with_std`` gives it.
"""

from __future__ import annotations

import torch
from torch import nn

from daof.envs.gaps import MISSING_KEY
from daof.filters.learned.kalmannet import STATE_KEYS, KalmanNetState
from daof.filters.learned.network import startup_feature

__all__ = ["KalmanNetStep", "StreamingStep", "streaming_step"]


def streaming_step(filt) -> nn.Module:
    """The exportable step of a learned filter: ``KalmanNetStep`` for KalmanNet, else ``StreamingStep``."""
    return KalmanNetStep(filt) if filt.kind == "KalmanNet" else StreamingStep(filt)


class _FilterStep(nn.Module):
    """What every exported step shares: the filter frozen in eval mode (its uncertainty head too, if it has
    one), which arguments it takes and what it outputs."""

    #: every argument of ``forward``, in order (subclasses)
    arguments: tuple[str, ...] = ()
    #: the outputs that feed the carried inputs, after the estimate (and σ)
    carried_outputs: tuple[str, ...] = ()
    closed_loop = True

    def __init__(self, filt):
        super().__init__()
        self.filter = filt.eval()
        for p in self.filter.parameters():
            p.requires_grad_(False)
        self.has_controls = filt.system.control_dim > 0
        #: the uncertainty head σ_t comes from, or None (no ``std`` output)
        self.head = None if filt.uncertainty is None else filt.uncertainty.eval().requires_grad_(False)

    @property
    def output_names(self) -> list[str]:
        """The outputs in order: ``estimate``, ``std`` when the filter has a head, then the carried state."""
        return ["estimate", *(["std"] if self.head is not None else []), *self.carried_outputs]

    def _std(self, features: list[torch.Tensor], step) -> torch.Tensor:
        """σ_t per state, exp(½ log σ²_t) of the head on ``features`` and ρ_t (as ``run_with_std``)."""
        if step is None:
            raise ValueError(f"{self.filter.name}'s step has an uncertainty head: it needs the step index t for ρ_t")
        rho = startup_feature(step).to(features[0].dtype)
        return self.head.std(torch.cat([*features, rho], -1))

    @property
    def input_names(self) -> list[str]:
        """The arguments this filter's step takes (not None), in order."""
        unused = ({"control", "prev_control"} if not self.has_controls else set()) | (
            {"prev_estimate"} if not self.closed_loop else set()
        )
        return [name for name in self.arguments if name not in unused]


class StreamingStep(_FilterStep):
    """The streaming step of ``filt`` (a ``LearnedFilter``); ``input_names`` lists its arguments in order."""

    def __init__(self, filt):
        super().__init__(filt)
        s, layout = filt.system, filt.layout
        self.layout = layout
        self.measured = layout.without("prev_estimate")
        self.closed_loop = layout.closed_loop
        self.predict_gaps = getattr(filt, "missing_fill", "hold") == "prediction"
        with torch.no_grad():
            layers = filt._inference_layers()
        # the folded layers as buffers (None entries stay None): constants of the exported program
        self._shape = []
        for i, layer in enumerate(layers):
            entry = []
            for j, item in enumerate(layer):
                if isinstance(item, tuple):  # the output squash (mid, half)
                    names = [self._keep(f"layer{i}_{j}_{k}", t) for k, t in enumerate(item)]
                    entry.append(tuple(names))
                else:
                    entry.append(None if item is None else self._keep(f"layer{i}_{j}", item))
            self._shape.append(entry)
        self.register_buffer("y_fill", filt.policy.input_loc[layout.offset("measurement")].detach().clone())
        if self.has_controls or self.predict_gaps:  # build the model's constant caches outside tracing
            with torch.no_grad():
                x = s.prior.mean.float().unsqueeze(0)
                u = torch.zeros(1, s.control_dim)
                if s.has_model:
                    s.g(s.f(x, u), u)

    def _keep(self, name: str, tensor: torch.Tensor) -> str:
        self.register_buffer(name, tensor.detach().clone())
        return name

    carried_outputs = ("next_window",)

    def _layers(self) -> list[tuple]:
        def get(item):
            if item is None:
                return None
            if isinstance(item, tuple):
                return tuple(getattr(self, name) for name in item)
            return getattr(self, item)

        return [tuple(get(item) for item in entry) for entry in self._shape]

    #: every argument of ``forward``, in order; a filter without controls or feedback takes None for those
    arguments = ("measurement", "control", "prev_control", "window", "prev_estimate", "step")

    def forward(self, measurement, control, prev_control, window, prev_estimate, step):
        """(x̂_t, h_t) of one step, (x̂_t, σ_t, h_t) with a head; control and prev_control are None without
        controls, prev_estimate for the SLF. σ_t reads h_t, x̂_t and ρ_t (``uncertainty_features``)."""
        filt, layout, prev = self.filter, self.layout, prev_estimate
        u = measurement[..., :0] if control is None else control  # f and g take empty controls
        u_prev = measurement[..., :0] if prev_control is None else prev_control
        first = step == 1  # [B, 1]: the window starts afresh
        missing = torch.isnan(measurement)
        if self.predict_gaps:
            held = filt.system.g(filt.predict(prev, u_prev), u)
        else:
            held = torch.where(first, self.y_fill, layout.field(window, "measurement"))
        values = {"measurement": torch.where(missing, held, measurement), "control": u, "prev_control": u_prev}
        if self.measured.missing_flags:
            values[MISSING_KEY] = missing.to(measurement.dtype)
        frame = filt._frame(prev, self.measured.frame(values))
        window = torch.where(first, layout.first_window(frame), layout.slide(window, frame))
        estimate = filt._fast_estimate(self._layers(), window, prev, u_prev, step)
        if self.head is None:
            return estimate, window
        return estimate, self._std([window, estimate], step), window

    def initial_state(self, batch: int = 1) -> dict[str, torch.Tensor]:
        """The carried inputs before the first measurement: h_0 (any value; zeros), x̂_0 (the prior mean), t = 1."""
        state = {"window": torch.zeros(batch, self.layout.width)}
        if self.closed_loop:
            state["prev_estimate"] = self.filter.system.prior.mean.float().expand(batch, -1).clone()
        state["step"] = torch.ones(batch, 1, dtype=torch.int64)
        return state


#: KalmanNet's carried state as inputs of its step, and the step's outputs
KALMANNET_STATE = tuple(f"state_{k}" for k in STATE_KEYS)


class KalmanNetStep(_FilterStep):
    """KalmanNet's step for export: (y_t, u_t, u_{t−1}, its recurrent state) -> (x̂_t, the next state).

    The filter's own ``step`` (the model's f and g, the gain network, the gaps' rule), with the
    state as seven tensors the caller carries: x̂_{t−1}, x̂_{t−2}, x̂⁻_{t−1}, y_{t−1} and the three
    GRUs' hidden states (``KalmanNetState``). With an uncertainty head it also takes ``step`` (t, for
    the head's ρ_t) and outputs σ_t after x̂_t.
    """

    arguments = ("measurement", "control", "prev_control", *KALMANNET_STATE)
    carried_outputs = tuple(f"next_{k}" for k in KALMANNET_STATE)

    def __init__(self, filt):
        super().__init__(filt)
        if self.head is not None:
            self.arguments = (*type(self).arguments, "step")
        with torch.no_grad():  # build the model's constant caches outside tracing
            self.filter.initial_state(1)

    def forward(
        self,
        measurement,
        control,
        prev_control,
        state_estimate,
        state_prev_estimate,
        state_prev_prior,
        state_prev_measurement,
        state_h_q,
        state_h_sigma,
        state_h_s,
        step=None,
    ):
        """(x̂_t, [σ_t,] the next state's seven tensors) of one step; control and prev_control are None without
        controls, step without a head. The arguments are named as the exported program's inputs
        (``KALMANNET_STATE``). σ_t reads what ``KalmanNet.uncertainty_features`` gives the head."""
        u = measurement[..., :0] if control is None else control
        u_prev = measurement[..., :0] if prev_control is None else prev_control
        state = KalmanNetState(
            state_estimate,
            state_prev_estimate,
            state_prev_prior,
            state_prev_measurement,
            state_h_q,
            state_h_sigma,
            state_h_s,
        )
        estimate, new = self.filter.step(state, measurement, u_prev, u)
        # x̂_{t−1} passes through as the next x̂_{t−2}: a copy, as ONNX renames an input that is also an output
        carried = new._replace(prev_estimate=new.prev_estimate.clone())
        if self.head is None:
            return (estimate, *carried)
        std = self._std([self.filter.step_features(measurement, u, estimate, new)], step)
        return (estimate, std, *carried)

    def initial_state(self, batch: int = 1) -> dict[str, torch.Tensor]:
        """The state before the first measurement (``KalmanNet.initial_state``); with a head, t = 1."""
        with torch.no_grad():
            state = self.filter.initial_state(batch)
        state = {name: value.contiguous() for name, value in zip(KALMANNET_STATE, state)}
        if self.head is not None:
            state["step"] = torch.ones(batch, 1, dtype=torch.int64)
        return state
