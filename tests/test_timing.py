"""daof.evaluate.timing: the cost per estimate and the throughput measure what they claim."""

import time

import pytest
import torch
from tensordict import TensorDict

from daof.evaluate.timing import cost_per_estimate, threads, throughput


class SleepyFilter:
    """Stands in for a filter: ``seconds_per_step`` of sleep per step; records every call."""

    def __init__(self, seconds_per_step: float):
        self.seconds_per_step = seconds_per_step
        self.calls: list[tuple[int, int, int]] = []  # (batch, steps, torch threads)

    def run_streaming(self, data):
        self.calls.append((data.shape[0], data.shape[1], torch.get_num_threads()))
        time.sleep(self.seconds_per_step * data.shape[1])
        return torch.zeros(*data.shape, 2)

    def run(self, data):
        return self.run_streaming(data) + 1.0


def _data(runs=3, steps=20):
    return TensorDict({"measurement": torch.zeros(runs, steps, 2)}, batch_size=[runs, steps])


def test_a_slower_filter_measures_slower_per_estimate():
    data = _data()
    fast = cost_per_estimate(SleepyFilter(2e-4), data, min_seconds=0.1)
    slow = cost_per_estimate(SleepyFilter(2e-3), data, min_seconds=0.1)
    # milliseconds per step, never below the sleep
    assert fast >= 0.2 and slow >= 2.0
    assert slow > 4 * fast


def test_the_cost_is_measured_at_batch_one_after_a_warm_up():
    filt = SleepyFilter(1e-4)
    cost_per_estimate(filt, _data(runs=5, steps=80), warmup_steps=30, min_seconds=0.05)
    batches, steps, _ = zip(*filt.calls)
    assert set(batches) == {1}
    assert steps[0] == 30 and set(steps[1:]) == {80}  # the warm-up, then whole runs
    assert len(filt.calls) >= 3
    short = SleepyFilter(1e-4)
    cost_per_estimate(short, _data(steps=10), warmup_steps=50, min_seconds=0.01)
    assert short.calls[0][1] == 10  # a warm-up never asks for more steps than there are


def test_the_thread_count_holds_while_timing_and_is_restored_afterwards():
    torch.set_num_threads(1)
    filt = SleepyFilter(1e-4)
    cost_per_estimate(filt, _data(), min_seconds=0.02, num_threads=2)
    assert {n for _, _, n in filt.calls[1:]} == {2}  # every timed pass
    assert torch.get_num_threads() == 1
    # by default: the count in force, e.g. the study's ``threads(timing_threads)``
    filt = SleepyFilter(1e-4)
    with threads(2):
        cost_per_estimate(filt, _data(), min_seconds=0.02)
        assert torch.get_num_threads() == 2
    assert {n for _, _, n in filt.calls} == {2}
    assert torch.get_num_threads() == 1


def test_threads_restores_the_count_when_the_body_fails():
    torch.set_num_threads(1)
    with pytest.raises(RuntimeError, match="boom"), threads(2):
        assert torch.get_num_threads() == 2
        raise RuntimeError("boom")
    assert torch.get_num_threads() == 1


def test_throughput_returns_the_runs_estimates_and_its_wall_time():
    data = _data(runs=4, steps=25)
    filt = SleepyFilter(4e-4)
    rate, estimates, std, wall = throughput(filt, data)
    assert filt.calls == [(4, 25, torch.get_num_threads())]  # one run of the whole batch
    assert torch.equal(estimates, torch.ones(4, 25, 2)) and std is None
    assert throughput(filt, data, with_std=True)[2] is None  # a filter without a std: the same shape
    assert wall >= 25 * 4e-4
    assert rate == pytest.approx(data.numel() / wall)


def test_cost_of_a_real_filter(lin):
    from daof.filters import StationaryKalmanFilter

    data = lin.simulate(2, 40, seed=0)
    cost = cost_per_estimate(StationaryKalmanFilter(lin), data, min_seconds=0.05)
    assert 0 < cost < 50  # ms: a 2-state stationary Kalman update
