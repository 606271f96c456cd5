"""DSACTLoss: the surrogate's gradients, the clip, the argmin-mean z′, α₀, bootstrapping, σ̄
checkpointing, a custom action key and the target updates (docs/design.md, "DSAC-T")."""

import math

import pytest
import torch
from daof.losses import DSACTLoss, ForeachSoftUpdate, clip_sampled_target, critic_surrogate
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import SoftUpdate, ValueEstimators

N_OBS, N_ACT, GAMMA = 3, 2, 0.99
RAW_ONE = math.log(math.e - 1.0)  # softplus(RAW_ONE) = 1
RAW_ZERO = -40.0  # softplus(RAW_ZERO) ≈ 4e-18


def make_actor(key="correction"):
    spec = Bounded(-2 * torch.ones(N_ACT), 2 * torch.ones(N_ACT), (N_ACT,))
    net = nn.Sequential(MLP(in_features=N_OBS, out_features=2 * N_ACT, num_cells=[16]), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        out_keys=[key],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
        return_log_prob=True,
    )


def make_mlp_critic(key="correction"):
    net = MLP(in_features=N_OBS + N_ACT, out_features=2, num_cells=[16])
    return TensorDictModule(net, in_keys=["observation", key], out_keys=["state_action_value"])


class ConstCritic(nn.Module):
    """A critic whose (μ, raw) output (per reward term) is one parameter, whatever the input."""

    def __init__(self, terms=1):
        super().__init__()
        self.out = nn.Parameter(torch.zeros(2 * terms))

    def forward(self, obs, act):
        return self.out.expand(*obs.shape[:-1], self.out.numel()) + 0.0 * (
            obs.sum(-1, keepdim=True) + act.sum(-1, keepdim=True)
        )


def make_loss(critic=None, **kwargs):
    critic = critic if critic is not None else make_mlp_critic()
    loss = DSACTLoss(make_actor(), critic, **kwargs)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=GAMMA)
    SoftUpdate(loss, tau=0.005)  # registers the target updater (silences the warning)
    return loss


def const_loss(online, target, **kwargs):
    """A loss with constant critics: ``online``/``target`` are [(μ, raw) per reward term] per critic."""
    critic = ConstCritic(kwargs.get("reward_components", 1))
    loss = make_loss(TensorDictModule(critic, ["observation", "correction"], ["state_action_value"]), **kwargs)
    with torch.no_grad():
        loss.qvalue_network_params["module", "out"].copy_(torch.tensor(online))
        loss.target_qvalue_network_params["module", "out"].copy_(torch.tensor(target))
    return loss


def make_batch(b, reward=None, terminated=None, done=None):
    reward = torch.randn(b, 1) if reward is None else reward.reshape(b, -1)
    terminated = torch.zeros(b, 1, dtype=torch.bool) if terminated is None else terminated.reshape(b, 1)
    done = terminated.clone() if done is None else done.reshape(b, 1)
    return TensorDict(
        {
            "observation": torch.randn(b, N_OBS),
            "correction": torch.rand(b, N_ACT) * 4 - 2,
            "next": {
                "observation": torch.randn(b, N_OBS),
                "reward": reward,
                "done": done,
                "terminated": terminated,
            },
        },
        [b],
    )


def test_surrogate_gradients_equal_closed_forms():
    torch.manual_seed(0)
    b, eps = 64, 0.1
    mu = torch.randn(b, requires_grad=True)
    sigma = (torch.rand(b) + 0.2).requires_grad_()
    y_q, y_b, sigma_bar = torch.randn(b), torch.randn(b), torch.tensor(0.7)
    critic_surrogate(mu, sigma, y_q, y_b, sigma_bar, eps).backward()
    m, s = mu.detach(), sigma.detach()
    scale = (0.7**2 + eps) / b
    torch.testing.assert_close(mu.grad, -scale * (y_q - m) / (s**2 + eps))
    torch.testing.assert_close(sigma.grad, -scale * ((m - y_b) ** 2 - s**2) / (s**3 + eps))


