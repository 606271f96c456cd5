"""RecordedSystem: env episodes replayed from a recorded bank, ``simulate`` memoised on disk."""

import pytest
import torch
from daof.envs import make_env, make_system
from daof.envs.filtering_env import FilteringEnv
from daof.envs.recorded import RecordedSystem, cached_simulate
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs


@pytest.fixture
def linear():
    return make_system("linear")


def test_bank_is_the_base_simulation(linear, tmp_path):
    """The bank is simulate(runs, steps + 1, seed) of the base system, bit for bit."""
    rec = RecordedSystem(linear, runs=5, steps=7, seed=3, cache_dir=tmp_path)
    expected = linear.simulate(5, 8, 3)
    assert rec.bank.batch_size == torch.Size([5, 8])
    for key in ("state", "measurement", "control", "prev_control"):
        torch.testing.assert_close(rec.bank[key], expected[key], rtol=0, atol=0)


def test_env_replays_bank_episodes_step_by_step(linear):
    """Every env row serves one bank episode in order: truth, measurement and controls of steps 1..T."""
    rec = RecordedSystem(linear, runs=4, steps=6, seed=0)
    env = FilteringEnv(rec, batch_size=3, max_steps=6, seed=11)
    td = env.rollout(6, break_when_any_done=False)
    bank = rec.bank
    episodes = env._sim["episode"]
    for row, ep in enumerate(episodes.tolist()):
        # the reset observation is step 1, then the "next" observations are steps 2..7
        torch.testing.assert_close(td["true_state"][row], bank["state"][ep, :6], rtol=0, atol=0)
        torch.testing.assert_close(td["next", "measurement"][row], bank["measurement"][ep, 1:7], rtol=0, atol=0)
        torch.testing.assert_close(td["control"][row], bank["control"][ep, :6], rtol=0, atol=0)
        torch.testing.assert_close(td["prev_control"][row, 0], bank["prev_control"][ep, 0], rtol=0, atol=0)
    assert td["next", "truncated"][:, -1].all() and not td["next", "truncated"][:, :-1].any()
    # the env's generator shuffles the deck: the same seed deals the same episodes (the deck is the
    # system's state, so a second env gets a system of its own)
    again = FilteringEnv(RecordedSystem(linear, runs=4, steps=6, seed=0), batch_size=3, max_steps=6, seed=11)
    again.reset()
    assert torch.equal(again._sim["episode"], episodes)


