"""Exported streaming steps (daof.export): the step equals eager streaming, the torch.export program and
the ONNX model (onnxruntime) equal eager on a 500-step trajectory with sensor gaps, the command and its
refusals. The AOTInductor package's parity is the slow test (its compile takes minutes)."""

import json

import pytest
import torch

from daof.export import (
    FORMATS,
    contract,
    example_inputs,
    export_filter,
    load_step,
    read_contract,
    stream,
    streaming_step,
)
from daof.export.__main__ import main
from daof.filters import UKF
from daof.filters.learned import make_filter
from daof.filters.learned.kalmannet import STATE_KEYS
from daof.train.schedules import ukf_schedule

onnxruntime = pytest.importorskip("onnxruntime")

#: the filter forms of the parity checks: kind and config fields
FORMS = {
    "DAOF-v1": ("DAOF-v1", {}),
    "DAOF-v2": ("DAOF-v2", {}),
    "SLF": ("SLF", {}),
    "DAOF-v1-hold": ("DAOF-v1", {}),
    "DAOF-v2-increment": ("DAOF-v2", {"v2_action": "increment"}),
    "DAOF-v2-flags": ("DAOF-v2", {"missing_mask": True}),
    "KalmanNet": ("KalmanNet", {}),
}
STEPS = 500


def tiny(form: str):
    """A randomly initialised filter (16 cells, N = 4) with fitted normalisation (and DAOF-v1's UKF schedules)."""
    kind, fields = FORMS[form]
    torch.manual_seed(1)
    f = make_filter(kind, system="veh2dof", window=4, num_cells=16, **fields)
    f.fit_normalizer(runs=4, steps=50)
    if kind == "DAOF-v1":
        f.set_schedules(ukf_schedule(f.system, seed=3, runs=4))
    if form.endswith("-hold"):
        f.missing_fill = "hold"
    return f.eval()


def gappy_data(system, runs: int = 3, steps: int = STEPS):
    """Simulated data with missing channels: a leading gap, single-channel and all-channel gaps of a few steps."""
    data = system.simulate(runs, steps, seed=20261207)
    y = data["measurement"].clone()
    y[0, 0, 0] = float("nan")  # before any value: the channel's training mean
    y[1, 0:3, :] = float("nan")
    y[0, 40:46, 1] = float("nan")
    y[2, 100:110, :] = float("nan")
    y[1, 300:302, 0] = float("nan")
    data["measurement"] = y
    return data


def step_through(step, data) -> torch.Tensor:
    """The step module called in Python step by step (state carried as the contract says)."""
    info = contract(step, {})
    return stream(lambda inputs: step(*(inputs.get(n) for n in step.arguments)), info, *_signals(data))


def _widths(step) -> dict[str, int]:
    args = example_inputs(step)
    return {name: a.shape[-1] for name, a in zip(step.arguments, args) if a is not None}


def _signals(data):
    return data["measurement"], data["control"], data["prev_control"]


def tolerance(system) -> torch.Tensor:
    """1e-5 of each state's scale: the half-width of its plausible range (0.3 rad, 1.5 rad/s on veh2dof).

    Not the typical error ``error_scale`` (0.01 rad for β): 1e-7 rad is ~3 float32 ulps of a 0.3 rad
    estimate, and onnxruntime's kernels (matmul order, erf, atan) differ from torch's by a few ulps
    (measured 1.8e-7 rad, bounded over 500 steps; docs/deploy.md).
    """
    return 1e-5 * (system.state_high - system.state_low) / 2


def assert_parity(estimates: torch.Tensor, eager: torch.Tensor, system) -> None:
    assert estimates.shape == eager.shape
    assert torch.isfinite(estimates).all()
    worst = (estimates - eager).abs().flatten(0, 1).max(0).values
    assert (worst <= tolerance(system)).all(), f"max |Δ| per state {worst.tolist()} > {tolerance(system).tolist()}"


@pytest.mark.parametrize("form", list(FORMS))
def test_step_module_equals_eager_streaming(form):
    """The step as a Python module, carried by hand, gives eager ``run_streaming``'s estimates to the bit."""
    f = tiny(form)
    data = gappy_data(f.system, steps=120)
    eager = f.run_streaming(data)
    with torch.no_grad():
        torch.testing.assert_close(step_through(streaming_step(f), data), eager, rtol=0, atol=0)
    # the gaps reach the estimates: the same data without them gives others
    full = f.system.simulate(3, 120, seed=20261207)
    assert not torch.equal(f.run_streaming(full), eager)


@pytest.fixture(scope="module", params=["DAOF-v1", "DAOF-v2", "SLF", "KalmanNet"])
def exported(request, tmp_path_factory):
    """(filter, its export directory) with the torch.export program and the ONNX model."""
    f = tiny(request.param)
    out = tmp_path_factory.mktemp(request.param)
    export_filter(f, out, ["torch", "onnx"])
    return f, out


