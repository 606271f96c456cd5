"""``RecordedSystem``: replay a recorded bank of episodes instead of simulating them afresh.

A filter's estimates never feed back into the simulated trajectory, so the episodes an env serves
can be simulated once and replayed (docs/experiment2.md). That pays off when simulating
is expensive and batches badly: veh14dof costs ~70 ms per env step at batch 32 but simulates
~15× more steps per second at batch 1024. The wrapper is a ``StochasticSystem`` that
``FilteringEnv`` runs unchanged:

* ``reset_episode`` deals episodes of the bank without replacement: every episode is served once
  before any is served again, in an order shuffled by the env's own generator (the undealt rest,
  ``deck``, goes into training checkpoints, so a resumed run deals the same ones), and ``advance``
  returns their recorded steps. Drawing with replacement would leave 37 % (1/e) of a bank unseen
  after as many draws as it holds episodes;
* ``simulate(runs, steps, seed)`` returns exactly the base system's ``simulate`` and, given a
  ``cache_dir``, memoises it on disk keyed by system, parameters, runs, steps and seed (validation
  and normaliser sets are the same for every training run; the bank itself is one such call);
* everything else (names, prior, bounds, ``f``/``g`` where the base offers them, ``report_scale``)
  is the base system's.

Build one with ``make_system(name, replay={"runs": 1024, "steps": 500, "seed": 1, "cache_dir": ...})``
or ``RecordedSystem(system, ...)``. The bank records ``steps + 1`` measured steps per episode, so
an env episode of up to ``steps`` estimates also gets the observation after its last estimate.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
from pathlib import Path

import torch
from daof.envs.checks import as_seed
from daof.envs.system import StochasticSystem, SystemWrapper
from tensordict import TensorDict

from daof.io import atomic_save, safe_load

__all__ = ["RecordedSystem", "cache_key", "cached_simulate", "find_recorded"]

#: bump when the cached file format or the meaning of its key changes
FORMAT = 1


def _params(system: StochasticSystem) -> dict:
    """The system's parameter dataclass as plain data (``{}`` if it has none), through any wrappers."""
    while isinstance(getattr(system, "system", None), StochasticSystem):
        system = system.system
    for value in vars(system).values():
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return dataclasses.asdict(value)
    return {}


def cache_key(system: StochasticSystem, runs: int, steps: int, seed: int, device="cpu") -> dict:
    """What identifies one ``simulate`` call: system, scenario, parameters, runs, steps, seed."""
    return {
        "format": FORMAT,
        "system": system.name,
        "scenario": system.scenario,
        "params": json.loads(json.dumps(_params(system), default=str)),
        "runs": int(runs),
        "steps": int(steps),
        "seed": as_seed(seed),
        "device": str(torch.device(device)),
    }


def _cache_path(cache_dir: Path, key: dict) -> Path:
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    return cache_dir / f"{key['system']}-{key['scenario']}-r{key['runs']}-t{key['steps']}-s{key['seed']}-{digest}.pt"


def cached_simulate(
    system: StochasticSystem, runs: int, steps: int, seed: int, cache_dir: str | Path | None, device="cpu"
) -> TensorDict:
    """``system.simulate(runs, steps, seed)``, memoised in ``cache_dir`` (``None``: not cached).

    Concurrent callers (parallel training jobs) take a file lock, so one simulates and the others
    read its file; a file is written atomically and checked against its key when read.
    """
    if cache_dir is None:
        return system.simulate(runs, steps, seed, device=device)
    cache = Path(cache_dir)
    cache.mkdir(parents=True, exist_ok=True)
    key = cache_key(system, runs, steps, seed, device)
    path = _cache_path(cache, key)
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            blob = _read_memo(path)
            if blob is not None and blob.get("key") == key:
                return TensorDict(blob["data"], batch_size=[runs, steps]).to(device)
            data = system.simulate(runs, steps, seed, device=device)
            atomic_save({"key": key, "data": {k: v.cpu() for k, v in data.items()}}, path)
            return data
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _read_memo(path: Path) -> dict | None:
    """A memoised simulation, or None if there is none or it does not read (truncated, foreign: simulated again)."""
    if not path.is_file():
        return None
    try:
        blob = safe_load(path)
    except ValueError:
        return None
    return blob if isinstance(blob, dict) and isinstance(blob.get("data"), dict) else None


