"""The study's reference is checked: a proposal PF, the convergence check and the reference's fallback."""

from __future__ import annotations

import math

import torch
from daof.envs.noise import GaussianNoise
from daof.envs.system import StochasticSystem


class BearingTracking(StochasticSystem):
    """A constant-velocity target in the plane seen by two precise bearing sensors (bearing-only tracking).

    x = [px, py, vx, vy]; white-noise acceleration of intensity ``q`` (m²/s³) over ``dt``; the sensors at
    (0, 0) and (100, 0) m measure atan2(py − s_y, px − s_x) with N(0, ``bearing_std``²) noise.
    """

    name = "bearing"
    dt = 1.0
    state_names = ("px", "py", "vx", "vy")
    state_units = ("m", "m", "m/s", "m/s")
    measurement_names = ("bearing_1", "bearing_2")
    measurement_units = ("rad", "rad")

    def __init__(self, q: float = 0.02, bearing_std: float = 0.0005, prior_std=(5.0, 5.0, 0.5, 0.5)):
        dt = self.dt
        block = q * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        cov = torch.zeros(4, 4)
        for i in (0, 1):  # per axis: position i and velocity i + 2
            idx = torch.tensor([i, i + 2])
            cov[idx[:, None], idx] = block
        self.process_noise = GaussianNoise(torch.zeros(4), cov)
        self.measurement_noise = GaussianNoise.diagonal([0.0, 0.0], [bearing_std, bearing_std])
        self.prior = GaussianNoise.diagonal([50.0, 100.0, 0.0, 0.0], prior_std)
        self.sensors = torch.tensor([[0.0, 0.0], [100.0, 0.0]])
        self.state_low = torch.tensor([-100.0, -100.0, -20.0, -20.0])
        self.state_high = torch.tensor([200.0, 200.0, 20.0, 20.0])
        self.error_scale = torch.tensor([1.0, 1.0, 0.5, 0.5])

    def f(self, x, u):
        return torch.cat([x[..., :2] + self.dt * x[..., 2:], x[..., 2:]], -1)

    def g(self, x, u):
        d = x[..., None, :2] - self.sensors.to(x.device, x.dtype)
        return torch.atan2(d[..., 1], d[..., 0])