def test_surrogate_with_zero_epsilon_is_the_gaussian_nll_gradient():
    """ε = 0: ∂L/∂μ is the NLL gradient at y_q, ∂L/∂σ the NLL gradient at y_b, times σ̄²/B."""
    torch.manual_seed(1)
    b = 32
    mu = torch.randn(b, requires_grad=True)
    sigma = (torch.rand(b) + 0.5).requires_grad_()
    y_q, y_b = torch.randn(b), torch.randn(b)
    critic_surrogate(mu, sigma, y_q, y_b, torch.tensor(2.0), 0.0).backward()
    mu2, sigma2 = mu.detach().clone().requires_grad_(), sigma.detach().clone().requires_grad_()
    nll_mean_term = ((y_q - mu2) ** 2 / (2 * sigma.detach() ** 2)).sum()
    nll_std_term = ((y_b - mu.detach()) ** 2 / (2 * sigma2**2) + sigma2.log()).sum()
    (nll_mean_term + nll_std_term).backward()
    torch.testing.assert_close(mu.grad, 4.0 / b * mu2.grad)
    torch.testing.assert_close(sigma.grad, 4.0 / b * sigma2.grad)


def test_clip_engages_exactly_beyond_xi_sigma_bar():
    mu, sigma_bar = torch.full((6,), 1.0), torch.tensor(0.5)  # ξσ̄ = 1.5
    y_z = torch.tensor([2.4, 2.5, 2.6, -0.4, -0.5, -0.6])
    y_b = clip_sampled_target(y_z, mu, sigma_bar, xi=3.0)
    torch.testing.assert_close(y_b, torch.tensor([2.4, 2.5, 2.5, -0.4, -0.5, -0.5]))


