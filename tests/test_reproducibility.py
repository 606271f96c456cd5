"""Reproducibility of the study: the same seeds give bit-identical numbers on the same machine, and an
interrupted study, restarted, reuses what it finished and computes only the rest (to the same bits)."""

import pytest
import torch

from daof.evaluate import run_study
from daof.filters import EKF, UKF, ParticleFilter
from daof.filters.learned import FilterConfig, LearnedFilter

RUNS, STEPS, SEED = 3, 40, 20261122


def filters(system) -> dict:
    """Fresh filter objects: classical ones with their seeds, and a tiny untrained DAOF-v1 whose
    initial weights come from a fixed torch seed (a trained one would come from a checkpoint)."""
    torch.manual_seed(0)
    daof = LearnedFilter(FilterConfig(kind="DAOF-v1", system="veh2dof", window=4, num_cells=16), system)
    daof.fit_normalizer(runs=4, steps=50)
    return {
        "EKF": EKF(system),
        "UKF": UKF(system),
        "PF": ParticleFilter(system, 200, seed=1),
        "DAOF-v1": daof,
    }


def study(system, cache_dir, fs=None, log=None):
    return run_study(
        system,
        fs if fs is not None else filters(system),
        RUNS,
        STEPS,
        SEED,
        measure_cost=False,
        cache_dir=cache_dir,
        log=log if log is not None else (lambda _: None),
    )


def assert_identical(a, b):
    assert list(a.results) == list(b.results)
    for name in a.results:
        ra, rb = a.results[name], b.results[name]
        assert ra.rmse == rb.rmse, name  # exact float equality, not approx
        assert ra.per_run_rmse == rb.per_run_rmse, name
        assert (ra.diverged, ra.repairs) == (rb.diverged, rb.repairs), name
        assert torch.equal(a.estimates[name], b.estimates[name]), name


class Interrupt(KeyboardInterrupt):
    """What Ctrl-C raises in the middle of a filter."""


class Interrupted:
    """A filter that is stopped (Ctrl-C) while it runs."""

    name = "interrupted"

    def run(self, data):
        raise Interrupt


class MustNotRun:
    """A filter whose finished result must come from the cache (it gives a std where the filter it stands for does)."""

    def __init__(self, std_source=None):
        self.std_source = std_source

    def run(self, data):
        raise AssertionError("a finished filter was filtered again")

    run_streaming = run


def test_same_seeds_give_bit_identical_study_numbers(veh, tmp_path):
    first = study(veh, tmp_path / "a")
    second = study(veh, tmp_path / "b")
    torch.testing.assert_close(first.data, second.data, rtol=0, atol=0)
    assert_identical(first, second)
    # and the numbers are real ones: four different filters, all finite
    rmse = torch.tensor([r.rmse for r in first.results.values()])
    assert torch.isfinite(rmse).all() and len({tuple(r) for r in rmse.tolist()}) == 4


def test_an_interrupted_study_resumes_from_what_it_finished(veh, tmp_path):
    reference = study(veh, tmp_path / "uninterrupted")
    cache = tmp_path / "cache"
    fs = filters(veh)
    with pytest.raises(Interrupt):  # stopped while the PF runs: EKF and UKF are finished
        study(veh, cache, {"EKF": fs["EKF"], "UKF": fs["UKF"], "PF": Interrupted(), "DAOF-v1": fs["DAOF-v1"]})
    assert sorted(p.name for p in cache.iterdir()) == ["EKF.pt", "UKF.pt"]  # no partial entries

    logs = []
    fs = filters(veh)
    resumed = study(
        veh,
        cache,
        {"EKF": MustNotRun("covariance"), "UKF": MustNotRun("covariance"), "PF": fs["PF"], "DAOF-v1": fs["DAOF-v1"]},
        logs.append,
    )
    reused = [line.split(":")[0] for line in logs if "reused finished result" in line]
    computed = [line.split(":")[0] for line in logs if "filtering" in line]
    assert reused == ["[1/4] EKF", "[2/4] UKF"] and computed == ["[3/4] PF", "[4/4] DAOF-v1"]
    assert_identical(resumed, reference)


def test_a_damaged_cache_entry_is_computed_again(veh, tmp_path):
    """A cache file cut short (the machine went down while writing it, before writes were atomic) or
    foreign is not an error: that filter is filtered again, the others are reused."""
    reference = study(veh, tmp_path / "cache")
    (tmp_path / "cache" / "UKF.pt").write_bytes(b"PK\x03\x04 truncated")
    torch.save({"something": "else"}, tmp_path / "cache" / "PF.pt")
    logs = []
    fs = filters(veh)
    again = study(
        veh,
        tmp_path / "cache",
        {"EKF": MustNotRun("covariance"), "UKF": fs["UKF"], "PF": fs["PF"], "DAOF-v1": MustNotRun()},
        logs.append,
    )
    assert any("unreadable cache entry" in line and "UKF.pt" in line for line in logs)
    assert [line.split(":")[0] for line in logs if "filtering" in line] == ["[2/4] UKF", "[3/4] PF"]
    assert_identical(again, reference)
