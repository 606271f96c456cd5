"""Train the supervised-learning filter (SLF) baseline by regression on the true state.

python recipes/veh2dof/train_slf.py window=20
python recipes/veh2dof/train_slf.py resume=runs/.../checkpoint.pt
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from daof.train.supervised import SLFTrainer


@hydra.main(config_path=".", config_name="slf", version_base="1.3")
def main(cfg: DictConfig) -> None:
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
