"""Where a trained DAOF's critic puts the best update at step t, beside its actor's (and a UKF's).

    .venv/bin/python diagnostics/critic_check.py runs/linear_check/paper/nominal/daof-v1-N20 --step 1

The DAOF of a run that acts by updates (DAOF-v1; its last ``checkpoint.pt``: actor, both critics)
meets the step-t states of its own training env (``--resets`` resets of the batched env, then
t − 1 steps of the filter itself). In unit actions a (the update of the prediction is b_t ⊙ a), per state:

- ``c × actor``: the deterministic action tanh(loc) the filter uses, scaled by c (c = 1: as used);
- ``critic argmax``: the argmax of min_i μ_i(h_t, a) on a grid (what the actor climbs, without
  the entropy term; systems of up to three states);
- ``UKF`` (DAOF-v1 at t = 1 only, where every filter starts from the prior and predicts alike):
  the UKF's first update (on the linear system, the Kalman filter's: the optimum).

For each: the mean reward it earns at step t against the true state, beside the critic's mean
value of it, and its least-squares slope on the actor's action (t = 1: on the UKF's; 1 = the same
size, > 1 = overshoot). With γ = 0 the critic's value is the expected reward, so the two columns
should rank the actions alike; where they do not, the critic is what misleads the actor.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from daof.filters import UKF
from daof.train.checkpoint import load_checkpoint
from daof.train.dsac import DSACTTrainer


def load_trainer(run: Path, scratch: Path) -> DSACTTrainer:
    """The run's trainer with every piece of its last checkpoint (it writes nothing into ``run``)."""
    cfg = OmegaConf.create(json.loads((run / "run_config.json").read_text()))
    cfg.output_dir, cfg.resume, cfg.logger.backend = str(scratch), None, ""
    trainer = DSACTTrainer(cfg)
    if not trainer.filter.acts_by_update:
        raise SystemExit(f"{run} is a {trainer.filter.config.kind} run whose action is the estimate, not an update")
    trainer.load_state_dict(load_checkpoint(run / "checkpoint.pt"))
    return trainer


def states_at(trainer: DSACTTrainer, step: int, resets: int) -> TensorDict:
    """Observations at step ``step`` of fresh training episodes, the filter itself run up to there."""
    policy = trainer.filter.filter_module()
    out = []
    for _ in range(resets):
        obs = trainer.env.reset()
        if step > 1:
            obs = trainer.env.rollout(step - 1, policy, auto_reset=False, tensordict=obs)[..., -1]["next"]
        out.append(obs)
    obs = torch.cat(out)
    if not (obs["step"] == step).all():
        raise SystemExit(f"the env is not at step {step} (episodes of {trainer.base_env.max_steps} steps?)")
    return obs


def critic_value(trainer: DSACTTrainer, obs: TensorDict, action: torch.Tensor) -> torch.Tensor:
    """Σ_k min_i μ_ik(h, a), what the actor maximises, for actions [..., B, n] against observations [B]."""
    td = obs.expand(*action.shape[:-1]).clone()
    td.set(trainer.filter.action_key, action)
    mu, _ = trainer.loss._critic_mu_sigma(td, trainer.loss.qvalue_network_params)
    return mu.min(0)[0].sum(-1)


def grid_argmax(trainer: DSACTTrainer, obs: TensorDict, points: int) -> torch.Tensor:
    """The critic's best unit action per observation on a points^n grid over [−1, 1]^n."""
    n = trainer.system.state_dim
    axis = torch.linspace(-1.0, 1.0, points)
    grid = torch.cartesian_prod(*[axis] * n).view(-1, 1, n)  # [G, 1, n]
    best = []
    for part in obs.split(max(1, 2**20 // len(grid))):  # chunks of ~1M critic evaluations
        values = critic_value(trainer, part, grid.expand(-1, part.shape[0], -1))  # [G, chunk]
        best.append(grid[values.argmax(0), 0])
    return torch.cat(best)


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a DAOF run directory (run_config.json, checkpoint.pt)")
    parser.add_argument("--step", type=int, default=1, help="the step t of the episodes to look at")
    parser.add_argument("--resets", type=int, default=8)
    parser.add_argument("--grid", type=int, default=81)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as scratch:
        trainer = load_trainer(args.run, Path(scratch))
    s, filt = trainer.system, trainer.filter
    obs = states_at(trainer, args.step, args.resets)
    # what a unit action is added to: the prediction (+ the reference gain's update, where used)
    prediction = filt.predict(obs["prev_estimate"], obs["prev_control"])
    reference = filt.reference_update(obs[filt.input_key], prediction, args.step)
    if reference is not None:
        prediction = prediction + reference
    bound = filt.bound_at(args.step)
    actor = filt.estimate(obs[filt.input_key], obs["prev_estimate"], obs["prev_control"], obs["step"]) - prediction
    actor = actor / bound
    actions = {f"{c:g} × actor": c * actor for c in (0.0, 0.5, 0.75, 1.0, 1.25)}
    if s.state_dim <= 3:  # a grid over more states is too large to search
        actions["critic argmax"] = grid_argmax(trainer, obs, args.grid)
    reference = "actor"
    if args.step == 1 and filt.config.kind == "DAOF-v1":
        data = TensorDict({k: obs[k].unsqueeze(1) for k in ("measurement", "control", "prev_control")}, [len(obs), 1])
        actions["UKF"] = (UKF(s).run(data)[:, 0] - prediction) / bound
        reference = "UKF"
    ref = actions["UKF"] if reference == "UKF" else actor
    weights = trainer.reward_weights
    weights = weights[min(args.step, len(weights)) - 1] if weights.ndim == 2 else weights  # W_t
    print(f"{args.run}: {len(obs)} states at step {args.step}, {trainer.frames} frames trained; b_t = {bound.tolist()}")
    names = s.state_names
    slope_columns = " | ".join(f"slope on {reference} ({n})" for n in names)
    print(f"| action | {slope_columns} | mean reward | critic's value |")
    print("|---|" + "---|" * s.state_dim + "---|---|")
    for name, a in actions.items():
        a = a.clamp(-1, 1)
        slopes = [float((a[:, i] * ref[:, i]).sum() / ref[:, i].pow(2).sum()) for i in range(s.state_dim)]
        reward = -((prediction + bound * a - obs["true_state"]).pow(2) * weights).sum(-1).mean()
        value = critic_value(trainer, obs, a).mean()
        print(f"| {name} | " + " | ".join(f"{v:.2f}" for v in slopes) + f" | {reward:.4f} | {value:.4f} |")


if __name__ == "__main__":
    main()
