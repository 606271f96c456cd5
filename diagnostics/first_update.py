"""How a trained DAOF-v1 makes its first update, beside a UKF's, on fresh runs of the system.

    .venv/bin/python diagnostics/first_update.py --system veh2dof runs/veh2dof/nominal/daof-v1-N20-s1/best.pt

At step 1 every filter starts from the prior mean, so the update x̂_1 − f(x̂_0, u_0) of the learned
filter and the UKF's can be compared run by run (200 runs, seed 9100). Per state: the std of each
update, the correlation between them, the least-squares slope of the learned update on the UKF's
(1 = the same size; > 1 = overshoot) and the median |a| of the learned unit action (1 = at its bound).
"""

from __future__ import annotations

import argparse

import torch
from daof.envs import make_system

from daof.filters import UKF
from daof.filters.learned import load_filter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--system", default="veh2dof", choices=["veh2dof", "linear"])
    parser.add_argument("--runs", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = make_system(args.system)
    data = system.simulate(args.runs, 1, seed=9100)
    prediction = system.f(system.prior.mean.expand(args.runs, -1), data["prev_control"][:, 0])
    ukf = UKF(system).run(data)[:, 0] - prediction
    names = system.state_names
    print("| filter | state | update std | UKF update std | correlation | slope on UKF | median \\|a\\| |")
    print("|---|---|---|---|---|---|---|")
    for path in args.checkpoints:
        filt = load_filter(path, system, expect={"kind": "DAOF-v1"})
        update = filt.run(data)[:, 0] - prediction
        unit = update / filt.bound_at(1)
        for i, name in enumerate(names):
            corr = torch.corrcoef(torch.stack([update[:, i], ukf[:, i]]))[0, 1].item()
            slope = float((update[:, i] * ukf[:, i]).sum() / ukf[:, i].pow(2).sum())
            print(
                f"| {path} | {name} | {update[:, i].std():.4f} | {ukf[:, i].std():.4f} | {corr:.2f} | {slope:.2f} "
                f"| {unit[:, i].abs().median():.2f} |"
            )


if __name__ == "__main__":
    main()