def test_clip_in_the_loss_is_centred_on_mu_and_sized_by_sigma_bar():
    """Online μ = 1, σ = σ̄ = 1; y_z = y_q = 5 lies 4 > ξσ̄ = 3 away, so the std term sees y_b = 4
    while the mean term still sees y_q = 5."""
    eps = 0.1
    loss = const_loss([[1.0, RAW_ONE]] * 2, [[5.0 / GAMMA, RAW_ZERO]] * 2, alpha_init=1e-9, epsilon=eps)
    batch = make_batch(16, reward=torch.zeros(16))
    loss_q, meta = loss.qvalue_loss(batch)
    loss_q.backward()
    torch.testing.assert_close(meta["sigma_bar"], torch.ones(2, 1))
    grad = loss.qvalue_network_params["module", "out"].grad
    d_sigma_d_raw = torch.sigmoid(torch.tensor(RAW_ONE))
    # (σ̄²+ε)·[−(y_q−μ)/(σ²+ε)] = −4 ;  (σ̄²+ε)·[−((y_b−μ)²−σ²)/(σ³+ε)] = −(9 − 1) = −8
    torch.testing.assert_close(grad[:, 0], torch.full((2,), -4.0), atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(grad[:, 1], torch.full((2,), -8.0) * d_sigma_d_raw, atol=1e-4, rtol=1e-4)


def test_z_prime_comes_from_the_argmin_mean_critic():
    torch.manual_seed(2)
    big = math.log(math.expm1(10.0))  # softplus = 10
    # Critic 0 has the smaller mean and no spread: z′ = μ′, so y_z = y_q exactly.
    loss = const_loss([[0.0, RAW_ONE]] * 2, [[0.0, RAW_ZERO], [1.0, big]])
    y_q, y_z = loss.compute_targets(make_batch(10_000))
    torch.testing.assert_close(y_z, y_q)
    # Critic 1 has the smaller mean and σ′ = 10: z′ − μ′ = 10·clamp(N(0,1), −3, 3).
    loss = const_loss([[0.0, RAW_ONE]] * 2, [[1.0, RAW_ZERO], [0.0, big]])
    y_q, y_z = loss.compute_targets(make_batch(10_000))
    noise = (y_z - y_q) / (GAMMA * 10.0)
    assert noise.abs().max().item() == pytest.approx(3.0, abs=1e-4)  # ~27 draws beyond 3 are clamped
    assert (noise.abs() > 3.0 - 1e-4).sum().item() >= 5
    assert noise.std().item() == pytest.approx(0.986, abs=0.03)  # std of a N(0,1) clamped at ±3


def test_alpha_starts_at_e_and_target_entropy_is_minus_action_dim():
    loss = make_loss()
    assert loss.log_alpha.item() == pytest.approx(1.0)
    out = loss(make_batch(8))
    assert out["alpha"].item() == pytest.approx(math.e, rel=1e-6)
    assert loss.target_entropy == -N_ACT
    # L_α = −log_alpha · mean(log π + H̄): its gradient is −mean(log π) − H̄ = entropy + dim A
    loss.zero_grad()
    out["loss_alpha"].backward()
    assert loss.log_alpha.grad.item() == pytest.approx(out["entropy"].item() + N_ACT, rel=1e-5)


def test_truncation_bootstraps_and_termination_does_not():
    loss = const_loss([[0.0, RAW_ONE]] * 2, [[5.0, RAW_ZERO], [6.0, RAW_ZERO]], alpha_init=1e-9)
    done = torch.tensor([False, True, True])
    terminated = torch.tensor([False, False, True])  # plain, truncated, terminated
    y_q, y_z = loss.compute_targets(make_batch(3, reward=torch.ones(3), terminated=terminated, done=done))
    expected = torch.tensor([[1 + GAMMA * 5.0], [1 + GAMMA * 5.0], [1.0]])
    torch.testing.assert_close(y_q, expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(y_z, expected, atol=1e-5, rtol=0)


def test_sigma_bar_moving_average_and_state_dict_round_trip():
    torch.manual_seed(3)
    loss = make_loss(tau_b=0.1)
    batch = make_batch(32)
    sigmas = []
    for _ in range(3):
        _, meta = loss.qvalue_loss(batch)
        with torch.no_grad():
            sigmas.append(loss._critic_mu_sigma(batch, loss.qvalue_network_params)[1].mean(1))
    # Params do not change between calls, so σ̄ = m, then 0.9m + 0.1m … = m.
    torch.testing.assert_close(loss.sigma_bar, sigmas[0])
    with torch.no_grad():
        loss.sigma_bar.fill_(2.0)
    _, meta = loss.qvalue_loss(batch)
    torch.testing.assert_close(meta["sigma_bar"], 0.9 * 2.0 + 0.1 * sigmas[0])
    # Evaluation mode reads σ̄ but does not move it.
    before = loss.sigma_bar.clone()
    loss.eval()
    loss.qvalue_loss(batch)
    torch.testing.assert_close(loss.sigma_bar, before)
    loss.train()
    # A fresh loss restores σ̄ and its initialised flag, so the next update is a moving average.
    fresh = make_loss(tau_b=0.1)
    assert not fresh.sigma_bar_initialised
    fresh.load_state_dict(loss.state_dict())
    assert bool(fresh.sigma_bar_initialised)
    torch.testing.assert_close(fresh.sigma_bar, before)
    _, meta = fresh.qvalue_loss(batch)
    torch.testing.assert_close(meta["sigma_bar"], 0.9 * before + 0.1 * sigmas[0])


def test_custom_action_key_and_gradient_routing():
    """The actor samples "correction" (no "action" anywhere); the actor loss reaches the actor
    only and the critic loss the critics only."""
    torch.manual_seed(4)
    loss = make_loss()
    assert loss.tensor_keys.action == "correction"
    batch = make_batch(16)
    assert "action" not in batch.keys()
    loss_q, _ = loss.qvalue_loss(batch)
    loss_q.backward()
    assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
    assert all(p.grad.abs().sum() > 0 for p in loss.qvalue_network_params.values(True, True))
    loss.zero_grad()
    loss_a, _ = loss.actor_loss(batch)
    loss_a.backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in loss.qvalue_network_params.values(True, True))
    assert all(p.grad.abs().sum() > 0 for p in loss.actor_network_params.values(True, True))
    out = loss(batch)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert batch["td_error"].shape == (16,)


def test_several_actor_samples_keep_the_gradient_and_cut_its_noise():
    """actor_samples = M averages M draws per state: the same expected actor gradient, ~1/M of its
    variance (over the sampling noise, batch and networks fixed)."""
    torch.manual_seed(0)
    one, many = make_loss(), make_loss(actor_samples=16)
    many.load_state_dict(one.state_dict())
    batch = make_batch(8)

    def grads(loss, seed):
        torch.manual_seed(seed)
        loss.zero_grad()
        value, meta = loss.actor_loss(batch)
        value.backward()
        return torch.cat([p.grad.flatten() for p in loss.actor_network_params.values(True, True)]), meta

    g1 = torch.stack([grads(one, k)[0] for k in range(200)])
    g16 = torch.stack([grads(many, k)[0] for k in range(200)])
    assert grads(many, 0)[1]["log_prob"].shape == (8, 16)
    assert (g16.var(0).sum() / g1.var(0).sum()).item() < 0.15  # 1/16 expected; measured 0.064
    spread = (g1.var(0).sum() / 200).sqrt()  # standard error of g1's mean
    assert (g1.mean(0) - g16.mean(0)).norm() < 4 * spread
    with pytest.raises(ValueError, match="actor_samples"):
        make_loss(actor_samples=0)


def test_soft_update_moves_target_actor_and_target_critics():
    loss = make_loss()
    updater = SoftUpdate(loss, tau=0.005)
    for name in ("actor_network", "qvalue_network"):
        online = getattr(loss, f"{name}_params")
        target = getattr(loss, f"target_{name}_params")
        old_target = target.clone()
        with torch.no_grad():
            online.apply_(lambda p: p.add_(1.0))
        updater.step()
        expected = old_target.apply(lambda t, o: 0.995 * t + 0.005 * o, online.data)
        for key, value in target.items(True, True):
            torch.testing.assert_close(value, expected[key])
            assert not torch.equal(value, old_target[key])


def test_decomposed_critic_per_term_targets_argmin_and_actor_sum():
    """K = 2 reward terms: each term bootstraps on its own argmin-mean target critic, the entropy
    bonus is split evenly, and the actor maximises Σ_k min_i μ_ik."""
    alpha = 0.5
    online = [[1.0, RAW_ONE, 3.0, RAW_ONE], [2.0, RAW_ONE, -1.0, RAW_ONE]]
    target = [[5.0, RAW_ZERO, 0.0, RAW_ZERO], [6.0, RAW_ZERO, -1.0, RAW_ZERO]]
    loss = const_loss(online, target, alpha_init=alpha, reward_components=2)
    batch = make_batch(4, reward=torch.tensor([[1.0, 2.0]]).expand(4, 2))
    y_q, y_z = loss.compute_targets(batch)
    assert y_q.shape == (4, 2)
    # term 0: min(5, 6) = 5 (critic 0); term 1: min(0, −1) = −1 (critic 1); each pays α log π′ / 2
    torch.testing.assert_close(y_z, y_q)  # the argmin critic of each term has σ′ ≈ 0
    bonus = y_q - torch.tensor([1 + GAMMA * 5.0, 2 - GAMMA * 1.0])
    torch.testing.assert_close(bonus[:, 0], bonus[:, 1])  # the same split bonus on both terms
    assert bonus.abs().max() > 0
    # actor: Σ_k min_i μ_ik = min(1, 2) + min(3, −1) = 0, so L_π = mean(α log π)
    torch.manual_seed(1)
    loss_a, meta = loss.actor_loss(batch)
    torch.testing.assert_close(loss_a, (alpha * meta["log_prob"]).mean())
    _, meta_q = loss.qvalue_loss(batch)
    assert meta_q["sigma_bar"].shape == (2, 2)
    with pytest.raises(ValueError, match="reward_components"):
        loss.compute_targets(make_batch(4))  # a scalar reward for a 2-term critic


def test_sigma_bar_of_a_checkpoint_without_reward_terms_loads():
    loss = make_loss()
    state = loss.state_dict()
    state["sigma_bar"] = torch.tensor([0.3, 0.4])  # σ̄ as saved before it had a reward-term dim
    loss.load_state_dict(state)
    torch.testing.assert_close(loss.sigma_bar, torch.tensor([[0.3], [0.4]]))


@pytest.mark.parametrize("terms", [1, 2])
def test_gamma_zero_targets_are_the_reward_without_bootstrapping(terms):
    """γ = 0 skips the target actor and critics; the targets equal the bootstrapped formula's."""
    torch.manual_seed(5)
    critic = ConstCritic(terms)
    loss = make_loss(
        TensorDictModule(critic, ["observation", "correction"], ["state_action_value"]), reward_components=terms
    )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.0)
    batch = make_batch(6, reward=torch.randn(6, terms), terminated=torch.tensor([0, 1, 0, 0, 1, 0]).bool())
    y_q, y_z = loss.compute_targets(batch)
    torch.testing.assert_close(y_q, batch["next", "reward"])
    torch.testing.assert_close(y_z, batch["next", "reward"])
    loss.make_value_estimator(ValueEstimators.TD0, gamma=1e-30)  # the general path, next values × ~0
    slow_q, slow_z = loss.compute_targets(batch)
    torch.testing.assert_close(slow_q, y_q)
    torch.testing.assert_close(slow_z, y_z)


