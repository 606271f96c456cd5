"""Train DSAC-T (or TorchRL's SAC, ``loss.name=sac``) on Pendulum-v1, one update per env step.

The check of DSAC-T (docs/pendulum.md): a deterministic mean return ≥ −200 over 10 episodes within
15,000 environment steps, level with SAC on the same networks and budget.

    python recipes/pendulum/dsac_t.py env.seed=0                 # DSAC-T
    python recipes/pendulum/dsac_t.py loss.name=sac env.seed=0   # SAC baseline
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger
from utils import evaluate, make_collector, make_env, make_loss, make_optimizers, make_replay_buffer


def update(loss, optimizers, updater, batch, step_actor: bool) -> dict[str, float]:
    """One gradient update: critics always; actor, α and the target networks when ``step_actor``."""
    if step_actor:
        out = loss(batch)
        total = out["loss_qvalue"] + out["loss_actor"] + out["loss_alpha"]
        groups = ("critic", "actor", "alpha")
    else:
        # DSACTLoss.qvalue_loss, or SACLoss's critic loss if SAC is run with a delay
        qvalue_loss = getattr(loss, "qvalue_loss", None) or loss.qvalue_v2_loss
        loss_q, _ = qvalue_loss(batch)
        out, total, groups = {"loss_qvalue": loss_q}, loss_q, ("critic",)
    for group in groups:
        optimizers[group].zero_grad(set_to_none=True)
    total.backward()
    for group in groups:
        optimizers[group].step()
    if step_actor:
        updater.step()
    return {k: v.detach().mean().item() for k, v in out.items()}


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.env.seed)
    logger = None
    if cfg.logger.backend:
        logger = get_logger(
            cfg.logger.backend,
            logger_name=cfg.logger.log_dir,
            experiment_name=cfg.logger.exp_name,
            wandb_kwargs={
                "mode": cfg.logger.wandb_mode,
                "project": cfg.logger.project,
                "config": OmegaConf.to_container(cfg, resolve=True),
            },
        )

    train_env, eval_env = make_env(cfg, cfg.env.seed), make_env(cfg, cfg.env.seed + 10_000)
    loss, updater, actor = make_loss(cfg, train_env)
    optimizers = make_optimizers(cfg, loss)
    collector = make_collector(cfg, train_env, actor)
    buffer = make_replay_buffer(cfg)
    policy_delay = cfg[cfg.loss.name].policy_delay

    start, frames, updates, last_eval, eval_return = time.time(), 0, 0, 0, float("nan")
    pbar = tqdm.tqdm(
        total=cfg.collector.total_frames, desc=f"{cfg.loss.name} seed {cfg.env.seed}", mininterval=cfg.progress_interval
    )
    collector_iter = iter(collector)
    while frames < cfg.collector.total_frames:
        with timeit("collect"):
            data = next(collector_iter)
        with timeit("rb - extend"):
            buffer.extend(data.reshape(-1))
        frames += data.numel()
        pbar.update(data.numel())

        metrics = {}
        if frames >= cfg.collector.init_random_frames:
            for _ in range(int(data.numel() * cfg.collector.utd_ratio)):
                with timeit("rb - sample"):
                    batch = buffer.sample()
                with timeit("update"):
                    metrics = update(loss, optimizers, updater, batch, updates % policy_delay == 0)
                updates += 1
            with timeit("update policy weights"):
                collector.update_policy_weights_()

        episode_end = data["next", "done"]
        if logger is not None and episode_end.any():
            logger.log_scalar("train/episode_return", data["next", "episode_reward"][episode_end].mean().item(), frames)
        if frames - last_eval >= cfg.eval.interval or frames >= cfg.collector.total_frames:
            last_eval = frames
            with timeit("eval"):
                eval_return = evaluate(eval_env, actor, cfg.eval.episodes, cfg.env.max_episode_steps)
            pbar.set_postfix(eval_return=f"{eval_return:.1f}")
            if logger is not None:
                logger.log_scalar("eval/return", eval_return, frames)
                logger.log_scalar("wall_time", time.time() - start, frames)
                for key, value in {**metrics, **timeit.todict(prefix="time")}.items():
                    logger.log_scalar(key if key.startswith("time") else f"train/{key}", value, frames)
            timeit.erase()
    pbar.close()
    collector.shutdown()

    wall = time.time() - start
    print(f"{cfg.loss.name} seed {cfg.env.seed}: final eval return {eval_return:.1f}, wall {wall:.0f}s")
    if logger is not None:
        logger.log_scalar("final/eval_return", eval_return, frames)
        logger.log_scalar("final/wall_time", wall, frames)
    if cfg.checkpoint:
        path = Path(cfg.logger.log_dir) / cfg.logger.exp_name / "checkpoint.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(
            {
                "loss": loss.state_dict(),
                "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                "frames": frames,
                "updates": updates,
            },
            path,
        )


if __name__ == "__main__":
    main()
