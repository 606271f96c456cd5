"""Exported streaming steps (daof.export): the step equals eager streaming, the torch.export program and
the ONNX model (onnxruntime) equal eager on a 500-step trajectory with sensor gaps, the command and its
refusals; with an uncertainty head the step's σ equals ``run_with_std``'s. The AOTInductor package's
parity is the slow test (its compile takes minutes)."""

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
from daof.filters.learned import load_filter, make_filter
from daof.filters.learned.kalmannet import STATE_KEYS
from daof.filters.learned.uncertainty import file_digest, head_path, save_head
from daof.train.schedules import ukf_schedule
from daof.train.uncertainty import HeadSettings, fit_head

onnxruntime = pytest.importorskip("onnxruntime")

#: the filter forms of the parity checks: kind and config fields
FORMS = {
    "DAOF-v1": ("DAOF-v1", {}),
    "DAOF-v2": ("DAOF-v2", {}),
    "SLF": ("SLF", {}),
    "DAOF-v1-hold": ("DAOF-v1", {}),
    "DAOF-v2-flags": ("DAOF-v2", {"missing_mask": True}),
    "KalmanNet": ("KalmanNet", {}),
}
STEPS = 500
KINDS = ["DAOF-v1", "DAOF-v2", "SLF", "KalmanNet"]
#: a head fitted cheaply (test_uncertainty.py's recipe, smaller): its σ varies with ρ_t and the features
HEAD = HeadSettings(runs=8, steps=60, epochs=3, batch_size=128, lr=1e-2, num_cells=16)


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


def with_head(form: str):
    """``tiny(form)`` with an uncertainty head fitted to it (``HEAD``) and attached."""
    f = tiny(form)
    f.attach_uncertainty(fit_head(f, HEAD, seed=5, log=lambda *_: None)[0])
    return f


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


def step_through(step, data, std: bool = False, shift: int = 0):
    """The step module called in Python step by step (state carried as the contract says); with ``std``
    (estimates, σ); ``shift`` adds to the step index t (a wrong ρ_t, for the checks that must fail)."""
    info = contract(step, {})

    def call(inputs):
        inputs = {**inputs, "step": inputs["step"] + shift} if shift else inputs
        return step(*(inputs.get(n) for n in step.arguments))

    return stream(call, info, *_signals(data), std=std)


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


#: σ's bound relative to σ itself, beside the estimates' bound: measured ≤ 2.3e-6 (onnxruntime, DAOF-v1), a few
#: ulps of the features passed through the head's normalisation and exp; a wrong feature or ρ_t is off by %
STD_RTOL = 1e-4


def assert_std_parity(std: torch.Tensor, eager: torch.Tensor, system) -> None:
    """σ within the estimates' bound (1e-5 of each state's scale) and within ``STD_RTOL`` of eager's σ."""
    assert_parity(std, eager, system)
    assert bool((std > 0).all())
    worst = ((std - eager).abs() / eager).flatten(0, 1).max(0).values
    assert (worst <= STD_RTOL).all(), f"max |Δσ|/σ per state {worst.tolist()} > {STD_RTOL}"


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


@pytest.mark.parametrize("kind", KINDS)
def test_step_module_std_equals_run_with_std(kind):
    """With a head the step module outputs σ as ``run_with_std`` on 500 steps with gaps, the estimates unchanged;
    the check fails for a step fed the wrong t (ρ_t off by 50 steps)."""
    f = with_head(kind)
    data = gappy_data(f.system)
    eager, eager_std = f.run_with_std(data)
    step = streaming_step(f)
    with torch.no_grad():
        estimates, std = step_through(step, data, std=True)
        torch.testing.assert_close(estimates, f.run_streaming(data), rtol=0, atol=0)
        assert_std_parity(std, eager_std, f.system)
        shifted = step_through(step, data, std=True, shift=50)[1]
    with pytest.raises(AssertionError, match="per state"):
        assert_std_parity(shifted, eager_std, f.system)


@pytest.mark.parametrize("kind", KINDS)
def test_a_head_adds_only_the_std_output(kind):
    """The contract of a filter with a head is the one without plus ``std`` (after ``estimate``), its source and,
    for KalmanNet, the step index t; carry names unchanged."""
    f = tiny(kind)
    plain = contract(streaming_step(f), {})
    f.attach_uncertainty(fit_head(f, HeadSettings(runs=8, steps=20, epochs=1, num_cells=16), 5, lambda *_: None)[0])
    step = streaming_step(f)
    info = contract(step, {})
    std = info["outputs"][1]
    assert step.output_names[:2] == ["estimate", "std"] and std["name"] == "std"
    assert std["shape"] == ["batch", 2] and std["units"] == ["rad", "rad/s"] and std["dtype"] == "float32"
    assert "uncertainty head" in std["source"] and "exp(½ log σ²_t)" in std["source"]
    assert info.pop("std_source") == "uncertainty head" and info.pop("uncertainty_head") == f.uncertainty.settings
    del info["outputs"][1]
    if kind == "KalmanNet":  # ρ_t needs t: the step index is an input of its own
        assert info["arguments"][-1] == "step" and info["inputs"][-1]["name"] == "step"
        assert info["initial"].pop("step") == 1 and info["carry"].pop("step") == "step + 1"
        del info["arguments"][-1], info["inputs"][-1]
    assert info == plain


