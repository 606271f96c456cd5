"""The JSON sidecar of an exported step: its inputs and outputs (names, shapes, dtypes, units) and how to carry them.

A runtime with no Python needs only this file and one of the artifacts: which tensors to feed in
what order, what comes out, what the carried state starts at and how it advances.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from daof.export.step import KALMANNET_STATE, KalmanNetStep
from daof.filters.learned.network import SCHEDULE_STEPS
from daof.io import atomic_write_text

__all__ = ["CONTRACT_FILE", "contract", "read_contract", "write_contract"]

CONTRACT_FILE = "contract.json"


def _tensor(name: str, width: int | str, dtype: str, meaning: str, **more) -> dict:
    return {"name": name, "shape": ["batch", width], "dtype": dtype, "meaning": meaning, **more}


def _signals(s, gaps: str) -> dict[str, dict]:
    """The step's per-step inputs y_t, u_t, u_{t−1}; ``gaps`` says how a missing channel is read."""
    m, c = s.measurement_dim, s.control_dim
    return {
        "measurement": _tensor(
            "measurement",
            m,
            "float32",
            f"y_t; NaN marks a missing channel, {gaps}",
            names=list(s.measurement_names),
            units=list(s.measurement_units),
        ),
        "control": _tensor("control", c, "float32", "u_t", names=list(s.control_names)),
        "prev_control": _tensor("prev_control", c, "float32", "u_{t−1}", names=list(s.control_names)),
    }


def _state(s) -> dict:
    return {"names": list(s.state_names), "units": list(s.state_units), "scale": s.error_scale.tolist()}


#: what the uncertainty head reads at step t (``uncertainty_features``), for the ``std`` output's description
_HEAD_FEATURES = {
    "KalmanNet": "y_t (a missing channel held), ν_t (0 where missing), x̂_t, x̂_t − x̂⁻_t, the three GRU states, ρ_t",
    "SLF": "the window h_t (next_window), x̂_t, ρ_t",
}


def _std_output(step) -> list[dict]:
    """The ``std`` output of a step with an uncertainty head (none without): its shape, units and source."""
    if step.head is None:
        return []
    s, kind = step.filter.system, step.filter.kind
    features = _HEAD_FEATURES.get(kind, "the window h_t (next_window, with x̂_{t−1}), x̂_t, ρ_t")
    source = (
        f"the filter's uncertainty head (an MLP, {step.head.in_features} features -> log σ²_t per state) on "
        f"{features}; ρ_t = max(0, 1 − (t − 1)/{SCHEDULE_STEPS}); σ_t = exp(½ log σ²_t), as Filter.run_with_std "
        "gives it"
    )
    meaning = "σ_t, the standard deviation of the error of x̂_t per state (in the state's units)"
    names = {"names": list(s.state_names), "units": list(s.state_units)}
    return [_tensor("std", s.state_dim, "float32", meaning, **names, source=source)]


def _envelope(step, files: dict[str, str], source: dict | None, **fields) -> dict:
    """The sidecar: what the filter is, ``fields`` (its step's own description), the files and their origin.

    A step with an uncertainty head adds ``std_source`` ("uncertainty head") and the head's sizes.
    """
    filt, s = step.filter, step.filter.system
    head = {"filter": filt.kind, "class": type(filt).__name__, "system": s.name, "scenario": s.scenario}
    if step.head is not None:
        fields = {**fields, "std_source": filt.std_source, "uncertainty_head": step.head.settings}
    return {**head, **fields, "files": files, "torch": torch.__version__, "source": source or {}}


