"""Write a filter's step (``StreamingStep``, ``KalmanNetStep``) as files: a ``torch.export`` program,
an AOTInductor package, an ONNX model.

Each writer traces the step with ``torch.export.export`` (batch size dynamic) and writes its file
atomically (a temporary file, then rename). ``FORMATS`` maps a format name to its file name.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

__all__ = ["AOTI_CONFIGS", "FORMATS", "ONNX_OPSET", "example_inputs", "export_program", "write"]

#: format -> file name inside the output directory
FORMATS = {"torch": "step.pt2", "aoti": "step_aoti.pt2", "onnx": "step.onnx"}
#: the ONNX opset the model is written with
ONNX_OPSET = 20
#: Inductor's options for the AOTInductor package: autotuned matmuls, which pick its C++ micro-GEMM
#: for the batch-1 layers (1.5× faster per step than the default's ATen addmm on veh2dof's DAOF-v2,
#: docs/deploy.md); compiling takes about a minute longer
AOTI_CONFIGS = {"max_autotune": True, "max_autotune_gemm_backends": "CPP,ATEN"}


def example_inputs(step: nn.Module, batch: int = 2) -> tuple[torch.Tensor | None, ...]:
    """Arguments of ``step`` at ``batch`` (None where it takes none), from its initial state."""
    s = step.filter.system
    state = step.initial_state(batch)
    values = {"measurement": torch.zeros(batch, s.measurement_dim)}
    if step.has_controls:
        values |= {"control": torch.zeros(batch, s.control_dim), "prev_control": torch.zeros(batch, s.control_dim)}
    values |= state
    return tuple(values.get(name) for name in step.arguments)


def export_program(step: nn.Module) -> torch.export.ExportedProgram:
    """The step traced by ``torch.export.export`` with a dynamic batch dimension (traced at batch 2)."""
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    args = example_inputs(step)
    with torch.no_grad():
        return torch.export.export(
            step.eval(), args, dynamic_shapes=tuple(None if a is None else {0: batch} for a in args)
        )


def write(program: torch.export.ExportedProgram, fmt: str, out: Path, output_names=("estimate", "next_window")) -> Path:
    """Write ``program`` in format ``fmt`` into directory ``out`` (ONNX outputs named ``output_names``);
    returns the file written."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; valid: {sorted(FORMATS)}")
    path = Path(out) / FORMATS[fmt]
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")  # same suffix: the writers check it
    try:
        if fmt == "torch":
            torch.export.save(program, tmp)
        elif fmt == "aoti":
            torch._inductor.aoti_compile_and_package(program, package_path=str(tmp), inductor_configs=AOTI_CONFIGS)
        else:
            _write_onnx(program, tmp, list(output_names))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _write_onnx(program: torch.export.ExportedProgram, path: Path, output_names: list[str]) -> None:
    """The ONNX model of ``program`` (torch.onnx's dynamo exporter); inputs keep the program's names."""
    onnx_program = torch.onnx.export(
        program,
        output_names=output_names,
        opset_version=ONNX_OPSET,
        dynamo=True,
        verbose=False,
    )
    onnx_program.save(str(path))