@pytest.fixture(scope="module", params=KINDS)
def exported(request, tmp_path_factory):
    """(filter, its export directory) with the torch.export program and the ONNX model."""
    f = tiny(request.param)
    out = tmp_path_factory.mktemp(request.param)
    export_filter(f, out, ["torch", "onnx"])
    return f, out


@pytest.fixture(scope="module", params=KINDS)
def exported_with_head(request, tmp_path_factory):
    """(filter with a head, its export directory) with the torch.export program and the ONNX model."""
    f = with_head(request.param)
    out = tmp_path_factory.mktemp(f"{request.param}-std")
    export_filter(f, out, ["torch", "onnx"])
    return f, out


@pytest.mark.parametrize("fmt", ["torch", "onnx"])
def test_exported_std_equals_run_with_std(exported_with_head, fmt):
    """500 steps with gaps at batch 3, and batch 1: σ as ``run_with_std``'s (``assert_std_parity``), x̂ as eager's."""
    f, out = exported_with_head
    data = gappy_data(f.system)
    eager, eager_std = f.run_with_std(data)
    info = read_contract(out)
    assert [spec["name"] for spec in info["outputs"]][:2] == ["estimate", "std"]
    estimates, std = stream(load_step(out, fmt), info, *_signals(data), std=True)
    assert_parity(estimates, f.run_streaming(data), f.system)
    assert_std_parity(std, eager_std, f.system)
    one = stream(load_step(out, fmt), info, *(x[2:, :150] for x in _signals(data)), std=True)
    assert_std_parity(one[1], eager_std[2:, :150], f.system)
    assert torch.equal(stream(load_step(out, fmt), info, *_signals(data)), estimates)  # without std: as before
    session = onnxruntime.InferenceSession(str(out / info["files"]["onnx"]), providers=["CPUExecutionProvider"])
    assert [o.name for o in session.get_outputs()] == streaming_step(f).output_names


def test_without_a_head_there_is_no_std(exported):
    """A filter without a head exports as before: no std output, no std_source; asking ``stream`` for σ is refused."""
    f, out = exported
    info = read_contract(out)
    carried = {"SLF": ["next_window"], "KalmanNet": [f"next_state_{k}" for k in STATE_KEYS]}
    assert [spec["name"] for spec in info["outputs"]] == ["estimate", *carried.get(f.kind, ["next_window"])]
    assert "std_source" not in info and "uncertainty_head" not in info
    assert f.kind != "KalmanNet" or "step" not in info["arguments"]
    with pytest.raises(ValueError, match="exported without an uncertainty head"):
        stream(load_step(out, "torch"), info, *_signals(gappy_data(f.system, steps=5)), std=True)


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


def test_command_exports_the_std_of_an_attached_head(tmp_path, capsys):
    """A checkpoint with its head beside it (``best.uncertainty.pt``) exports σ too; a stale head is left off."""
    f = with_head("KalmanNet")
    f.save(tmp_path / "best.pt")
    save_head(f.uncertainty, head_path(tmp_path / "best.pt"), file_digest(tmp_path / "best.pt"))
    out = tmp_path / "exported"
    assert main([str(tmp_path / "best.pt"), "--out", str(out), "--format", "torch"]) == 0
    assert "std: the error std per state, from best.uncertainty.pt" in capsys.readouterr().out
    info = read_contract(out)
    assert info["std_source"] == "uncertainty head" and info["source"]["uncertainty_head"] == "best.uncertainty.pt"
    assert len(info["source"]["uncertainty_head_sha256"]) == 64
    data = gappy_data(f.system, steps=60)
    std = stream(load_step(out, "torch"), info, *_signals(data), std=True)[1]
    assert_std_parity(std, load_filter(tmp_path / "best.pt").run_with_std(data)[1], f.system)
    f.save(tmp_path / "best.pt", extra={"another": "version"})  # the head no longer fits this file
    with pytest.warns(UserWarning, match="fitted to another filter checkpoint"):
        assert main([str(tmp_path / "best.pt"), "--out", str(out), "--format", "torch"]) == 0
    assert "std" not in [spec["name"] for spec in read_contract(out)["outputs"]]


@pytest.mark.slow
@pytest.mark.parametrize("form", KINDS)
def test_aoti_package_equals_eager(form, tmp_path):
    """The AOTInductor package (compiled C++) on the same 500-step trajectory: max |Δ| ≤ 1e-5 of each state's scale."""
    f = tiny(form)
    export_filter(f, tmp_path, ["aoti"])
    data = gappy_data(f.system)
    estimates = stream(load_step(tmp_path, "aoti"), read_contract(tmp_path), *_signals(data))
    assert_parity(estimates, f.run_streaming(data), f.system)
