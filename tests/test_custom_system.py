"""A system of the user's own code (docs/custom_system.md): by import path through make_system, the
training CLI and an experiment YAML kept outside daof, trained, studied and reported end to end.

``TinySystem`` below lives in this test module only: daof neither registers nor ships it. The
experiment's training subprocesses import it because the runner puts this file's folder on their
PYTHONPATH (``daof.envs.registry.import_root``); the working directory is elsewhere.
"""

from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from daof.envs import StochasticSystem, make_system
from daof.envs.noise import GaussianNoise
from daof.envs.registry import import_root

PATH = f"{__name__}:TinySystem"


@dataclass
class TinyParams:
    a: float = 0.8
    q: float = 0.1
    r: float = 0.2


class TinySystem(StochasticSystem):
    """x_t = a x + 0.5 sin(x) + u, y = x + x³/10 + w, u_t = 0.5 cos(0.3 t)."""

    name = "tiny"
    params_class = TinyParams
    dt = 0.1
    state_names = ("x",)
    state_units = ("m",)
    measurement_names = ("y",)
    measurement_units = ("m",)
    control_names = ("u",)

    def __init__(self, scenario: str = "nominal", params: TinyParams | None = None):
        self.scenario = scenario
        self.p = p = params or TinyParams()
        self.prior = GaussianNoise.diagonal([0.0], [1.0])
        self.process_noise = GaussianNoise.diagonal([0.0], [math.sqrt(p.q)])
        self.measurement_noise = GaussianNoise.diagonal([0.0], [math.sqrt(p.r)])

    def f(self, x, u):
        return self.p.a * x + 0.5 * torch.sin(x) + u

    def g(self, x, u):
        return x + x**3 / 10

    def control(self, t, params):
        return 0.5 * torch.cos(0.3 * t.float()).unsqueeze(-1)


class NoParams(TinySystem):
    """Built by a plain constructor: no parameter overrides."""

    params_class = None

    def __init__(self):
        super().__init__("nominal", TinyParams())


class SimulatorOnly(TinySystem):
    """A simulator and nothing for filters to call (like veh14dof): it draws x and y itself."""

    has_model = False
    f, g = StochasticSystem.f, StochasticSystem.g

    def transition(self, x, u, params, generator):
        return TinySystem.f(self, x, u) + self.process_noise.sample(x.shape[:-1], generator)

    def measure(self, x, u, params, generator):
        return TinySystem.g(self, x, u) + self.measurement_noise.sample(x.shape[:-1], generator)


class Broken(StochasticSystem):
    def __init__(self, scenario="nominal"):
        raise RuntimeError("cannot build")


EXPERIMENT = """
defaults:
  - experiment_schema
  - _self_
system: {system}
title: "A system of the user's code"
root: {root}
learned:
  SLF: {{filter: slf}}
classical:
  UKF: {{filter: UKF}}
  PF-oracle: {{filter: ParticleFilter, seed: 2}}
reference: [PF-oracle]
profiles:
  tiny:
    runs: 3
    steps: 40
    frames: {{SLF: 1000}}
    particles: {{PF-oracle: 2000}}
    overrides:
      SLF: [network.num_cells=16, collector.env_batch=4, collector.episode_steps=50, validation.runs=2,
            validation.steps=30, validation.every_frames=500, checkpoint.every_frames=500]
"""


def test_a_system_of_the_test_module_trains_and_reports_end_to_end_by_import_path(
    local_ray, tmp_path, monkeypatch, capsys
):
    from daof.experiments.experiment import main
    from daof.filters.learned import load_filter

    project = tmp_path / "project"  # the user's own project folder: their YAML and results, not daof's
    project.mkdir()
    (project / "experiment.yaml").write_text(EXPERIMENT.format(system=PATH, root=project / "runs"))
    monkeypatch.chdir(project)  # the test module is not importable from here: only through PYTHONPATH
    monkeypatch.delenv("PYTHONPATH", raising=False)
    main(["experiment=experiment.yaml", "profile=tiny"])
    out = project / "runs" / "nominal"
    results = json.loads((out / "report" / "results.json").read_text())
    assert results["system"] == PATH and results["runs"] == 3 and results["steps"] == 40
    assert list(results["filters"]) == ["UKF", "PF-oracle", "SLF"]
    assert "reference_check" in results  # the reference was checked (doubling its particles) before any ratio
    for name, row in results["filters"].items():
        assert len(row["rmse"]) == 1 and math.isfinite(row["rmse"][0]), name
    assert (out / "report" / "report.md").read_text().count(PATH) >= 1
    saved = json.loads((out / "slf-N20-s1" / "run_config.json").read_text())
    assert saved["system"] == PATH
    # the checkpoint rebuilds its system from the import path it records
    filt = load_filter(out / "slf-N20-s1" / "best.pt")
    assert isinstance(filt.system, TinySystem) and filt.system.name == PATH
    assert load_filter(out / "slf-N20-s1" / "best.pt", make_system(PATH)).config.system == PATH


