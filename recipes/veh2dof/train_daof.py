"""Train DAOF-v1 or DAOF-v2 with DSAC-T (the recipe of every system; configs pick the system).

python recipes/veh2dof/train_daof.py version=v1 window=20            # Experiment I
python recipes/veh2dof/train_daof.py resume=runs/.../checkpoint.pt     # continue an interrupted run
python recipes/veh2dof/train_daof.py --config-path $PWD/recipes/veh14dof --config-name config   # another system
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # imported here so that `--cfg job` (how an experiment checks a finished run) stays fast
    from daof.train.dsac import DSACTTrainer

    trainer = DSACTTrainer(cfg)
    if cfg.resume:
        trainer.resume(cfg.resume)
    summary = trainer.train()
    best = summary["best"].get("record", {})
    rmse = ", ".join(f"{k[5:]}={v:.4g}" for k, v in best.items() if k.startswith("rmse_"))
    print(f"{summary['kind']}: best validation RMSE {rmse} at {summary['best']['frames']} frames")
    print(f"filter: {cfg.output_dir}/best.pt  wall: {summary['wall_s']} s")


if __name__ == "__main__":
    main()
