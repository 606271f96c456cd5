"""Train the supervised-learning filter (SLF) baseline by regression on the true state.

python recipes/veh2dof/train_slf.py window=20
python recipes/veh2dof/train_slf.py resume=runs/.../checkpoint.pt
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig


@hydra.main(config_path=".", config_name="slf", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # imported here so that `--cfg job` (how an experiment checks a finished run) stays fast
    from daof.train.supervised import SLFTrainer

    trainer = SLFTrainer(cfg)
    if cfg.resume:
        trainer.resume(cfg.resume)
    summary = trainer.train()
    best = summary["best"].get("record", {})
    rmse = ", ".join(f"{k[5:]}={v:.4g}" for k, v in best.items() if k.startswith("rmse_"))
    print(f"SLF: best validation RMSE {rmse} at {summary['best']['frames']} samples")
    print(f"filter: {cfg.output_dir}/best.pt  wall: {summary['wall_s']} s")


if __name__ == "__main__":
    main()