def test_training_jobs_put_the_system_folder_on_pythonpath(tmp_path, monkeypatch):
    from daof.experiments.jobs import TrainingJob

    here = str(Path(__file__).resolve().parent)
    assert import_root(PATH) == Path(here)
    assert import_root("linear") is None
    monkeypatch.setattr(sys.modules["__main__"], "_TinyInMain", TinySystem, raising=False)
    with pytest.raises(ValueError, match="is defined in the script being run"):
        import_root("__main__:_TinyInMain")
    job = TrainingJob("SLF", tmp_path, 10, pythonpath=[here])
    assert job.environment({"PYTHONPATH": "/elsewhere"})["PYTHONPATH"] == f"{here}{os.pathsep}/elsewhere"
    assert job.environment({})["PYTHONPATH"] == here
    assert "PYTHONPATH" not in TrainingJob("SLF", tmp_path, 10).environment({})


def test_make_system_by_import_path_takes_parameters_and_scenario_checks():
    system = make_system(PATH, q=0.5)
    assert type(system) is TinySystem and system.p.q == 0.5 and system.name == PATH
    assert make_system(f"{__name__}:NoParams").name == f"{__name__}:NoParams"
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['nope'\]"):
        make_system(PATH, nope=1)
    with pytest.raises(ValueError, match="takes no parameter overrides"):
        make_system(f"{__name__}:NoParams", q=0.5)
    with pytest.raises(ValueError, match="unknown scenario 'mismatch'"):
        make_system(PATH, "mismatch")


@pytest.mark.parametrize(
    "path, message",
    [
        ("no_such_module_xyz.sub:Cls", "no module named 'no_such_module_xyz'"),
        (f"{__name__}:Missing", f"module '{__name__}' has no attribute 'Missing'"),
        (f"{__name__}:TinyParams", "is not a StochasticSystem subclass"),
        (f"{__name__}:EXPERIMENT", "is not a StochasticSystem subclass"),
        (f"{__name__}:", "is not an import path 'package.module:Class'"),
        (":TinySystem", "is not an import path 'package.module:Class'"),
        ("no_such_system", "unknown system 'no_such_system'"),
    ],
)
def test_a_bad_import_path_is_one_line(path, message):
    with pytest.raises(ValueError, match=message) as error:
        make_system(path)
    assert "\n" not in str(error.value)


