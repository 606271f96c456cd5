"""DSAC-T's views of a learned filter's network: the stochastic actor and what a collector runs.

Training only: the deployed filter is ``filter.filter_module()`` (the squashed loc). Both views
wrap the filter's own ``policy`` module, so they train (and, swapped in, validate) its weights.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor, TanhNormal

from daof.envs.filtering_env import FEEDBACK_KEY
from daof.filters.learned import LearnedFilter

__all__ = ["FEEDBACKS", "exploration_policy", "stochastic_actor"]

#: what a DSAC-T collector feeds back into h_{t+1}: the sampled action or the deterministic estimate
FEEDBACKS = ("sample", "mean")


def stochastic_actor(filter: LearnedFilter) -> ProbabilisticActor:
    """TanhNormal actor over ``filter.action_key`` (the estimate, or an update filter's unit update) for DSAC-T.

    The loc is not squashed (``tanh_loc=False``); its bounds are the filter's action range.
    """
    module = TensorDictModule(filter.policy, in_keys=filter.policy_in_keys, out_keys=["loc", "scale"])
    spec = Bounded(filter.low, filter.high, shape=filter.low.shape, device=filter.low.device)
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[filter.action_key],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": filter.low, "high": filter.high, "tanh_loc": False},
        return_log_prob=False,
    )


def exploration_policy(filter: LearnedFilter, feedback: str = "sample") -> TensorDictSequential:
    """What a collector runs: sample from π and, for a filter that acts by updates, add the prediction.

    ``feedback="mean"`` also writes ``FEEDBACK_KEY``: the deterministic estimate (the squashed loc,
    through the same prediction), which the env then feeds back instead of the sampled one.
    """
    if feedback not in FEEDBACKS:
        raise ValueError(f"feedback must be one of {FEEDBACKS}, got {feedback!r}")

    def estimate_of(key: str, out_key: str) -> list[TensorDictModule]:
        """The estimate of an update ``key``: the filter's prediction plus it (nothing for an estimate)."""
        if not filter.acts_by_update:
            return []
        in_keys = [key, "prev_estimate", "prev_control", "step", filter.input_key]
        return [TensorDictModule(filter.update_estimate, in_keys=in_keys, out_keys=[out_key])]

    modules = [stochastic_actor(filter), *estimate_of("correction", "action")]
    if feedback == "mean":
        modules.append(TensorDictModule(filter.squash, in_keys=["loc"], out_keys=[FEEDBACK_KEY]))
        modules += estimate_of(FEEDBACK_KEY, FEEDBACK_KEY)
    return TensorDictSequential(*modules)