def test_rewards_score_the_recorded_truth(linear):
    """Reward = −‖x_t − x̂_t‖²_W on the replayed truth (an estimate of 0 scores the state itself)."""
    rec = RecordedSystem(linear, runs=2, steps=3, seed=1)
    env = FilteringEnv(rec, batch_size=2, max_steps=3, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(2, rec.state_dim)
    out = env.step(td)
    expected = -(td["true_state"].pow(2) * env.reward_weights).sum(-1, keepdim=True)
    torch.testing.assert_close(out["next", "reward"], expected)


def test_partial_reset_draws_a_new_episode_for_the_reset_rows_only(linear):
    rec = RecordedSystem(linear, runs=50, steps=4, seed=2)
    env = FilteringEnv(rec, batch_size=4, max_steps=4, seed=5)
    td = env.reset()
    td["action"] = torch.zeros(4, rec.state_dim)
    env.step(td)
    before = env._sim.clone()
    mask = torch.tensor([True, False, True, False])
    env.reset(TensorDict({"_reset": mask.unsqueeze(-1)}, batch_size=[4]))
    assert torch.equal(env._sim["t"][~mask], before["t"][~mask])
    assert torch.equal(env._sim["episode"][~mask], before["episode"][~mask])
    assert (env._sim["t"][mask] == 1).all()


def test_episodes_are_dealt_without_replacement(linear):
    """Every bank episode is served once per pass, in a fresh shuffle each pass, across resets."""
    rec = RecordedSystem(linear, runs=10, steps=2, seed=0)
    env = FilteringEnv(rec, batch_size=4, max_steps=2, seed=3)
    dealt = []
    for _ in range(5):  # 20 episodes: two passes over the bank, the second one straddling resets
        env.reset()
        dealt.append(env._sim["episode"].clone())
    dealt = torch.cat(dealt)
    assert sorted(dealt[:10].tolist()) == list(range(10)) and sorted(dealt[10:].tolist()) == list(range(10))
    assert not torch.equal(dealt[:10], dealt[10:])


def test_the_deck_round_trips_through_state_dict(linear):
    """A system restored from ``state_dict`` deals what the original deals next."""
    rec = RecordedSystem(linear, runs=7, steps=2, seed=0)
    gen = torch.Generator().manual_seed(1)
    rec.deal(3, gen)
    saved, gen_state = rec.state_dict(), gen.get_state()
    expected = rec.deal(9, gen)
    other = RecordedSystem(linear, runs=7, steps=2, seed=0)
    other.load_state_dict(saved)
    gen.set_state(gen_state)
    assert torch.equal(other.deal(9, gen), expected)


def test_find_recorded_sees_through_wrappers(linear):
    from daof.envs.gaps import GappySystem
    from daof.envs.recorded import find_recorded

    rec = RecordedSystem(linear, runs=3, steps=4, seed=0)
    assert find_recorded(GappySystem(rec, 0.1, 0.0, 4)) is rec
    assert find_recorded(rec) is rec and find_recorded(linear) is None


def test_longer_episode_than_the_bank_is_an_error(linear):
    rec = RecordedSystem(linear, runs=2, steps=3, seed=0)
    env = FilteringEnv(rec, batch_size=2, max_steps=5, seed=0)
    with pytest.raises(ValueError, match="episodes of up to 3 steps"):
        env.rollout(5, break_when_any_done=False)


def test_simulate_is_memoised_on_disk(linear, tmp_path, monkeypatch):
    first = cached_simulate(linear, 3, 5, 42, tmp_path)
    files = sorted(p.name for p in tmp_path.glob("*.pt"))
    assert len(files) == 1 and "r3-t5-s42" in files[0]

    def fail(*args, **kwargs):
        raise AssertionError("simulated again instead of reading the cache")

    monkeypatch.setattr(linear, "simulate", fail)
    again = cached_simulate(linear, 3, 5, 42, tmp_path)
    assert torch.equal(again["measurement"], first["measurement"]) and torch.equal(again["state"], first["state"])
    with pytest.raises(AssertionError, match="simulated again"):
        cached_simulate(linear, 3, 5, 43, tmp_path)  # another seed is another entry


def test_cache_key_includes_the_system_parameters(tmp_path):
    a = cached_simulate(make_system("linear"), 2, 4, 0, tmp_path)
    b = cached_simulate(make_system("linear", measurement_std=3.0), 2, 4, 0, tmp_path)
    assert len(list(tmp_path.glob("*.pt"))) == 2
    assert not torch.equal(a["measurement"], b["measurement"])


def test_recorded_system_simulate_equals_base(linear, tmp_path):
    rec = RecordedSystem(linear, runs=2, steps=2, seed=0, cache_dir=tmp_path)
    torch.testing.assert_close(rec.simulate(3, 4, 9)["state"], linear.simulate(3, 4, 9)["state"], rtol=0, atol=0)
    assert rec._bank is None  # simulate() does not build the bank


def test_make_system_replay_option_and_delegation(tmp_path):
    rec = make_system("linear", replay={"runs": 2, "steps": 3, "seed": 4, "cache_dir": str(tmp_path)})
    assert isinstance(rec, RecordedSystem) and (rec.bank_runs, rec.bank_steps, rec.bank_seed) == (2, 3, 4)
    base = make_system("linear")
    x, u = torch.ones(2), torch.ones(1)
    torch.testing.assert_close(rec.f(x, u), base.f(x, u))  # the model, where the base offers one
    assert rec.name == "linear" and rec.state_names == base.state_names and rec.describe()["replay"]["runs"] == 2
    with pytest.raises(ValueError, match="unknown replay option"):
        make_system("linear", replay={"episodes": 3})
    assert not isinstance(make_system("linear", replay=None), RecordedSystem)


def test_veh14dof_replay_env_passes_check_env_specs(tmp_path):
    """The simulator-only system through the wrapper: specs hold, report_scale is the base's."""
    env = make_env("veh14dof", batch_size=2, window=3, max_steps=4, replay={"runs": 3, "steps": 4, "seed": 1}, h=0.01)
    system = env.base_env.system
    assert isinstance(system, RecordedSystem) and not system.has_model
    assert system.report_scale.shape == (6,)
    check_env_specs(env)
    with pytest.raises(NotImplementedError):
        system.f(torch.zeros(6), torch.zeros(0))
