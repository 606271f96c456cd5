"""Where a trained DSAC-T filter loses accuracy: its actor, its Polyak-averaged actor, its critics' best action.

    .venv/bin/python diagnostics/actor_vs_critic.py runs/experiment2/paper/nominal/daof-v2-rs-N20

For a run trained with a quadratic critic form (``network.critic_form=quadratic`` or
``reward_quadratic``), whose critics carry their best action m(h) explicitly, it prints the RMSE
against the truth (validation set: 20 runs × 500 steps, seed 9100; ``--runs``/``--seed`` for
others; SI units) of

* the online actor, the filter the run saves (its final weights, from ``checkpoint.pt``);
* the target actor, DSAC-T's Polyak average of the online actor's weights;
* each critic's m(h), read on the windows of the online actor's own closed loop.

At γ = 0 m(h) is the critic's estimate of E[x | h], the estimate the actor is trained to follow:
an actor well behind its critics loses accuracy in its own update, not in the critics' regression.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
from omegaconf import OmegaConf

from daof.train.dsac import DSACTTrainer


def _rmse(estimate: torch.Tensor, truth: torch.Tensor) -> str:
    return "[" + ", ".join(f"{v:.3g}" for v in (estimate - truth).pow(2).mean((0, 1)).sqrt().tolist()) + "]"


def critics_best_actions(trainer: DSACTTrainer, windows: torch.Tensor, steps: torch.Tensor) -> list[torch.Tensor]:
    """m(h) of each critic [runs, T, n] in state units, on windows [runs, T, F] read at steps [runs, T]."""
    loss, actor = trainer.loss, trainer.filter
    critic = loss.qvalue_network.module
    if critic.form == "mlp":
        raise SystemExit("the run's critics are MLPs of (h, a): they have no explicit best action")
    out = []
    for params in loss.qvalue_network_params.unbind(0):
        with params.to_module(loss.qvalue_network), torch.inference_mode():
            best = critic.heads(windows.flatten(0, 1), steps.flatten()[:, None])[2]
        out.append(torch.addcmul(*actor.squash_affine(), best).unflatten(0, windows.shape[:2]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a DSAC-T run directory (run_config.json, checkpoint.pt)")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=9100)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = OmegaConf.create(json.loads((args.run / "run_config.json").read_text()))
    with tempfile.TemporaryDirectory() as scratch:  # the trainer's own files go there: the run is only read
        cfg.output_dir = scratch
        trainer = DSACTTrainer(cfg)
        trainer.resume(args.run / "checkpoint.pt")
    actor, loss = trainer.filter, trainer.loss
    data = trainer.system.simulate(args.runs, 500, args.seed)
    truth = data["state"]
    y, u_prev, u = actor.validate(data)
    with torch.inference_mode():
        steps = list(actor.stream_steps(y, u_prev, u))
    windows = torch.stack([w for w, _, _ in steps], 1)
    online = torch.stack([e for _, _, e in steps], 1)
    print(f"{args.run}: RMSE on {args.runs} runs x 500 steps, seed {args.seed}, SI units")
    print(f"  online actor  {_rmse(online, truth)}")
    with loss.target_actor_network_params.to_module(loss.actor_network), torch.inference_mode():
        print(f"  target actor  {_rmse(actor.run(data), truth)}")
    index = torch.arange(1, windows.shape[1] + 1).expand(windows.shape[:2])
    for i, best in enumerate(critics_best_actions(trainer, windows, index)):
        print(f"  critic {i + 1} m(h) {_rmse(best, truth)}")


if __name__ == "__main__":
    main()
