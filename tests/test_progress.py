"""Progress of long work: a training's progress file and the experiment's line per running job."""

import json

from test_training import tiny_cfg

from daof.experiments.jobs import TrainingJob, progress_line
from daof.train.supervised import SLFTrainer


def test_a_training_leaves_its_progress_and_the_experiment_reads_it(tmp_path):
    SLFTrainer(tiny_cfg("slf.yaml", tmp_path, **{"collector.total_frames": 400})).train()
    progress = json.loads((tmp_path / "progress.json").read_text())
    assert progress["frames"] == progress["total"] == 400
    assert set(progress["rmse"]) == {"beta", "yaw_rate"}
    line = progress_line(TrainingJob("SLF", tmp_path, 400))
    assert line.startswith("400/400 frames (100 %)") and "validation RMSE beta" in line


def test_a_running_job_shows_its_eta(tmp_path):
    rmse = {"beta": 0.0105, "yaw_rate": 0.0254}
    (tmp_path / "progress.json").write_text(
        json.dumps({"frames": 400_000, "total": 1_600_000, "wall_s": 120.0, "rmse": rmse})
    )
    line = progress_line(TrainingJob("DAOF-v1", tmp_path, 1_600_000))
    assert line == "400k/1.6M frames (25 %), 2.0 min, ETA 6.0 min, validation RMSE beta 0.0105 yaw_rate 0.0254"
    assert progress_line(TrainingJob("DAOF-v2", tmp_path / "none", 10)) == "starting"


def test_every_filter_reports_each_run_step_to_the_study_bar(lin):
    from daof.filters import EKF, UKF, KalmanFilter, ParticleFilter, StationaryKalmanFilter
    from daof.filters.learned import FilterConfig, LearnedFilter

    data = lin.simulate(3, 7, seed=0)
    learned = LearnedFilter(FilterConfig(kind="DAOF-v2", system="linear", num_cells=8, window=3), lin)
    kalmannet = LearnedFilter(FilterConfig(kind="KalmanNet", system="linear"), lin)
    for filt in (
        EKF(lin),
        UKF(lin),
        KalmanFilter(lin),
        StationaryKalmanFilter(lin),
        ParticleFilter(lin, 50),
        learned,
        kalmannet,
    ):
        done = []
        filt.progress = done.append
        filt.run(data)
        filt.progress = None
        assert sum(done) == 3 * 7, type(filt).__name__