class RecordedSystem(SystemWrapper):
    """``base`` with env episodes replayed from a bank of ``runs`` recorded episodes.

    Args:
        base: the system that records (and, in ``simulate``, generates) the data.
        runs: episodes in the bank.
        steps: the longest env episode the bank serves (it records ``steps + 1`` steps).
        seed: the bank's simulation seed (keep it disjoint from validation and evaluation seeds).
        cache_dir: directory of the on-disk memo of ``simulate`` (``None``: memory only).
    """

    def __init__(self, base: StochasticSystem, runs: int = 1024, steps: int = 500, seed: int = 0, cache_dir=None):
        if isinstance(base, RecordedSystem):
            raise ValueError("base is already a RecordedSystem")
        if int(runs) < 1 or int(steps) < 1:
            raise ValueError(f"a bank needs runs >= 1 and steps >= 1, got runs={runs}, steps={steps}")
        super().__init__(base)
        self.bank_runs, self.bank_steps, self.bank_seed = int(runs), int(steps), as_seed(seed)
        self.cache_dir = Path(cache_dir) if cache_dir else None
        self._bank: TensorDict | None = None
        #: bank episodes still to be dealt in the current pass (refilled with a fresh shuffle)
        self.deck = torch.zeros(0, dtype=torch.long)

    @classmethod
    def from_mapping(cls, base: StochasticSystem, replay) -> RecordedSystem:
        """From a config mapping (``make_system(..., replay={...})``); unknown keys are a ``ValueError``."""
        fields = ("runs", "steps", "seed", "cache_dir")
        kwargs = {str(k): v for k, v in replay.items()}
        unknown = sorted(set(kwargs) - set(fields))
        if unknown:
            raise ValueError(f"unknown replay option(s) {unknown}; valid: {list(fields)}")
        return cls(base, **kwargs)

    # ----------------------------------------------------------------- data
    def simulate(self, runs: int, steps: int, seed: int, device="cpu") -> TensorDict:
        """The base system's ``simulate`` (memoised on disk when ``cache_dir`` is set)."""
        return cached_simulate(self.base, runs, steps, seed, self.cache_dir, device)

    @property
    def bank(self) -> TensorDict:
        """The recorded episodes [runs, steps + 1] (simulated, or read from the cache, on first use)."""
        if self._bank is None:
            self._bank = self.simulate(self.bank_runs, self.bank_steps + 1, self.bank_seed)
        return self._bank

    def deal(self, runs: int, generator: torch.Generator) -> torch.Tensor:
        """The next ``runs`` episode indices of the deck, reshuffling the whole bank when it runs out."""
        while len(self.deck) < runs:
            shuffled = torch.randperm(self.bank_runs, generator=generator, device=generator.device).cpu()
            self.deck = torch.cat([self.deck, shuffled])
        episode, self.deck = self.deck[:runs], self.deck[runs:]
        return episode

    def reset_episode(self, runs: int, generator: torch.Generator, device="cpu") -> TensorDict:
        """Deal ``runs`` bank episodes (without replacement, see ``deal``) at t = 0."""
        bank = self.bank
        episode = self.deal(runs, generator)
        return TensorDict(
            {
                "episode": episode,
                "t": torch.zeros(runs, dtype=torch.long),
                "u": bank["prev_control"][episode, 0],
            },
            batch_size=[runs],
        ).to(device)

    def advance(self, sim: TensorDict, generator: torch.Generator) -> tuple[TensorDict, TensorDict]:
        """Step t -> t + 1 of every run's bank episode: the recorded observation at t + 1."""
        t = sim["t"] + 1
        last = int(t.max())
        if last > self.bank_steps + 1:
            raise ValueError(
                f"the bank serves episodes of up to {self.bank_steps} steps; step {last - 1} was asked for "
                "(record a longer bank: steps >= the env's max_steps)"
            )
        episode, index = sim["episode"].cpu(), (t - 1).cpu()
        bank = self.bank
        device = sim.device if sim.device is not None else t.device
        obs = TensorDict(
            {k: bank[k][episode, index] for k in ("state", "measurement", "control", "prev_control")},
            batch_size=sim.batch_size,
        ).to(device)
        new_sim = TensorDict({"episode": sim["episode"], "t": t, "u": obs["control"]}, batch_size=sim.batch_size)
        return new_sim, obs

    # ----------------------------------------------------------------- helpers
    def state_dict(self) -> dict:
        """What a resumed run needs to deal the same episodes: the undealt rest of the deck."""
        return {"deck": self.deck.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.deck = state["deck"].clone()

    def describe(self) -> dict:
        info = self.base.describe()
        info["replay"] = {
            "runs": self.bank_runs,
            "steps": self.bank_steps,
            "seed": self.bank_seed,
            "cache_dir": str(self.cache_dir) if self.cache_dir else None,
        }
        return info

    def __repr__(self) -> str:
        return f"RecordedSystem({self.name}, runs={self.bank_runs}, steps={self.bank_steps}, seed={self.bank_seed})"


def find_recorded(system: StochasticSystem) -> RecordedSystem | None:
    """The ``RecordedSystem`` ``system`` is or wraps (``GappySystem(RecordedSystem(...))``), if any."""
    while system is not None:
        if isinstance(system, RecordedSystem):
            return system
        system = getattr(system, "base", None)
    return None