def test_a_list_of_critics_keeps_each_critics_own_parameters():
    """DSACTLoss(actor, [critic_1, critic_2]): the ensemble is those two modules' parameters, targets
    included; one module is expanded and its copies re-sampled (TorchRL), which loses a zeroed row."""
    critics = [make_mlp_critic() for _ in range(2)]
    for critic in critics:
        with torch.no_grad():
            critic.module[-1].weight[0].zero_()
    loss = make_loss(critics, num_qvalue_nets=2)
    for params in (loss.qvalue_network_params, loss.target_qvalue_network_params):
        for i, critic in enumerate(critics):
            for key, value in TensorDict.from_module(critic).flatten_keys().items():
                torch.testing.assert_close(params.flatten_keys()[key][i], value)
    expanded = make_loss(critics[0], num_qvalue_nets=2)
    assert expanded.qvalue_network_params["module", "2", "weight"][:, 0].abs().amax() > 0
    with pytest.raises(ValueError, match="2 critics"):
        make_loss(critics, num_qvalue_nets=3)


def test_foreach_soft_update_gives_soft_updates_numbers_bit_for_bit():
    torch.manual_seed(0)
    a = make_loss()
    b = make_loss()
    b.load_state_dict(a.state_dict())
    slow, fast = SoftUpdate(a, tau=0.005), ForeachSoftUpdate(b, tau=0.005)
    for loss in (a, b):
        with torch.no_grad():
            for p in loss.parameters():
                p.add_(torch.linspace(-1, 1, p.numel()).reshape(p.shape))
    before = {k: v.clone() for k, v in a.state_dict().items()}
    for _ in range(3):
        slow.step()
        fast.step()
    sa, sb = a.state_dict(), b.state_dict()
    moved = [k for k in sa if k.startswith("target_") and not torch.equal(sa[k], before[k])]
    assert len(moved) >= 4  # the actor's and the critics' targets
    for key in sa:
        assert torch.equal(sa[key], sb[key]), key