@pytest.mark.parametrize("fmt", ["torch", "onnx"])
def test_exported_step_equals_eager(exported, fmt):
    """500 steps with gaps (3 runs at once: the batch size is dynamic): max |Δ| ≤ 1e-5 of each state's scale."""
    f, out = exported
    data = gappy_data(f.system)
    eager = f.run_streaming(data)
    estimates = stream(load_step(out, fmt), read_contract(out), *_signals(data))
    assert_parity(estimates, eager, f.system)
    # batch 1 too (a deployed filter's case): the third run's first 150 steps, through its all-channel gap
    one = stream(load_step(out, fmt), read_contract(out), *(x[2:, :150] for x in _signals(data)))
    assert_parity(one, eager[2:, :150], f.system)


def test_contract_describes_the_step(exported):
    """The sidecar names every input and output with its shape and dtype, the state's names, units and start."""
    f, out = exported
    info = json.loads((out / "contract.json").read_text())
    step = streaming_step(f)
    assert [spec["name"] for spec in info["inputs"]] == step.input_names
    assert [spec["name"] for spec in info["outputs"]] == step.output_names
    assert step.output_names[0] == "estimate" and info["arguments"] == list(step.arguments)
    widths = _widths(step)
    for spec in info["inputs"]:
        assert spec["shape"] == ["batch", widths[spec["name"]]]
        assert spec["dtype"] == ("int64" if spec["name"] == "step" else "float32")
    estimate = info["outputs"][0]
    assert estimate["names"] == ["beta", "yaw_rate"] and estimate["units"] == ["rad", "rad/s"]
    assert info["files"] == {"torch": FORMATS["torch"], "onnx": FORMATS["onnx"]}
    # every carried input starts at a stated value and is fed by an output
    assert set(info["carry"]) - {"step"} == set(info["initial"]) - {"step"}
    assert {source for name, source in info["carry"].items() if name != "step"} <= set(step.output_names)
    carried = {"SLF": {"window"}, "KalmanNet": {f"state_{k}" for k in STATE_KEYS}}
    assert set(info["carry"]) - {"step"} == carried.get(f.kind, {"window", "prev_estimate"})
    session = onnxruntime.InferenceSession(str(out / info["files"]["onnx"]), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == step.input_names
    assert [o.name for o in session.get_outputs()] == step.output_names


def test_command_exports_a_checkpoint(tmp_path, capsys):
    """``python -m daof.export`` writes the program and the contract; a bad format or file is one line, exit 2."""
    f = tiny("DAOF-v2")
    f.save(tmp_path / "best.pt")
    out = tmp_path / "exported"
    assert main([str(tmp_path / "best.pt"), "--out", str(out), "--format", "torch"]) == 0
    info = read_contract(out)
    assert info["files"] == {"torch": "step.pt2"} and info["source"]["checkpoint"] == "best.pt"
    assert len(info["source"]["sha256"]) == 64
    data = gappy_data(f.system, steps=60)
    assert_parity(stream(load_step(out, "torch"), info, *_signals(data)), f.run_streaming(data), f.system)
    capsys.readouterr()
    assert main([str(tmp_path / "best.pt"), "--out", str(out), "--format", "tflite"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "tflite" in err
    assert main([str(tmp_path / "none.pt"), "--out", str(out)]) == 2
    assert "no filter checkpoint" in capsys.readouterr().err
    with pytest.raises(ValueError, match="only a learned filter"):
        export_filter(UKF(f.system), tmp_path / "ukf")
    with pytest.raises(ValueError, match="export formats"):
        export_filter(f, tmp_path / "none", [])
    with pytest.raises(FileNotFoundError, match="--format onnx"):
        load_step(out, "onnx")
    with pytest.raises(ValueError, match="unknown export format"):
        load_step(out, "tflite")
    with pytest.raises(FileNotFoundError, match="not an exported filter"):
        load_step(tmp_path, "torch")


@pytest.mark.slow
@pytest.mark.parametrize("form", ["DAOF-v1", "DAOF-v2", "SLF", "KalmanNet"])
def test_aoti_package_equals_eager(form, tmp_path):
    """The AOTInductor package (compiled C++) on the same 500-step trajectory: max |Δ| ≤ 1e-5 of each state's scale."""
    f = tiny(form)
    export_filter(f, tmp_path, ["aoti"])
    data = gappy_data(f.system)
    estimates = stream(load_step(tmp_path, "aoti"), read_contract(tmp_path), *_signals(data))
    assert_parity(estimates, f.run_streaming(data), f.system)