def test_a_module_that_fails_to_import_is_one_line(tmp_path, monkeypatch):
    (tmp_path / "user_broken_mod.py").write_text("import no_such_dependency_xyz\n")
    (tmp_path / "user_raising_mod.py").write_text("raise RuntimeError('bad\\nconfig')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match="no module named 'no_such_dependency_xyz' while importing 'user_broken_mod'"):
        make_system("user_broken_mod:X")
    with pytest.raises(ValueError, match=r"importing 'user_raising_mod' failed: RuntimeError: bad$"):
        make_system("user_raising_mod:X")


def test_an_entry_point_names_a_system(monkeypatch):
    import importlib.metadata

    point = importlib.metadata.EntryPoint(name="tiny_ep", value=PATH, group="daof.systems")
    real = importlib.metadata.entry_points
    monkeypatch.setattr(
        importlib.metadata,
        "entry_points",
        lambda **kw: [point] if kw == {"group": "daof.systems", "name": "tiny_ep"} else real(**kw),
    )
    system = make_system("tiny_ep", r=0.3)
    assert type(system) is TinySystem and system.p.r == 0.3 and system.name == "tiny_ep"
    from daof.train.config import compose_config

    assert compose_config(["filter=slf", "system=tiny_ep"]).system == "tiny_ep"


def test_the_training_cli_takes_an_import_path():
    from daof.train.config import compose_config

    cfg = compose_config(["filter=slf", f"system={PATH}", "overrides.q=0.4"])
    assert cfg.system == PATH and cfg.overrides.q == 0.4 and cfg.kind == "SLF"
    assert cfg.collector.total_frames == 1_600_000  # the filter's own budget: no system file is involved
    assert cfg.output_dir == f"runs/{PATH.replace(':', '.')}/nominal/slf-N20-s1"  # no ':' (Windows refuses it)
    with pytest.raises(ValueError, match=f"module '{__name__}' has no attribute 'Nope'"):
        compose_config(["filter=slf", f"system={__name__}:Nope"])
    with pytest.raises(ValueError, match="unknown parameter"):
        compose_config(["filter=slf", f"system={PATH}", "overrides.nope=1"])
    with pytest.raises(ValueError, match="unknown system 'foo'; valid: linear, veh14dof, veh2dof or an import path"):
        compose_config(["filter=slf", "system=foo"])


def test_an_experiment_file_that_is_not_there_is_one_line(tmp_path):
    from daof.experiments.config import compose_experiment

    with pytest.raises(ValueError, match="no experiment file"):
        compose_experiment(str(tmp_path / "missing.yaml"))
    (tmp_path / "notes.txt").write_text("")
    with pytest.raises(ValueError, match="is not a .yaml file"):
        compose_experiment(str(tmp_path / "notes.txt"))


def test_classical_only_studies_the_classical_filters_without_training():
    from daof.experiments.experiment import plan_experiment

    plan = plan_experiment("linear", ["profile=paper", "classical_only=true"])
    sp = plan.scenarios["nominal"]
    assert sp.jobs == {} and plan.cfg.learned == {} and plan.cfg.requirements == {}
    assert list(plan.cfg.classical) == ["KF", "KF-stationary", "PF"] and plan.cfg.reference == ["KF"]
    assert len(plan_experiment("linear", ["profile=paper"]).scenarios["nominal"].jobs) == 4


def test_the_ungm_example_is_the_papers_model(monkeypatch):
    """examples/ungm: x_t = x/2 + 25x/(1+x²) + 8cos(1.2(t−1)) + v, y = x²/20 + w (Gordon et al. 1993)."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1]))
    system = make_system("examples.ungm.system:UNGM")
    x = torch.tensor([[-3.0], [0.5], [10.0]])
    u = torch.tensor([[8.0], [-2.0], [0.0]])
    expected = [0.5 * v + 25 * v / (1 + v * v) + w for v, w in zip([-3.0, 0.5, 10.0], [8.0, -2.0, 0.0])]
    torch.testing.assert_close(system.f(x, u)[:, 0], torch.tensor(expected))
    torch.testing.assert_close(system.g(x, u)[:, 0], torch.tensor([9.0, 0.25, 100.0]) / 20)
    data = system.simulate(2, 3, seed=0)  # the step to x_t is driven by u_{t−1} = 8 cos(1.2 (t−1))
    torch.testing.assert_close(data["prev_control"][0, :, 0], 8 * torch.cos(1.2 * torch.arange(3.0)))
    noise = [system.prior.covariance, system.process_noise.covariance, system.measurement_noise.covariance]
    assert [float(c) for c in noise] == pytest.approx([5.0, 10.0, 1.0])


def test_a_simulator_only_system_trains_model_free_filters_and_refuses_model_based_ones(tmp_path):
    from daof.filters import UKF
    from daof.filters.learned import make_filter
    from daof.train.__main__ import train
    from daof.train.config import compose_config

    path = f"{__name__}:SimulatorOnly"
    small = ["network.num_cells=8", "collector.env_batch=4", "collector.episode_steps=30", "validation.runs=2",
             "validation.steps=20", "validation.every_frames=240", "checkpoint.every_frames=240"]  # fmt: skip
    cfg = compose_config(["filter=slf", f"system={path}", "window=4", "collector.total_frames=240", *small,
                          f"output_dir={tmp_path}"])  # fmt: skip
    summary = train(cfg)
    assert summary["frames"] >= 240 and (tmp_path / "best.pt").is_file()
    system = make_system(path)
    with pytest.raises(ValueError, match="DAOF-v1 needs a model predictor"):
        make_filter("DAOF-v1", system=system, window=4)
    with pytest.raises(NotImplementedError, match="offers no transition model"):
        UKF(system).run(system.simulate(1, 3, seed=0))


def test_the_ungm_numbers_the_docs_quote_are_the_committed_reports():
    """docs/custom_system.md and the log quote the classical-only UNGM report: ratios and the PF's convergence."""
    root = Path(__file__).resolve().parents[1]
    results = json.loads((root / "docs/results/ungm-classical/results.json").read_text())
    assert results["reference"] == "PF-oracle" and results["runs"] == 100 and results["steps"] == 100
    ratio = {name: f["rmse"][0] / results["filters"]["PF-oracle"]["rmse"][0] for name, f in results["filters"].items()}
    (check,) = results["reference_check"]["candidates"]  # PF-oracle with twice its particles
    assert check["name"] == "PF-oracle" and check["converged"]
    change = f"{check['change_percent'][0]:.2f}"
    quoted = f"UKF {ratio['UKF']:.2f}×, EKF {ratio['EKF']:.2f}× the PF-oracle, whose RMSE moves {change} %"
    assert quoted in " ".join((root / "docs/custom_system.md").read_text().split())
    log = " ".join((root / "docs/log/2026-12-07-custom-systems.md").read_text().split())
    assert f"9.201 ({ratio['UKF']:.2f}×)" in log and f"20.89 ({ratio['EKF']:.2f}×)" in log and f"{change} %" in log
    assert ratio["UKF"] >= 1.3 and float(change) < 1.0  # what the example was chosen for: a gap, a converged reference