def contract(step: nn.Module, files: dict[str, str], source: dict | None = None) -> dict:
    """The sidecar of ``step`` (plain data): ``files`` maps format -> file name, ``source`` says where it came from.

    ``inputs`` and ``outputs`` in order; ``arguments`` every argument of the step's ``forward`` (those
    not in ``inputs`` take None); ``initial`` the carried inputs' values before the first measurement
    (a list: a row for every batch entry; a string: zeros of the input's width) and ``carry`` which
    output feeds each of them at the next step.
    """
    if isinstance(step, KalmanNetStep):
        return _kalmannet_contract(step, files, source)
    s, layout = step.filter.system, step.layout
    n, width = s.state_dim, layout.width
    gaps = (
        "read as its prediction g(f(x̂_{t−1}, u_{t−1}), u_t)" if step.predict_gaps else "read as its last present value"
    )
    state = _state(s)
    described = {
        **_signals(s, gaps),
        "window": _tensor("window", width, "float32", f"h_{{t−1}}, the carried window: {layout.describe()}"),
        "prev_estimate": _tensor("prev_estimate", n, "float32", "x̂_{t−1}, the last estimate", **state),
        "step": _tensor("step", 1, "int64", "t = 1, 2, …: the index of this measurement since the reset"),
    }
    inputs = [described[name] for name in step.input_names]
    outputs = [
        _tensor("estimate", n, "float32", "x̂_t", **state),
        *_std_output(step),
        _tensor("next_window", width, "float32", "h_t: feed back as window"),
    ]
    initial = {"window": f"zeros [batch, {width}] (any value: at step 1 the window starts afresh)", "step": 1}
    carry = {"window": "next_window", "step": "step + 1"}
    if step.closed_loop:
        initial["prev_estimate"] = s.prior.mean.float().tolist()
        carry["prev_estimate"] = "estimate"
    return _envelope(
        step,
        files,
        source,
        window=layout.window,
        frame=[list(field) for field in layout.fields],
        missing_fill="prediction" if step.predict_gaps else "hold",
        arguments=list(step.arguments),
        inputs=inputs,
        outputs=outputs,
        initial=initial,
        carry=carry,
    )


#: what each of KalmanNet's carried tensors holds (``KalmanNetState``)
_KALMANNET_MEANING = {
    "state_estimate": "x̂_{t−1}",
    "state_prev_estimate": "x̂_{t−2}",
    "state_prev_prior": "x̂⁻_{t−1} = f(x̂_{t−2}, u_{t−2})",
    "state_prev_measurement": "y_{t−1}, each channel's last present value",
    "state_h_q": "the Q-GRU's hidden state",
    "state_h_sigma": "the Σ-GRU's hidden state",
    "state_h_s": "the S-GRU's hidden state",
}


def _kalmannet_contract(step: KalmanNetStep, files: dict[str, str], source: dict | None) -> dict:
    s = step.filter.system
    start = step.initial_state(1)
    gaps = "adds nothing to the update (no channel present: the step only predicts)"
    carried = {
        name: _tensor(name, start[name].shape[-1], "float32", _KALMANNET_MEANING[name]) for name in KALMANNET_STATE
    }
    step_input = _tensor("step", 1, "int64", "t = 1, 2, …: the index of this measurement since the reset (σ's ρ_t)")
    described = {**_signals(s, gaps), **carried, "step": step_input}
    outputs = [_tensor("estimate", s.state_dim, "float32", "x̂_t", **_state(s)), *_std_output(step)]
    outputs += [{**carried[name], "name": f"next_{name}", "meaning": f"feed back as {name}"} for name in carried]
    initial = {name: start[name][0].tolist() for name in carried}
    carry = {name: f"next_{name}" for name in carried}
    if "step" in step.arguments:  # with a head
        initial["step"], carry["step"] = 1, "step + 1"
    return _envelope(
        step,
        files,
        source,
        missing_fill="prediction",
        arguments=list(step.arguments),
        inputs=[described[name] for name in step.input_names],
        outputs=outputs,
        initial=initial,
        carry=carry,
    )


def write_contract(info: dict, out: str | Path) -> Path:
    """Write the sidecar into directory ``out`` (atomically)."""
    path = Path(out) / CONTRACT_FILE
    atomic_write_text(path, json.dumps(info, indent=2, ensure_ascii=False) + "\n")
    return path


def read_contract(out: str | Path) -> dict:
    """The sidecar in directory ``out`` (``FileNotFoundError`` / ``ValueError`` as one line)."""
    path = Path(out) / CONTRACT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no {CONTRACT_FILE} in {out}: not an exported filter directory")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error})") from None
