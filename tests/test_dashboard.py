"""wandb dashboards: an offline training run holds its resolved config, name, group, tags, scalars
and learning-curve table; a report run holds the results table, its figures and the report artifact."""

import json
import struct
import time
import zlib
from pathlib import Path

import pytest
from test_training import tiny_cfg

from daof.dashboard import log_report
from daof.train.supervised import SLFTrainer

wandb_pb = pytest.importorskip("wandb.proto.wandb_internal_pb2")

#: wandb's offline record file: a 7-byte header, then 32 KiB blocks of chunks (crc32, length, type)
HEADER, BLOCK, CHUNK = 7, 32768, 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def read_records(path: Path) -> list:
    """Every ``Record`` of an offline run's ``run-*.wandb`` file (wandb's log format, read independently)."""
    data = path.read_bytes()
    assert data[:4] == b":W&B", data[:8]
    records, pending, pos = [], b"", HEADER
    while pos + CHUNK <= len(data):
        room = BLOCK - (pos % BLOCK)
        if room < CHUNK:  # a block's tail too short for a chunk header is padding
            pos += room
            continue
        checksum, length, kind = struct.unpack("<IHB", data[pos : pos + CHUNK])
        body = data[pos + CHUNK : pos + CHUNK + length]
        if length == 0 and kind == 0:
            break
        assert zlib.crc32(bytes([kind]) + body) & 0xFFFFFFFF == checksum
        pos += CHUNK + length
        pending = body if kind in (FULL, FIRST) else pending + body
        if kind in (FULL, LAST):
            record = wandb_pb.Record()
            record.ParseFromString(pending)
            records.append(record)
    return records


def _offline_run(root: Path) -> Path:
    (run,) = sorted(root.rglob("offline-run-*"))
    return run


def finished_records(run: Path, timeout_s: float = 60.0) -> list:
    """The run's records once wandb's service has written its exit record (it flushes after ``finish``)."""
    deadline = time.monotonic() + timeout_s
    while True:
        records = read_records(next(run.glob("run-*.wandb")))
        if any(r.WhichOneof("record_type") == "exit" for r in records) or time.monotonic() > deadline:
            return records
        time.sleep(0.5)


def _config(records) -> dict:
    config = {}
    for r in records:
        updates = r.run.config.update if r.WhichOneof("record_type") == "run" else ()
        updates = r.config.update if r.WhichOneof("record_type") == "config" else updates
        for item in updates:
            config[item.key] = json.loads(item.value_json)
    return config


def test_a_training_run_logs_config_identity_scalars_and_curve(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    cfg = tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 400, "logger.backend": "wandb"})
    SLFTrainer(cfg).train()
    run = _offline_run(tmp_path)
    records = finished_records(run)
    (meta,) = [r.run for r in records if r.WhichOneof("record_type") == "run"][:1]
    assert meta.display_name == "SLF veh2dof/nominal N=20 seed=1"
    assert {"SLF", "veh2dof", "nominal", "N=20", "seed=1"} <= set(meta.tags)
    config = _config(records)
    assert config["network"]["num_cells"] == 16 and config["collector"]["total_frames"] == 400
    scalars = {
        item.key or "/".join(item.nested_key)
        for r in records
        if r.WhichOneof("record_type") == "history"
        for item in r.history.item
    }
    assert {"val/rmse_beta", "val/rmse_yaw_rate"} <= scalars
    tables = list((run / "files" / "media" / "table").glob("learning_curve_*.table.json"))
    assert tables and json.loads(tables[0].read_text())["columns"] == ["frames", "rmse_beta", "rmse_yaw_rate"]


def test_a_report_run_logs_the_results_table_and_figures(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    report = tmp_path / "report"
    report.mkdir()
    results = {
        "profile": "tiny", "system": "veh2dof", "scenario": "nominal", "runs": 2, "steps": 10, "states": ["beta", "r"],
        "filters": {"UKF": {"rmse": [0.1, 0.2], "ratio_to_oracle": [1.1, 1.0], "cost_ms": 0.1, "diverged": 0}},
    }  # fmt: skip
    (report / "results.json").write_text(json.dumps(results))
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2, 2))
    fig.savefig(report / "per_run_rmse_box.png")
    plt.close(fig)
    log_report(report, name="report veh2dof", group="veh2dof-tiny", tags=["tiny"], project="daof", mode="offline")
    run = _offline_run(tmp_path)
    (table,) = (run / "files" / "media" / "table").glob("results_*.table.json")
    content = json.loads(table.read_text())
    assert content["columns"][:3] == ["filter", "rmse_beta", "rmse_r"] and content["data"][0][0] == "UKF"
    assert list((run / "files" / "media" / "images").glob("figures/per_run_rmse_box_*.png"))
    assert not (report / "wandb").exists()  # the report directory holds the report only


def test_the_experiment_switch_logs_every_training_without_making_finished_runs_stale(tmp_path):
    from daof.experiments.experiment import plan_experiment

    def jobs(*extra):
        plan = plan_experiment("veh2dof", ["profile=tiny", f"root={tmp_path}", *extra])
        return next(iter(plan.scenarios.values())).jobs

    plain, logged = jobs(), jobs("logger=wandb")
    job = logged["DAOF-v1"]
    assert {"logger.backend=wandb", "logger.group=veh2dof-tiny", "logger.tags=[tiny]"} <= set(job.overrides)
    finished = plain["DAOF-v1"]
    finished.output_dir.mkdir(parents=True)
    (finished.output_dir / "run_config.json").write_text(json.dumps(finished.requested_config))
    assert job.output_dir == finished.output_dir and job.config_matches()
    with pytest.raises(ValueError, match="logger must be one of"):
        jobs("logger=tensorboard")