def _rms(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Root-mean-square difference per state over runs and steps."""
    return ((a.double() - b.double()) ** 2).mean((0, 1)).sqrt()


def _precise_linear():
    """The linear oscillator with a position sensor 50x more precise than its default (std 0.002 m, below the
    position's process noise 0.01 m): the measurement, not the dynamics, places the particles."""
    from daof.envs import make_system

    return make_system("linear", measurement_std=0.002)


def test_the_proposal_pf_is_the_posterior_mean_on_a_linear_gaussian_system():
    """On a linear-Gaussian system the Kalman filter is the exact posterior mean: the proposal PF agrees with it.

    Tolerance: a PF's estimate differs from the posterior mean by Monte Carlo error of about one posterior
    std (≈ the KF's RMSE) / √ESS; measured 0.042 / 0.048 of the KF's RMSE with 1,000 particles (0.077 / 0.091
    with 300: the 1/√N of Monte Carlo error), so 0.15 leaves a 3x margin. Weights without the
    p(x_t | x_{t-1}) / q correction count the measurement twice and miss it (measured 0.10 / 1.19); a
    bootstrap PF with 1,000 particles is 0.17 / 0.54 off.
    """
    from daof.filters import KalmanFilter, ProposalParticleFilter

    system = _precise_linear()
    data = system.simulate(5, 100, 3)
    kf = KalmanFilter(system).run(data)
    pf = ProposalParticleFilter(system, 1000, seed=1)
    gap = _rms(pf.run(data), kf) / _rms(kf, data["state"])
    assert (gap < 0.15).all(), gap
    assert pf.stats["prior_proposals"] == 0 and pf.stats["diverged"] == 0


def test_the_proposal_pf_agrees_with_the_bootstrap_pf_with_non_gaussian_noise(veh):
    """veh2dof nominal (Gaussian-mixture process noise, Laplace measurement noise): both PFs estimate the same
    posterior mean, the proposal PF from a Gaussian proposal with the true densities in its weights.

    Tolerance: both carry Monte Carlo error (≈ posterior std / √ESS, the bootstrap with 5,000 particles, the
    proposal PF with 1,000); their gap measured 0.086 / 0.093 of the bootstrap's RMSE (two bootstrap seeds:
    0.025 / 0.035), so 0.15.
    """
    from daof.filters import ParticleFilter, ProposalParticleFilter

    data = veh.simulate(3, 100, 5)
    bootstrap = ParticleFilter(veh, 5000, seed=1).run(data)
    proposal = ProposalParticleFilter(veh, 1000, seed=1).run(data)
    gap = _rms(proposal, bootstrap) / _rms(bootstrap, data["state"])
    assert (gap < 0.15).all(), gap


def test_the_proposal_pf_refuses_a_noise_without_a_density(lin):
    """A noise with no density (here: one that only samples) cannot weight particles: one clear line."""
    import copy

    import pytest
    from daof.envs.noise import Noise

    from daof.filters import ProposalParticleFilter

    class SampleOnly(Noise):
        dim = 2
        mean = torch.zeros(2)
        covariance = torch.eye(2)

    system = copy.deepcopy(lin)
    system.process_noise = SampleOnly()
    with pytest.raises(ValueError, match="process noise of linear \\(SampleOnly\\) has no density"):
        ProposalParticleFilter(system, 10)

    class Flat(SampleOnly):  # a density, but no spread on one axis: no Gaussian proposal
        covariance = torch.diag(torch.tensor([1.0, 0.0]))

        def log_prob(self, value):
            return value.new_zeros(value.shape[:-1])

    system.process_noise = Flat()
    with pytest.raises(ValueError, match="process noise covariance of linear is not positive definite"):
        ProposalParticleFilter(system, 10)


def test_the_proposal_pf_weights_only_the_present_channels():
    """A NaN channel takes no part: a step with both bearings missing leaves the estimates finite and moves
    them only by the dynamics; one missing bearing still updates from the other."""
    from daof.filters import ProposalParticleFilter

    system = BearingTracking()
    data = system.simulate(2, 10, 1)
    gappy = data.clone()
    gappy["measurement"][:, 4] = math.nan  # both channels at step 5
    gappy["measurement"][:, 6, 0] = math.nan  # one channel at step 7
    pf = ProposalParticleFilter(system, 200, seed=1)
    estimates = pf.run(gappy)
    assert torch.isfinite(estimates).all() and pf.stats["diverged"] == 0
    full = ProposalParticleFilter(system, 200, seed=1).run(data)
    assert torch.equal(estimates[:, :4], full[:, :4])  # identical before the first gap
    assert not torch.equal(estimates[:, 4], full[:, 4])


def _study(system, filters: dict, runs: int, steps: int):
    from daof.evaluate import run_study

    return run_study(system, filters, runs, steps, 20261122, measure_cost=False, log=lambda _: None, reference=None)


def test_the_bootstrap_pf_fails_its_check_and_no_converged_reference_means_the_best_filter(tmp_path):
    """On the bearing system a bootstrap PF with 300 particles moves its RMSE by far more than 1 % when doubled;
    with no other candidate the ratios are to the best filter (lowest mean normalised RMSE), never to it."""
    from daof.experiments.reference import best_filter, choose_reference
    from daof.filters import UKF, ParticleFilter

    system = BearingTracking()
    filters = {"UKF": UKF(system), "PF": ParticleFilter(system, 300, seed=1)}
    study = _study(system, filters, 10, 30)
    choice = choose_reference(study, ["PF"], filters, set(), limit_percent=1.0, seed=3, cache_dir=tmp_path, log=print)
    (pf,) = choice.candidates
    assert not pf.converged and max(pf.change_percent) > 10  # measured 27-61 % per state
    assert choice.how == "best" and choice.name == best_filter(study, exclude={"PF"}) == "UKF"
    assert study.reference == "UKF" and study.results["UKF"].ratio_to_oracle == [1.0] * 4
    assert study.results["PF"].ratio_to_oracle[0] > 2  # its own error, now measured against the UKF
    assert "No reference candidate converged (PF): the ratios are to the best filter of this study, UKF" in "\n".join(
        choice.lines()
    )
    assert study.reference_check["how"] == "best"


def test_an_unconverged_reference_falls_back_to_the_next_candidate(tmp_path):
    """A bootstrap PF with 300 particles fails its check on the precise linear system; the next candidate, a
    proposal PF not yet a row of the study (a fallback), runs, passes the check and becomes the reference."""
    from daof.experiments.reference import choose_reference
    from daof.filters import ParticleFilter, ProposalParticleFilter

    lin = _precise_linear()
    rows = {"PF": ParticleFilter(lin, 300, seed=1)}
    study = _study(lin, rows, 10, 100)
    candidates = {**rows, "PF-proposal": ProposalParticleFilter(lin, 1000, seed=5)}
    choice = choose_reference(
        study, ["PF", "PF-proposal"], candidates, set(), limit_percent=1.0, seed=3, cache_dir=tmp_path, log=print
    )
    boot, proposal = choice.candidates
    assert not boot.converged and max(boot.change_percent) >= 1.0
    assert proposal.converged and max(proposal.change_percent) < 1.0
    assert (choice.name, choice.how) == ("PF-proposal", "converged") and study.reference == "PF-proposal"
    assert list(study.results) == ["PF", "PF-proposal"]  # the fallback joined the study
    assert study.results["PF-proposal"].ratio_to_oracle == [1.0, 1.0]
    lines = choice.lines()
    assert lines[0].startswith("PF (300 particles), convergence check: with 600 particles (seed 3)")
    assert lines[1].startswith("Reference: PF-proposal (1000 particles)") and lines[1].endswith(": converged.")


def test_an_exact_reference_is_taken_without_a_check(tmp_path, lin):
    """The Kalman filter on a linear-Gaussian system is marked exact: chosen first, nothing doubled."""
    from daof.experiments.reference import choose_reference
    from daof.filters import KalmanFilter, ParticleFilter

    filters = {"KF": KalmanFilter(lin), "PF": ParticleFilter(lin, 30, seed=1)}
    study = _study(lin, filters, 2, 20)
    choice = choose_reference(study, ["KF", "PF"], filters, {"KF"}, limit_percent=1.0, seed=3, cache_dir=tmp_path)
    assert (choice.name, choice.how) == ("KF", "exact") and [c.name for c in choice.candidates] == ["KF"]
    assert not list(tmp_path.iterdir())  # no doubled run
    assert "exact" in choice.lines()[0]


def test_a_best_filter_reference_stays_a_practical_winner(tmp_path):
    """When no candidate converged, the reference is a practical filter (the best): the scenario report still
    ranks it among the practical filters and leaves out only the candidates the check tried."""
    from daof.evaluate.report import scenario_winners
    from daof.experiments.reference import choose_reference
    from daof.filters import UKF, ParticleFilter

    system = BearingTracking()
    filters = {"UKF": UKF(system), "PF": ParticleFilter(system, 300, seed=1)}
    study = _study(system, filters, 4, 20)
    choose_reference(study, ["PF"], filters, set(), limit_percent=1.0, seed=3, cache_dir=tmp_path)
    assert study.reference == "UKF"
    assert scenario_winners(study)["overall_without_oracle"] == "UKF"  # PF, the failed candidate, left out
