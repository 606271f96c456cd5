"""Train one learned filter: ``python -m daof.train [filter=daof_v1|...|kalmannet] [system=...] [key=value ...]``.

    python -m daof.train                                   # DAOF-v1 on veh2dof, N = 20
    python -m daof.train filter=daof_v2 system=linear      # DAOF-v2 on the linear check
    python -m daof.train filter=slf system=veh14dof window=10
    python -m daof.train resume=runs/veh2dof/nominal/daof-v1-N20-s1/checkpoint.pt
    python -m daof.train filter=slf --cfg                  # print the resolved config, train nothing

The configuration is ``daof/conf/train.yaml`` over the typed defaults of ``daof.train.config``.
A bad override or an impossible config ends the command with one line, before any work.
"""

from __future__ import annotations

import sys

from omegaconf import DictConfig, OmegaConf

from daof.train.config import FILTER_KINDS, compose_config

__all__ = ["main", "train"]


def train(cfg: DictConfig) -> dict:
    """Train (or resume) the filter ``cfg`` names (a ``compose_config`` result); returns its summary."""
    if FILTER_KINDS[cfg.kind] == "dsac":
        from daof.train.dsac import DSACTTrainer as Trainer
    elif FILTER_KINDS[cfg.kind] == "kalmannet":
        from daof.train.kalmannet import KalmanNetTrainer as Trainer
    else:
        from daof.train.supervised import SLFTrainer as Trainer
    trainer = Trainer(cfg)
    if cfg.resume:
        trainer.resume(cfg.resume)
    return trainer.train()


def main(argv: list[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    show = "--cfg" in args
    try:
        cfg = compose_config([a for a in args if a != "--cfg"])
        if show:
            print(OmegaConf.to_yaml(cfg), end="")
            return
        summary = train(cfg)
    except (ValueError, OSError) as error:  # OSError: a disk that fills or turns read-only mid-run
        sys.exit(f"error: {error}")
    best = summary["best"].get("record", {})
    rmse = ", ".join(f"{k[5:]}={v:.4g}" for k, v in best.items() if k.startswith("rmse_"))
    print(f"{summary['kind']}: best validation RMSE {rmse} at {summary['best']['frames']} frames")
    print(f"filter: {cfg.output_dir}/best.pt  wall: {summary['wall_s']} s")


if __name__ == "__main__":
    main()
