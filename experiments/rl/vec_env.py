"""stable-baselines3's ``VecEnv`` over the vectorised race (:class:`racing_env.vector.RaceVectorEnv`).

:class:`RaceVecEnv` presents B races of one learner against opponents as SB3 expects them,
race ``k`` where a ``DummyVecEnv`` of B Gymnasium views (:class:`racing_env.RaceEnv`, each in
SB3's ``Monitor``) has copy ``k``. The races are stepped by a few ``RaceVectorEnv`` groups,
one per distinct race (learner index and :class:`racing_env.RaceConfig`, e.g. the learner's
car and the start scenario), each advancing all its races in one compiled call; their
results are put back in race order.

What SB3 gets, per step: observations ``(B, O)`` float32; rewards ``(B,)`` float32 (as
``DummyVecEnv`` stores them); dones ``(B,)`` bool; B info dicts with the learner's ``s``,
``lap``, ``position``, ``collided``, ``off_track``, ``finished``, ``finish_time`` [s] (None
until finished), ``out``, ``reward_terms`` and ``TimeLimit.truncated``, and, with a pool of
opponents, ``opponents`` (the drawn driver of each opponent car). A race that ends is reset
in the same step (Gymnasium's ``same_step`` autoreset): its info then also holds
``terminal_observation`` (the last observation of the ended episode) and ``Monitor``'s
``episode`` record ``{"r": return, "l": length [steps], "t": wall time [s] since the env
was made}`` with the :data:`INFO_KEYWORDS` of the episode's last step.

Seeding follows SB3: ``seed(s)`` makes the next ``reset()`` start race ``k`` with seed
``s + k``, after which it runs exactly the episodes of copy ``k`` of a ``DummyVecEnv``
seeded the same way: the states agree to a few ulps (XLA vectorises sin and cos across
races), the opponents' actions being rounded to float32 as the single agents round theirs.

:meth:`RaceVecEnv.get_state` and :meth:`RaceVecEnv.set_state` save and restore everything
the races' future depends on (race states, their start keys, the opponents' per-race
memory, the episodes' returns so far), so that training resumed from a checkpoint goes on
exactly as if it had not stopped (:mod:`experiments.rl.train`).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from typing import Any, Sequence

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv

import racing_env  # noqa: F401 - registers racing_env/Race-v0
from planners.agents.batched import make_batched_opponent
from racing_env.config import RaceConfig
from racing_env.env import RacingParallelEnv

__all__ = ["INFO_KEYWORDS", "RaceVecEnv"]

INFO_KEYWORDS = ("finished", "position", "out", "finish_time")
"""The learner's info entries copied into every ``episode`` record, as SB3's ``Monitor``
does with its ``info_keywords`` (what the training's episode log reads)."""

_SCALARS = ("s", "lap", "position", "collided", "off_track", "finished", "out")
_SINGLE_SPACES = {"observation_space": "single_observation_space", "action_space": "single_action_space"}


@dataclasses.dataclass
class _Group:
    """The races of one ``RaceVectorEnv``: ``races`` (G,) are their indices in the VecEnv."""

    env: Any
    races: np.ndarray
    pools: dict[str, tuple[list[str], Any]]  # opponent agent -> its pool's specs and batched pool

    def drivers(self) -> dict[str, np.ndarray]:
        """Per pool, the entry each race drew for its episode, ``{agent: (G,) int}``."""
        return {agent: np.array(pool.inner.driver) for agent, (_, pool) in self.pools.items()}


class RaceVecEnv(VecEnv):
    """B races of one learner against opponents, as an SB3 ``VecEnv`` (module docstring).

    Args:
        races: per race ``k``, ``(learner, config)``: the learner's car index and the race
            (:class:`racing_env.RaceConfig`; ``render_mode`` None). Races with equal pairs
            are stepped together; every race must observe the same number of features.
        opponents: the opponent cars' drivers, one per opponent car in car order (or one
            for all): agent specs (``"lane-keeping"``, ``"ilqgame-fb:replan_every=5"``,
            ``"rl:PATH"``), lists of specs (a pool: each race draws the car's driver at
            every episode from the episode's seed), or None (a coasting car); ``()`` for
            a lone learner. See :class:`racing_env.vector.RaceVectorEnv`.
        info_keywords: the learner's info entries copied into each ``episode`` record.
    """

    def __init__(self, races: Sequence[tuple[int, RaceConfig]], opponents: Sequence[Any] = (),
                 info_keywords: Sequence[str] = INFO_KEYWORDS) -> None:
        races = [(int(learner), config) for learner, config in races]
        if not races:
            raise ValueError("a RaceVecEnv needs at least one race")
        self.info_keywords = tuple(info_keywords)
        self.groups = [self._make_group(learner, config, members, opponents)
                       for (learner, config), members in _grouped(races)]
        observation_space = self.groups[0].env.single_observation_space
        for group in self.groups[1:]:
            if group.env.single_observation_space.shape != observation_space.shape:
                raise ValueError(f"every race must observe the same features: {observation_space.shape} and "
                                 f"{group.env.single_observation_space.shape} differ (other numbers of cars?)")
        self._learners = np.array([learner for learner, _ in races])
        super().__init__(len(races), observation_space, self.groups[0].env.single_action_space)
        self._actions: np.ndarray | None = None
        self._returns = np.zeros(self.num_envs)  # the episodes' returns so far, as Monitor sums them
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._t_start = time.time()
        self._started = False

    @staticmethod
    def _make_group(learner: int, config: RaceConfig, members: list[int], opponents: Sequence[Any]) -> _Group:
        fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
        cars = [j for j in range(config.num_agents) if j != learner]
        entries = list(opponents) * (len(cars) if len(opponents) == 1 else 1)
        if len(entries) != len(cars):
            raise ValueError(f"need {len(cars)} opponents for {config.num_agents} cars, got {len(opponents)}")
        game = _race_game(config) if any(_is_spec(e) for e in entries) else None
        drivers = [_SingleAgentActions(make_batched_opponent(list(e) if not isinstance(e, str) else e, game, j,
                                                             len(members)))
                   if _is_spec(e) else e for j, e in zip(cars, entries)]
        env = gymnasium.make_vec("racing_env/Race-v0", num_envs=len(members), vectorization_mode="vector_entry_point",
                                 opponents=drivers, learner=learner, autoreset_mode="same_step", **fields)
        pools = {f"car_{j}": (list(e), d) for j, e, d in zip(cars, entries, drivers)
                 if _is_spec(e) and not isinstance(e, str)}
        return _Group(env, np.array(members), pools)

    # --- the VecEnv interface --------------------------------------------------------------
    def reset(self) -> np.ndarray:
        """Start every race (with the seeds of :meth:`seed`, once); returns ``(B, O)`` float32."""
        seeds = self._seeds
        if any(s is None for s in seeds) and not all(s is None for s in seeds):
            raise ValueError(f"seed every race or none, got {seeds}")
        if any(o for o in self._options):
            raise ValueError("RaceVecEnv takes no reset options")
        observations = np.zeros((self.num_envs,) + self.observation_space.shape, self.observation_space.dtype)
        for group in self.groups:
            seed = None if seeds[0] is None else [int(seeds[k]) for k in group.races]
            obs, infos = group.env.reset(seed=seed)
            observations[group.races] = obs
            rows = np.arange(len(group.races))
            for k, info in zip(group.races, self._race_infos(group, infos, rows, group.drivers())):
                self.reset_infos[k] = info
        self._reset_seeds()
        self._reset_options()
        self._returns[:] = 0.0
        self._lengths[:] = 0
        self._started = True
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        """Step every race with the actions given to :meth:`step_async` (``(B, 2)``)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        actions, self._actions = self._actions, None
        b = self.num_envs
        observations = np.zeros((b,) + self.observation_space.shape, self.observation_space.dtype)
        rewards = np.zeros(b)
        terminated, truncated = np.zeros(b, dtype=bool), np.zeros(b, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(b)]
        for group in self.groups:
            drivers = group.drivers()  # the episodes' drivers (a race that ends draws its next one in the step)
            obs, reward, term, trunc, group_infos = group.env.step(actions[group.races])
            observations[group.races], rewards[group.races] = obs, reward
            terminated[group.races], truncated[group.races] = term, trunc
            done = term | trunc
            rows = np.arange(len(group.races))
            # the ended races' infos are their last step's (final_info), the others' this step's
            running = self._race_infos(group, group_infos, rows, drivers)
            if done.any():
                last = self._race_infos(group, group_infos["final_info"], np.flatnonzero(done), drivers)
                for row, info in zip(np.flatnonzero(done), last):
                    running[row] = info
                    info["terminal_observation"] = group_infos["final_obs"][row]
            for k, info in zip(group.races, running):
                infos[k] = info
        self._returns += rewards
        self._lengths += 1
        dones = terminated | truncated
        for k in np.flatnonzero(dones):
            info = infos[k]
            info["TimeLimit.truncated"] = bool(truncated[k] and not terminated[k])
            episode = {"r": round(float(self._returns[k]), 6), "l": int(self._lengths[k]),
                       "t": round(time.time() - self._t_start, 6)}
            episode.update({key: info[key] for key in self.info_keywords})
            info["episode"] = episode
        for k in np.flatnonzero(~dones):
            infos[k]["TimeLimit.truncated"] = False
        self._returns[dones] = 0.0
        self._lengths[dones] = 0
        return observations, rewards.astype(np.float32), dones, infos

    @staticmethod
    def _race_infos(group: _Group, infos: dict[str, Any], rows: np.ndarray,
                    drivers: dict[str, np.ndarray]) -> list[dict[str, Any]]:
        """The learner's info dicts of the group's races ``rows`` from the group's batched
        ``infos`` (Python scalars, as :class:`racing_env.RaceEnv` gives them), naming the pools'
        ``drivers`` (:meth:`_Group.drivers`)."""
        columns = {key: np.asarray(infos[key])[rows].tolist() for key in _SCALARS}
        finish = np.asarray(infos["finish_time"])[rows].tolist()
        terms = infos.get("reward_terms", {})
        term_columns = {name: np.asarray(values)[rows].tolist() for name, values in terms.items()}
        named = {agent: [specs[d] for d in drivers[agent][rows].tolist()] for agent, (specs, _) in group.pools.items()}
        out = []
        for r in range(len(rows)):
            info = {key: column[r] for key, column in columns.items()}
            info["finish_time"] = finish[r] if info["finished"] else None
            info["reward_terms"] = {name: column[r] for name, column in term_columns.items()}
            if named:
                info["opponents"] = [names[r] for names in named.values()]
            out.append(info)
        return out

    def close(self) -> None:
        for group in self.groups:
            group.env.close()

    # --- attributes and methods of the races -----------------------------------------------
    def _group_of(self, indices) -> list[tuple[_Group, list[int]]]:
        """The groups of the races ``indices`` (None: all), each with the races asked of it."""
        wanted = [int(k) for k in self._get_indices(indices)]
        asked = [(g, [k for k in wanted if k in set(g.races.tolist())]) for g in self.groups]
        return [(g, races) for g, races in asked if races]

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        """Per race, the attribute of the ``RaceVectorEnv`` that steps it, except
        ``render_mode`` (None: the races are not rendered), ``learner`` (the race's learner
        index) and ``observation_space``/``action_space`` (one race's, as a single env has)."""
        wanted = list(self._get_indices(indices))
        if attr_name == "render_mode":
            return [None] * len(wanted)
        if attr_name == "learner":
            return [int(self._learners[k]) for k in wanted]
        attr_name = _SINGLE_SPACES.get(attr_name, attr_name)
        owner = {int(k): g for g in self.groups for k in g.races}
        return [getattr(owner[k].env.unwrapped, attr_name) for k in wanted]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        """Set the attribute of the ``RaceVectorEnv`` groups of the races ``indices``; a
        group's attribute is every one of its races', so ``indices`` must cover whole groups."""
        for group, asked in self._group_of(indices):
            if len(asked) != len(group.races):
                raise ValueError(f"races {group.races.tolist()} share one env: set {attr_name!r} for all of them")
            setattr(group.env.unwrapped, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        """Call the method of each ``RaceVectorEnv`` group of the races ``indices`` once;
        every race asked gets its group's result (in the order asked)."""
        results = {}
        for group, asked in self._group_of(indices):
            result = getattr(group.env.unwrapped, method_name)(*method_args, **method_kwargs)
            results.update({k: result for k in asked})
        return [results[k] for k in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices=None) -> list[bool]:
        """Whether each race is wrapped in ``wrapper_class``: it counts as SB3's ``Monitor``
        (this env writes Monitor's ``episode`` records), and as nothing else."""
        return [issubclass(Monitor, wrapper_class)] * len(list(self._get_indices(indices)))

    def get_images(self):
        raise NotImplementedError("the vectorised races do not render: race a recorded start with "
                                  "racing_env.parallel_env")

    # --- saving and restoring the races ----------------------------------------------------
    @property
    def exact_state(self) -> bool:
        """Whether :meth:`get_state` captures every opponent's memory (False when an
        opponent keeps per-race state in objects of its own, e.g. one single agent per race)."""
        return all(_capturable(o) for g in self.groups for o in g.env.unwrapped.opponents.values())

    def get_state(self) -> dict[str, Any]:
        """Everything the races' future depends on, as picklable NumPy data: each group's
        race states, start keys and opponents' per-race memory, and the episodes'
        returns and lengths so far. Needs :meth:`reset` first."""
        if not self._started:
            raise RuntimeError("call reset() before get_state()")
        return {"groups": [_group_state(g.env.unwrapped) for g in self.groups],
                "returns": self._returns.copy(), "lengths": self._lengths.copy(), "num_envs": self.num_envs}

    def set_state(self, state: dict[str, Any]) -> None:
        """Put the races back as :meth:`get_state` found them (in an env made with the same
        arguments); pending seeds are dropped, so no reset follows."""
        if state["num_envs"] != self.num_envs or len(state["groups"]) != len(self.groups):
            raise ValueError(f"a state of {state['num_envs']} races in {len(state['groups'])} groups cannot be put "
                             f"into {self.num_envs} races in {len(self.groups)} groups")
        for group, saved in zip(self.groups, state["groups"]):
            _restore_group_state(group.env.unwrapped, saved)
        self._returns, self._lengths = state["returns"].copy(), state["lengths"].copy()
        self._reset_seeds()
        self._started = True


def _is_spec(entry: Any) -> bool:
    """Whether an ``opponents`` entry is an agent spec or a list of them (a pool)."""
    return isinstance(entry, str) or (isinstance(entry, (list, tuple)) and bool(entry)
                                      and all(isinstance(e, str) for e in entry))


def _race_game(config: RaceConfig):
    """The :class:`racing_env.RaceGame` of the race ``config`` (the one its vectorised env plays)."""
    race = RacingParallelEnv(config)
    try:
        return race.game
    finally:
        race.close()


class _SingleAgentActions:
    """A batched opponent (:mod:`planners.agents.batched`) with its actions rounded to
    float32, as the single agents round theirs (:meth:`planners.agents.BaseAgent._finish`)
    and as :class:`racing_env.vector.RaceVectorEnv` rounds them again (a no-op then), so that
    the races are those of :class:`racing_env.RaceEnv`; it also names the opponent whose
    per-race memory a checkpoint saves. A scripted driver stays a JAX function, fused into
    the compiled step."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.index, self.num_races, self.spec = inner.index, inner.num_races, inner.spec
        policy = inner.jax_policy
        self.jax_policy = None if policy is None else (lambda x: policy(x).astype(jnp.float32).astype(x.dtype))

    def reset(self, races: np.ndarray, seeds: np.ndarray) -> None:
        self.inner.reset(races, seeds)

    def act(self, observations: np.ndarray, x: np.ndarray, racing: np.ndarray):
        actions, diagnostics = self.inner.act(observations, x, racing)
        return np.asarray(actions, dtype=np.float32).astype(np.float64), diagnostics


def _grouped(races: list[tuple[int, RaceConfig]]) -> list[tuple[tuple[int, RaceConfig], list[int]]]:
    """The distinct ``(learner, config)`` pairs in order of first appearance, each with the
    indices of its races."""
    groups: list[tuple[tuple[int, RaceConfig], list[int]]] = []
    for k, race in enumerate(races):
        for key, members in groups:
            if key == race:
                members.append(k)
                break
        else:
            groups.append((race, [k]))
    return groups


# --- the state of a RaceVectorEnv ----------------------------------------------------------------
# RaceVectorEnv has no state API yet: these read and write its attributes of the races in
# flight (_state, _obs_all, _keys, _needs_reset).
_RACE_ATTRIBUTES = ("_needs_reset",)


def _group_state(env: Any) -> dict[str, Any]:
    """A ``RaceVectorEnv``'s races in flight as NumPy data (see :meth:`RaceVecEnv.get_state`)."""
    return {
        "state": jax.device_get(env._state),
        "obs_all": np.asarray(env._obs_all),
        "keys": None if env._keys is None else np.asarray(env._keys),
        **{name: copy.deepcopy(getattr(env, name)) for name in _RACE_ATTRIBUTES},
        "opponents": {j: _opponent_state(o) for j, o in env.opponents.items()},
    }


def _restore_group_state(env: Any, saved: dict[str, Any]) -> None:
    env._state = jax.tree_util.tree_map(jnp.asarray, saved["state"])
    env._obs_all = jnp.asarray(saved["obs_all"])
    env._keys = None if saved["keys"] is None else jnp.asarray(saved["keys"])
    for name in _RACE_ATTRIBUTES:
        setattr(env, name, copy.deepcopy(saved[name]))
    for j, opponent in env.opponents.items():
        _restore_opponent(opponent, saved["opponents"][j])


def _capturable(opponent: Any) -> bool:
    """Whether :func:`_opponent_state` captures the opponent's per-race memory."""
    if isinstance(opponent, _SingleAgentActions):
        return _capturable(opponent.inner)
    if hasattr(opponent, "agents") or hasattr(opponent, "policy"):  # LoopedOpponent, a looped callable
        return False
    return all(_capturable(m) for m in getattr(opponent, "members", None) or ())


def _opponent_state(opponent: Any) -> dict[str, Any] | None:
    """A batched opponent's per-race memory: its NumPy array attributes (a planner's plans
    and their ages, a pool's drawn drivers, which races were started) and those of a pool's
    members; None for opponents that keep it in other objects (one single agent per race)."""
    if isinstance(opponent, _SingleAgentActions):
        return _opponent_state(opponent.inner)
    if not _capturable(opponent):
        return None
    state: dict[str, Any] = {name: value.copy() for name, value in vars(opponent).items()
                             if isinstance(value, np.ndarray)}
    members = getattr(opponent, "members", None)
    if members is not None:
        state["members"] = [_opponent_state(m) for m in {id(m): m for m in members}.values()]
    return state


def _restore_opponent(opponent: Any, saved: dict[str, Any] | None) -> None:
    if isinstance(opponent, _SingleAgentActions):
        opponent = opponent.inner
    if saved is None:
        raise ValueError(f"the memory of {opponent!r} was not saved (RaceVecEnv.exact_state is False): its races "
                         "cannot be restored")
    for name, value in saved.items():
        if name != "members":
            setattr(opponent, name, value.copy())
    if "members" in saved:
        unique = list({id(m): m for m in opponent.members}.values())
        for member, member_state in zip(unique, saved["members"]):
            _restore_opponent(member, member_state)
