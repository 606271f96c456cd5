"""The JSON sidecar of an exported step: its inputs and outputs (names, shapes, dtypes, units) and how to carry them.

A runtime with no Python needs only this file and one of the artifacts: which tensors to feed in
what order, what comes out, what the carried state starts at and how it advances.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from daof.export.step import StreamingStep
from daof.io import atomic_write_text

__all__ = ["CONTRACT_FILE", "contract", "read_contract", "write_contract"]

CONTRACT_FILE = "contract.json"


def _tensor(name: str, width: int | str, dtype: str, meaning: str, **more) -> dict:
    return {"name": name, "shape": ["batch", width], "dtype": dtype, "meaning": meaning, **more}


def contract(step: StreamingStep, files: dict[str, str], source: dict | None = None) -> dict:
    """The sidecar of ``step`` (plain data): ``files`` maps format -> file name, ``source`` says where it came from."""
    filt, s, layout = step.filter, step.filter.system, step.layout
    n, m, c, width = s.state_dim, s.measurement_dim, s.control_dim, layout.width
    gaps = "its prediction g(f(x̂_{t−1}, u_{t−1}), u_t)" if step.predict_gaps else "its last present value"
    state = {"names": list(s.state_names), "units": list(s.state_units), "scale": s.error_scale.tolist()}
    described = {
        "measurement": _tensor(
            "measurement",
            m,
            "float32",
            f"y_t; NaN marks a missing channel, read as {gaps}",
            names=list(s.measurement_names),
            units=list(s.measurement_units),
        ),
        "control": _tensor("control", c, "float32", "u_t", names=list(s.control_names)),
        "prev_control": _tensor("prev_control", c, "float32", "u_{t−1}", names=list(s.control_names)),
        "window": _tensor("window", width, "float32", f"h_{{t−1}}, the carried window: {layout.describe()}"),
        "prev_estimate": _tensor("prev_estimate", n, "float32", "x̂_{t−1}, the last estimate", **state),
        "step": _tensor("step", 1, "int64", "t = 1, 2, …: the index of this measurement since the reset"),
    }
    inputs = [described[name] for name in step.input_names]
    outputs = [
        _tensor("estimate", n, "float32", "x̂_t", **state),
        _tensor("next_window", width, "float32", "h_t: feed back as window"),
    ]
    initial = {"window": f"zeros [batch, {width}] (any value: at step 1 the window starts afresh)", "step": 1}
    carry = {"window": "next_window", "step": "step + 1"}
    if step.closed_loop:
        initial["prev_estimate"] = s.prior.mean.float().tolist()
        carry["prev_estimate"] = "estimate"
    return {
        "filter": filt.kind,
        "class": type(filt).__name__,
        "system": s.name,
        "scenario": s.scenario,
        "window": layout.window,
        "frame": [list(field) for field in layout.fields],
        "missing_fill": "prediction" if step.predict_gaps else "hold",
        "inputs": inputs,
        "outputs": outputs,
        "initial": initial,
        "carry": carry,
        "files": files,
        "torch": torch.__version__,
        "source": source or {},
    }


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
