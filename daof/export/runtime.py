"""Run an exported step: load an artifact as a callable, and stream a trajectory through it.

``load_step(directory, fmt)`` gives ``step(inputs) -> outputs`` (the contract's outputs in order,
the estimate first) for inputs a dict of tensors by the contract's input names, whichever the
format: the ``torch.export`` program (``torch.export.load``), the AOTInductor package
(``aoti_load_package``) or the ONNX model (onnxruntime, one thread). ``stream`` carries the state as the contract says.
"""

from __future__ import annotations

from pathlib import Path

import torch

from daof.export.artifacts import FORMATS
from daof.export.contract import read_contract
from daof.export.step import StreamingStep

__all__ = ["load_step", "stream", "trajectory"]


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
    if fmt == "aoti":  # the package's runner on the flat tensors (its __call__ adds a pytree round trip)
        run = torch._inductor.aoti_load_package(str(path)).loader.run

        def step(inputs: dict[str, torch.Tensor]):
            return tuple(run([inputs[name] for name in names]))

        return step
    module = torch.export.load(path).module()
    arguments = info.get("arguments", StreamingStep.arguments)  # contracts before KalmanNet's had none

    def step(inputs: dict[str, torch.Tensor]):
        with torch.no_grad():
            return module(*(inputs.get(name) for name in arguments))

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
        return tuple(torch.from_numpy(out) for out in run(None, {name: inputs[name].numpy() for name in names}))

    return step


def stream(step, info: dict, measurement, control=None, prev_control=None, std: bool = False):
    """Estimates [runs, steps, n] of ``step`` on [runs, steps, ·] data, carrying the state from its initial value;
    with ``std``, (estimates, σ) as ``Filter.run_with_std`` (a step exported with an uncertainty head).

    The per-step inputs are sliced before the loop, so the loop holds the step and the carry only
    (``benchmarks/bench_learned.py`` times it).
    """
    return trajectory(step, info, measurement, control, prev_control, std)()


def trajectory(step, info: dict, measurement, control=None, prev_control=None, std: bool = False):
    """A function that streams the data through ``step`` and returns the estimates, with ``std`` also σ
    (``stream``, prepared).

    The carried inputs start at the contract's ``initial`` values and take the outputs its ``carry``
    names; ``step`` (t = 1, 2, …) is an input of its own, set before the loop.
    """
    runs, steps = measurement.shape[:2]
    spec = {entry["name"]: entry for entry in info["inputs"]}
    outputs = [entry["name"] for entry in info["outputs"]]
    if std and "std" not in outputs:
        raise ValueError(
            f"this {info.get('filter', 'filter')} step has no std output: it was exported without an uncertainty "
            "head (fit one: python -m daof.train.uncertainty RUN_DIR, then export again)"
        )
    carry = {name: outputs.index(source) for name, source in info["carry"].items() if source in outputs}
    per_step = {"measurement": measurement.unbind(1)}
    if "control" in spec:
        per_step |= {"control": control.unbind(1), "prev_control": prev_control.unbind(1)}
    per_step = [{key: value[t].contiguous() for key, value in per_step.items()} for t in range(steps)]
    if "step" in spec:
        for t, inputs in enumerate(per_step):
            inputs["step"] = torch.full((runs, 1), t + 1, dtype=torch.int64)
    start = {name: _initial(info["initial"][name], spec[name], runs) for name in carry}

    def run() -> torch.Tensor:
        out, carried = [], start
        for inputs in per_step:
            inputs.update(carried)
            result = step(inputs)
            carried = {name: result[k] for name, k in carry.items()}
            out.append(result[0])
        return torch.stack(out, 1)

    def run_with_std() -> tuple[torch.Tensor, torch.Tensor]:
        out, sigma, carried, k_std = [], [], start, outputs.index("std")
        for inputs in per_step:
            inputs.update(carried)
            result = step(inputs)
            carried = {name: result[k] for name, k in carry.items()}
            out.append(result[0])
            sigma.append(result[k_std])
        return torch.stack(out, 1), torch.stack(sigma, 1)

    return run_with_std if std else run


def _initial(value, spec: dict, runs: int) -> torch.Tensor:
    """A carried input's value before step 1: the contract's row for every run, or zeros (a string says so)."""
    if isinstance(value, list):
        return torch.tensor(value, dtype=torch.float32).expand(runs, -1).contiguous()
    return torch.zeros(runs, spec["shape"][1])
