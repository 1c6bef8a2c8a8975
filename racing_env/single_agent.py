"""Gymnasium view of a race: one learner against opponents.

The opponents are agent specs, agent factories, agents or callables
``policy(observation, joint_state) -> action`` (a normalised action in ``[-1, 1]^2``), so
planners, scripted drivers and trained models can be plugged in
(:mod:`racing_env.opponents`: the entries every learner face takes). The env is registered
as ``racing_env/Race-v0``::

    env = gymnasium.make("racing_env/Race-v0", opponents=["lane-keeping"], track="trefoil")

Guide: docs/env.md.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import gymnasium
import numpy as np

from racing_env.config import RaceConfig
from racing_env.env import RacingParallelEnv, agent_name
from racing_env.opponents import (
    MAKE_AGENT,
    SHARED_AGENT_HINT,
    check_keywords,
    is_agent,
    is_factory,
    is_spec_list,
    learner_config,
    make_from_factory,
    opponent_cars,
    planners_function,
)

OpponentPolicy = Callable[[np.ndarray, np.ndarray], Any]


def coasting_policy(observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
    """An opponent that applies zero jerk (keeps its accelerations)."""
    return np.zeros(2, dtype=np.float32)


def _opponent_policy(entry: Any, car: int) -> OpponentPolicy:
    """The driver of car ``car`` from an ``opponents`` entry (:mod:`racing_env.opponents`):
    specs and factories make an agent of their own for the car."""
    if entry is None:
        return coasting_policy
    if isinstance(entry, OpponentPool):
        return entry
    if isinstance(entry, str):
        return planners_function(MAKE_AGENT)(entry)
    if is_spec_list(entry):
        make_agent = planners_function(MAKE_AGENT)
        return OpponentPool([make_agent(spec) for spec in entry], names=list(entry))
    if is_factory(entry):
        return make_from_factory(entry, car)
    if callable(entry):
        return entry
    raise ValueError(f"opponent {entry!r} of car {car} must be None (coasting), an agent spec (str), a list of specs "
                     "(a pool), an OpponentPool, an agent factory (e.g. an agent class) or a callable "
                     "policy(observation, joint_state) -> action")


class OpponentPool:
    """Several drivers for one opponent car: every episode drives with one of them.

    :class:`RaceEnv` draws the driver at each ``reset``, uniformly, from its own seeded
    generator, so the same seed gives the same sequence of opponents. The drawn names are
    in the learner's ``info["opponents"]``.

    Args:
        policies: the drivers (callables, or agents resettable as a car).
        names: one name per driver (default: the agents' ``name`` or ``driver<k>``).
    """

    def __init__(self, policies: Sequence[OpponentPolicy], names: Sequence[str] | None = None) -> None:
        self.policies = list(policies)
        if not self.policies:
            raise ValueError("an opponent pool needs at least one policy")
        if not all(callable(p) for p in self.policies):
            raise ValueError("every driver of an opponent pool must be a callable policy(observation, joint_state)")
        if names is None:
            names = [getattr(p, "name", f"driver{k}") for k, p in enumerate(self.policies)]
        self.names = [str(name) for name in names]
        if len(self.names) != len(self.policies):
            raise ValueError(f"{len(self.names)} names for {len(self.policies)} drivers")
        self.current = 0

    def draw(self, rng: np.random.Generator) -> None:
        """Pick this episode's driver."""
        self.current = int(rng.integers(len(self.policies)))

    @property
    def driver(self) -> OpponentPolicy:
        return self.policies[self.current]

    @property
    def name(self) -> str:
        return self.names[self.current]

    def __call__(self, observation: np.ndarray, joint_state: np.ndarray) -> Any:
        return self.driver(observation, joint_state)


class RaceEnv(gymnasium.Env):
    """One learner (``car_<learner>``) against ``N - 1`` opponents.

    Args:
        opponents: one entry per opponent (in car order, skipping the learner), or one
            entry for all: ``None`` (coasting), an agent spec (``"lane-keeping"``), a list
            of specs (a pool), an :class:`OpponentPool`, an agent factory (an agent class,
            a ``functools.partial`` of one, a zero-argument callable), an agent object or a
            callable ``policy(observation, joint_state) -> action``
            (:mod:`racing_env.opponents`). Default: coasting cars (one when ``num_agents``
            is not given, none for a lone learner). Their number fixes N = len(opponents) + 1
            unless ``num_agents`` is given.
        learner: index of the learner's car.
        **config: ``RaceConfig`` fields (track, scenario, laps, reward, ...); without
            ``weights`` the game planner opponents plan with has the racing jerk weight
            (:meth:`RaceConfig.game_weights`), as in :func:`racing_env.parallel_env`. One
            default differs from ``RaceConfig``'s: ``on_off_track`` is
            :data:`racing_env.opponents.LEARNER_OFF_TRACK` (``terminate``: a learner that
            leaves the track is out), the rule ``racing train`` trains with. Any other
            keyword is refused (``TypeError``, naming the allowed ones).

    A spec or a factory makes an agent of its own for each car it drives. An agent (it has
    ``reset(seed, index, env_info)`` besides ``act``) is reset as its car at every
    ``reset``, with the episode's seed, so planners take this env's game and start each
    episode without a previous plan. An agent object drives one car only: reusing it for
    several opponents is refused (give its spec or a factory instead).

    The episode ends (terminated) when the learner finishes or retires, and is truncated
    at ``max_steps``. ``info`` is the learner's PettingZoo info.
    """

    metadata = RacingParallelEnv.metadata

    def __init__(
        self,
        opponents: Sequence[Any] | None = None,
        learner: int = 0,
        **config: Any,
    ) -> None:
        check_keywords(config, "racing_env/Race-v0 (RaceEnv)")
        num, entries = opponent_cars(opponents, learner, config)
        pools = [entry for _, entry in entries if isinstance(entry, OpponentPool)]
        if len({id(p) for p in pools}) != len(pools):
            raise ValueError("an opponent pool drives one car: give one pool per opponent")
        policies = {car: _opponent_policy(entry, car) for car, entry in entries}
        drivers = [d for p in policies.values() for d in (p.policies if isinstance(p, OpponentPool) else [p])]
        agents = [p for p in drivers if is_agent(p)]
        if len({id(p) for p in agents}) != len(agents):
            raise ValueError(f"an agent object (with reset(seed, index, env_info)) drives one car; {SHARED_AGENT_HINT}")
        self.race = RacingParallelEnv(RaceConfig(num_agents=num, **learner_config(config)))
        self.render_mode = self.race.render_mode
        self.learner = agent_name(learner)
        self._opponents = {agent_name(car): policy for car, policy in policies.items()}
        self._has_pool = any(isinstance(p, OpponentPool) for p in policies.values())  # info names the drawn drivers
        self.observation_space = self.race.observation_space(self.learner)
        self.action_space = self.race.action_space(self.learner)
        self._observations: dict[str, np.ndarray] = {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._observations, infos = self.race.reset(seed=seed, options=options)
        for agent, policy in self._opponents.items():
            if isinstance(policy, OpponentPool):
                policy.draw(self.np_random)
                policy = policy.driver
            if is_agent(policy):
                policy.reset(seed, self.race.possible_agents.index(agent), self.race)
        return self._observations[self.learner], self._with_opponents(infos[self.learner])

    def _with_opponents(self, info: dict) -> dict:
        """The learner's info, with this episode's drawn drivers when a pool is raced."""
        if self._has_pool:
            info = {**info, "opponents": [getattr(p, "name", None) for p in self._opponents.values()]}
        return info

    def step(self, action):
        if self.learner not in self.race.agents:
            raise RuntimeError("the learner is not racing (its episode ended, terminated or truncated, or none has "
                               "started): call reset() before step()")
        state = self.race.state()
        actions = {self.learner: action}
        for agent in self.race.agents:
            if agent != self.learner:
                actions[agent] = np.asarray(self._opponents[agent](self._observations[agent], state))
        observations, rewards, terms, truncs, infos = self.race.step(actions)
        self._observations = observations
        return (
            observations[self.learner],
            rewards[self.learner],
            terms[self.learner],
            truncs[self.learner],
            self._with_opponents(infos[self.learner]),
        )

    def render(self):
        return self.race.render()

    def close(self) -> None:
        self.race.close()


ENV_ID = "racing_env/Race-v0"


def register() -> None:
    """Register ``racing_env/Race-v0`` with Gymnasium (idempotent)."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="racing_env.single_agent:RaceEnv",
                           vector_entry_point="racing_env.vector:RaceVectorEnv")
