"""Run an exported step: load an artifact as a callable, and stream a trajectory through it.

``load_step(directory, fmt)`` gives ``step(inputs) -> (estimate, next_window)`` for inputs a dict
of tensors by the contract's input names, whichever the format: the ``torch.export`` program
(``torch.export.load``), the AOTInductor package (``aoti_load_package``) or the ONNX model
(onnxruntime, one thread). ``stream`` carries the state as the contract says.
"""

from __future__ import annotations

from pathlib import Path

import torch

from daof.export.artifacts import FORMATS
from daof.export.contract import read_contract
from daof.export.step import StreamingStep

__all__ = ["load_step", "stream"]


def load_step(directory: str | Path, fmt: str, threads: int = 1):
    """The step stored in ``directory`` as format ``fmt``, a callable on a dict of input tensors."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; valid: {sorted(FORMATS)}")
    info = read_contract(directory)
    path = Path(directory) / FORMATS[fmt]
    if not path.is_file():
        raise FileNotFoundError(f"no {fmt} artifact at {path} (export with --format {fmt})")
    names = [spec["name"] for spec in info["inputs"]]
    if fmt == "onnx":
        return _onnx_step(path, names, threads)
    module = torch.export.load(path).module() if fmt == "torch" else torch._inductor.aoti_load_package(str(path))

    def step(inputs: dict[str, torch.Tensor]):
        with torch.no_grad():
            return module(*(inputs.get(name) for name in StreamingStep.arguments))

    return step


def _onnx_step(path: Path, names: list[str], threads: int):
    try:
        import onnxruntime
    except ImportError:
        raise ImportError("running the ONNX model needs onnxruntime: pip install 'daof[export]'") from None
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = threads
    session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    run = session.run

    def step(inputs: dict[str, torch.Tensor]):
        estimate, window = run(None, {name: inputs[name].numpy() for name in names})
        return torch.from_numpy(estimate), torch.from_numpy(window)

    return step


def stream(step, info: dict, measurement, control=None, prev_control=None) -> torch.Tensor:
    """Estimates [runs, steps, n] of ``step`` on [runs, steps, ·] data, carrying the state from its initial value."""
    runs, steps = measurement.shape[:2]
    spec = {entry["name"]: entry for entry in info["inputs"]}
    state = {"window": torch.zeros(runs, spec["window"]["shape"][1])}
    if "prev_estimate" in info["initial"]:
        state["prev_estimate"] = torch.tensor(info["initial"]["prev_estimate"]).expand(runs, -1).contiguous()
    state["step"] = torch.ones(runs, 1, dtype=torch.int64)
    out = []
    for t in range(steps):
        inputs = {"measurement": measurement[:, t].contiguous(), **state}
        if "control" in spec:
            inputs |= {"control": control[:, t].contiguous(), "prev_control": prev_control[:, t].contiguous()}
        estimate, state["window"] = step(inputs)
        if "prev_estimate" in state:
            state["prev_estimate"] = estimate
        state["step"] = state["step"] + 1
        out.append(estimate)
    return torch.stack(out, 1)
