"""The Monte Carlo study: one data set, every filter, the protocol's metrics, a report."""

from daof.evaluate.dropout import Dropout, apply_dropout, dropout_mask
from daof.evaluate.metrics import count_diverged, per_run_rmse, pooled_rmse
from daof.evaluate.study import FilterResult, Study, run_study
from daof.evaluate.timing import cost_per_estimate, throughput

__all__ = [
    "Dropout",
    "FilterResult",
    "Study",
    "apply_dropout",
    "count_diverged",
    "cost_per_estimate",
    "dropout_mask",
    "per_run_rmse",
    "pooled_rmse",
    "run_study",
    "throughput",
]
