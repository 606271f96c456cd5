"""Export a trained learned filter as a self-contained streaming step (docs/deploy.md).

``export_filter(filt, out, formats)`` writes the step (``streaming_step``) as a ``torch.export``
program, an AOTInductor package and an ONNX model, with the JSON contract beside them (the step
also outputs the error std σ when the filter has an uncertainty head, ``filt.uncertainty``);
``python -m daof.export CHECKPOINT --out DIR`` does it from a checkpoint. ``load_step`` and
``stream`` run what was written.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from daof.export.artifacts import FORMATS, ONNX_OPSET, example_inputs, export_program, write
from daof.export.contract import CONTRACT_FILE, contract, read_contract, write_contract
from daof.export.runtime import load_step, stream, trajectory
from daof.export.step import KalmanNetStep, StreamingStep, streaming_step

__all__ = [
    "CONTRACT_FILE",
    "FORMATS",
    "KalmanNetStep",
    "ONNX_OPSET",
    "StreamingStep",
    "contract",
    "example_inputs",
    "export_filter",
    "export_program",
    "file_digest",
    "load_step",
    "read_contract",
    "stream",
    "streaming_step",
    "trajectory",
    "write",
]


def export_filter(filt, out: str | Path, formats=("torch", "onnx"), source: dict | None = None) -> dict:
    """Write ``filt``'s streaming step (with σ if it has an uncertainty head) into directory ``out`` in
    ``formats``, then its contract (returned)."""
    from daof.filters.learned import LearnedFilter

    if not isinstance(filt, LearnedFilter):
        raise ValueError(
            f"only a learned filter (DAOF-v1, DAOF-v2, SLF, KalmanNet) exports, not a {type(filt).__name__}"
        )
    unknown = [fmt for fmt in formats if fmt not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"export formats must be some of {sorted(FORMATS)}, got {list(formats)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    step = streaming_step(filt)
    program = export_program(step)
    files = {fmt: write(program, fmt, out, step.output_names).name for fmt in formats}
    info = contract(step, files, source)
    if "onnx" in formats:
        info["onnx_opset"] = ONNX_OPSET
    write_contract(info, out)
    return info


def file_digest(path: str | Path) -> str:
    """The sha256 of a file (the contract names the checkpoint it was exported from)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
