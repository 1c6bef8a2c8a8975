"""RacingParallelEnv: a PettingZoo ParallelEnv of N cars racing on a track.

A step is one jitted call for all cars (``_race_step``): the physics, then the race's
rules (finishing order, retirements, positions, rewards: :mod:`racing_env.referee`). The
race's constants go in as one packed array (:mod:`racing_env.packing`); the results come
back as a few packed arrays, from which the PettingZoo dictionaries are built as plain
Python values.

Actions are normalised jerks in ``[-1, 1]^2``, scaled by each car's jerk limits
``(jx_max, jy_max)``. Finite actions outside the box are clipped to it (the only silent
correction); a container other than a mapping, non-numeric values (strings, booleans,
objects), NaN/inf, wrong shapes and unknown or missing agents are refused with an error and
leave the environment unchanged.
"""

from __future__ import annotations

import functools
import math
import numbers
import warnings
from typing import Any, Mapping

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from pettingzoo import ParallelEnv

from racing_env import race
from racing_env.config import RaceConfig
from racing_env.dynamics import SLIPSTREAM, STATE_DIM, S
from racing_env.game import RaceGame
from racing_env.observation import observation_size
from racing_env.packing import Layout, pack, unpack
from racing_env.race import RaceInfo, RaceParams, check_starts_behind, finish_line
from racing_env.referee import REWARD_TERMS, RaceStatus
from racing_env.scenarios import make_scenario
from racing_env.steward import VERDICTS
from racing_env.starts import fresh_key, key_from_seed
from racing_env.track import get_track


# Columns of the packed rows (:func:`_per_car_rows`): floats, then int32 (N columns each for
# the pair fields after the per-car ones).
_FLOAT_COLUMNS = ("finish_time", "reward", *REWARD_TERMS, "penalty", "serving")
_INT_COLUMNS = ("active", "finished", "out", "place", "position", "collided", "off_track", "lap", "faults",
                "last_move", "direction_changes")
_PAIR_INTS = ("contact", "last_contact", "incident", "fault", "rule")


def _per_car_rows(params: RaceParams, status: RaceStatus, reward, info: RaceInfo):
    """Per-car results packed into two arrays (two to read back instead of a dozen).

    Returns floats ``(N, len(_FLOAT_COLUMNS) + N)``: the columns of ``_FLOAT_COLUMNS``, then the
    closing speeds of the incidents begun in the step; and int32 ``(N, len(_INT_COLUMNS) + 5 N)``:
    the columns of ``_INT_COLUMNS``, then the ``(N, N)`` fields of ``_PAIR_INTS``.
    """
    floats = jnp.concatenate([status.finish_time[:, None], reward[:, None], info.terms, status.penalty[:, None],
                              status.serving[:, None], info.incidents.closing], axis=1)
    flags = [status.active, status.finished, status.out, status.place, info.position, info.collided,
             info.off_track, info.lap, status.faults, status.last_move, status.direction_changes]
    pairs = [info.contact, status.last_contact, info.incidents.incident, info.incidents.fault, info.incidents.rule]
    ints = jnp.concatenate([jnp.stack(flags, axis=1), *pairs], axis=1).astype(jnp.int32)
    return floats, ints


@functools.partial(jax.jit, static_argnames=("layout",))
def _race_step(constants: jax.Array, layout: Layout, x, status: RaceStatus, actions, steps):
    """One step of the race core (:func:`racing_env.race.step`) from ``steps`` steps taken,
    with the packed :class:`racing_env.race.RaceParams` ``constants``.

    Returns ``x_next (N, 6)``, observations ``(N, obs)`` float32 and the packed per-car
    results (:func:`_per_car_rows`).
    """
    params = unpack(constants, layout)
    state, obs, reward, _, _, info = race.step(None, race.RaceState(x, status, steps), actions, params)
    return (state.x, obs) + _per_car_rows(params, state.status, reward, info)


@functools.partial(jax.jit, static_argnames=("layout",))
def _race_start(constants: jax.Array, layout: Layout, x):
    """Observations ``(N, obs)`` float32 and the packed per-car results (:func:`_per_car_rows`) of a
    start state: no incidents, no rewards."""
    params = unpack(constants, layout)
    state, obs, info = race.start(x, params)
    return (obs,) + _per_car_rows(params, state.status, jnp.zeros(x.shape[0], x.dtype), info)


@functools.partial(jax.jit, static_argnames=("layout",))
def _race_draw(constants: jax.Array, layout: Layout, key):
    """The next episode of a race's ``key`` (:func:`racing_env.race.next_start`): the key
    carried on, the start ``x0 (N, 6)`` and whether it is free of overlaps."""
    carried, x0, free, _ = race.next_start(key, unpack(constants, layout))
    return carried, x0, free


def _is_real(action: Any) -> bool:
    """Whether ``action`` holds real numbers only. NumPy would silently turn strings such as
    ``'0.5'`` and booleans into floats."""
    if isinstance(action, np.ndarray):
        return action.dtype.kind in "fiu"
    if isinstance(action, (bool, np.bool_, str, bytes)):
        return False
    if isinstance(action, (list, tuple)):
        return all(map(_is_real, action))
    if isinstance(action, numbers.Real):
        return True
    return np.asarray(action).dtype.kind in "fiu"  # e.g. JAX arrays


def agent_name(index: int) -> str:
    return f"car_{index}"


class RacingParallelEnv(ParallelEnv):
    """N point-mass cars racing in a Frenet frame (PettingZoo Parallel API).

    ``state()`` returns the joint state ``(N, 6)`` (full information for planners);
    ``game`` is the ``RaceGame`` the planners should use (its weights:
    :meth:`RaceConfig.game_weights`, by default the racing jerk weight). ``infos[agent]`` holds ``s``,
    ``lap``, ``position`` (1 = leading), ``collided``, ``contact_with``, ``off_track``,
    ``finished``, ``finish_time`` [s] (None until finished), ``out`` (retired by an incident rule or
    the steward), ``penalty`` (the steward's time penalties so far [s]), ``faults`` (incidents
    the car answered for), ``incidents`` (those begun in this step, each a dict: ``with`` the
    other car, ``verdict`` from :data:`racing_env.steward.VERDICTS`, ``at_fault`` whether this
    car answers, ``closing_speed`` [m/s]) and the ``reward_terms``.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "name": "racing_v0", "render_fps": 10}

    def __init__(self, config: RaceConfig | None = None, **kwargs: Any) -> None:
        if config is None:
            config = RaceConfig(**kwargs)
        elif kwargs:
            raise ValueError("pass either a RaceConfig or keyword arguments, not both")
        self.config = config
        self.render_mode = config.render_mode
        self.track = get_track(config.track)
        num = config.num_agents
        self.possible_agents = [agent_name(i) for i in range(num)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self.finish_s = finish_line(config, self.track)
        scenario = make_scenario(config.scenario, self.track, num, config.vehicles, seed=0, finish_s=self.finish_s)
        self.game = RaceGame.create(
            self.track, scenario.vehicles, config.game_weights(), dt=config.dt, horizon=config.horizon,
            slipstream=SLIPSTREAM if config.slipstream else None,
        )
        check_starts_behind(self.finish_s, scenario.x0, config.scenario)
        #: the race's constants for the race core (racing_env.race)
        self.params = race.race_params(config, self.track, self.game, self.finish_s)
        # on the device once, as one array: a step neither re-transfers them nor pays for
        # their argument leaves (racing_env.packing)
        self._constants, self._layout = pack(self.params)
        obs_dim = observation_size(num, len(config.preview_distances), config.observed_rivals)
        # every finite float32 vector (no natural bounds): finite limits,
        # because Gymnasium's check_env warns about infinite Box bounds
        big = np.finfo(np.float32).max
        self._obs_space = gymnasium.spaces.Box(-big, big, (obs_dim,), np.float32)
        self._act_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.state_space = gymnasium.spaces.Box(-np.inf, np.inf, (num, STATE_DIM), np.float64)
        self._key: np.ndarray | None = None  # the race's key (racing_env.starts), set by reset
        self._x = np.zeros((num, STATE_DIM))
        self._renderer = None

    # --- spaces ---------------------------------------------------------------------------
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        self._check_agent(agent)
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        self._check_agent(agent)
        return self._act_space

    def _check_agent(self, agent: str) -> None:
        if agent not in self._index:
            raise KeyError(f"unknown agent {agent!r}; agents are {self.possible_agents}")

    @property
    def num_cars(self) -> int:
        return len(self.possible_agents)

    # --- episode --------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: Mapping[str, Any] | None = None):
        """Start a race. ``options`` may hold ``x0`` (a joint start state ``(N, 6)``).

        The start is drawn with JAX from the scenario (:mod:`racing_env.starts`): ``seed``
        (an integer >= 0) sets the race's key, and each reset draws the next episode of it,
        so a seeded env runs the same episodes as the vectorised env's race of that seed.
        """
        if seed is not None:
            self._key = key_from_seed(seed)
        elif self._key is None:
            self._key = fresh_key()
        key, drawn, free = (np.asarray(a) for a in _race_draw(self._constants, self._layout, self._key))
        self._key = key
        options = dict(options or {})
        if "x0" in options:
            x0 = np.array(options.pop("x0"), dtype=np.float64)
            if x0.shape != (self.num_cars, STATE_DIM) or not np.all(np.isfinite(x0)):
                raise ValueError(
                    f"options['x0'] must be a finite array of shape {(self.num_cars, STATE_DIM)}, "
                    f"got shape {x0.shape}"
                )
        else:
            if not free:
                raise ValueError(f"scenario {self.config.scenario!r} found no start without overlapping cars")
            x0 = np.array(drawn)
            # seed 0's grid was checked in __init__; another seed's jitter moves cars by up to 1 m
            check_starts_behind(self.finish_s, x0, self.config.scenario)
        if options:
            # PettingZoo's parallel_api_test resets with options={"options": 1}: unknown keys
            # are ignored with a warning rather than refused.
            warnings.warn(f"ignoring unknown reset options {sorted(options)}; allowed: ['x0']", stacklevel=2)
        self._x = x0
        num = self.num_cars
        self._race_status = RaceStatus(*(np.asarray(a) for a in RaceStatus.start(num, np.float64)))
        self._steps = 0
        self.agents = list(self.possible_agents)
        obs, floats, ints = (
            np.asarray(a)
            for a in _race_start(self._constants, self._layout, x0)
        )
        obs = obs.copy()  # writable
        self._position = ints[:, _INT_COLUMNS.index("position")]
        per_car = self._infos(floats.tolist(), ints.tolist(), with_terms=False)
        infos = {a: per_car[i] for i, a in enumerate(self.agents)}
        observations = {a: obs[self._index[a]] for a in self.agents}
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def _checked_actions(self, actions: Mapping[str, Any]) -> np.ndarray:
        """The live agents' normalised actions as ``(N, 2)`` (zero for cars no longer
        racing; clipped and scaled in the jitted step); raises on bad input before anything
        changes."""
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"actions must be a mapping {{agent: action}} (e.g. a dict), got {type(actions).__name__}"
            )
        live = self.agents
        if live and len(actions) == len(live) and all(agent in actions for agent in live):
            # The usual case in one go: every live agent acts with a finite (2,) action.
            raw = [actions[agent] for agent in live]
            normalised = None
            if all(map(_is_real, raw)):
                try:
                    normalised = np.array(raw, dtype=np.float64)
                except (TypeError, ValueError):
                    pass
            if (
                normalised is not None
                and normalised.shape == (len(live), 2)
                and all(map(math.isfinite, normalised.ravel().tolist()))
            ):
                if len(live) == self.num_cars:
                    return normalised
                actions_all = np.zeros((self.num_cars, 2))
                actions_all[[self._index[agent] for agent in live]] = normalised
                return actions_all
        self._refuse(actions)
        raise AssertionError("unreachable: _refuse raises on every input the fast path refuses")

    def _refuse(self, actions: Mapping[str, Any]) -> None:
        """Raise the error that explains why ``actions`` cannot be applied."""
        if not self.agents:
            raise RuntimeError("the race is over (or was never started): call reset() first")
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise KeyError(f"unknown agent(s) {unknown}; agents are {self.possible_agents}")
        retired = [a for a in actions if a not in self.agents]
        if retired:
            raise KeyError(f"agent(s) {retired} are no longer racing; live agents: {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"missing action(s) for {missing}; every live agent must act")
        for agent, action in actions.items():
            if not _is_real(action):
                raise TypeError(f"action of {agent} must hold real numbers (no strings or booleans), got {action!r}")
            a = np.asarray(action, dtype=np.float64)
            if a.shape != (2,):
                raise ValueError(f"action of {agent} must have shape (2,) (normalised [jx, jy]), got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"action of {agent} must be finite, got {a.tolist()}")

    def step(self, actions: Mapping[str, Any]):
        """Apply normalised jerk actions of all live agents for one time step."""
        normalised = self._checked_actions(actions)  # validates before anything changes
        out = _race_step(self._constants, self._layout, self._x, self._race_status, normalised, self._steps)
        self._steps += 1
        # np.asarray waits for each result; jax.device_get cost about 60 us more per step.
        x, obs, floats, ints = (np.asarray(a) for a in out)
        self._x = x
        obs = obs.copy()  # writable, as users may normalise observations in place
        self._race_status = self._status_from_rows(floats, ints)
        self._position = ints[:, _INT_COLUMNS.index("position")]

        floats, ints = floats.tolist(), ints.tolist()
        per_car = self._infos(floats, ints, with_terms=True)
        truncate = self._steps >= self.config.max_steps
        live = self.agents
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in live:
            i = self._index[agent]
            active = ints[i][0] == 1
            observations[agent] = obs[i]
            rewards[agent] = floats[i][1]
            terminations[agent] = not active
            truncations[agent] = truncate and active
            infos[agent] = per_car[i]
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    # --- bookkeeping ----------------------------------------------------------------------
    def _status_from_rows(self, floats: np.ndarray, ints: np.ndarray) -> RaceStatus:
        """The race's status from the packed rows of :func:`_per_car_rows`."""
        num = self.num_cars
        flag = lambda name: ints[:, _INT_COLUMNS.index(name)]  # noqa: E731
        value = lambda name: floats[:, _FLOAT_COLUMNS.index(name)]  # noqa: E731
        last = len(_INT_COLUMNS) + num * _PAIR_INTS.index("last_contact")
        return RaceStatus(
            active=flag("active").astype(bool), finished=flag("finished").astype(bool), out=flag("out").astype(bool),
            place=flag("place"), finish_time=value("finish_time"), penalty=value("penalty"), faults=flag("faults"),
            serving=value("serving"), last_contact=ints[:, last:last + num], last_move=flag("last_move"),
            direction_changes=flag("direction_changes"))

    @property
    def _active(self) -> np.ndarray:
        return self._race_status.active

    @property
    def _finished(self) -> np.ndarray:
        return self._race_status.finished

    @property
    def _out(self) -> np.ndarray:
        return self._race_status.out

    def _infos(self, floats: list[list[float]], ints: list[list[int]], with_terms: bool) -> list[dict[str, Any]]:
        """Every car's info dict from the rows of :func:`_per_car_rows` as Python lists
        (element-wise indexing of NumPy arrays took more time than the physics step's own
        Python side)."""
        s = self._x[:, S].tolist()
        names = self.possible_agents
        num, terms_at = self.num_cars, slice(2, 2 + len(REWARD_TERMS))
        pair = {name: len(_INT_COLUMNS) + num * k for k, name in enumerate(_PAIR_INTS)}
        per_car = []
        for i in range(num):
            row, values = ints[i], floats[i]
            finish_time, penalty, closing = values[0], values[2 + len(REWARD_TERMS)], values[len(_FLOAT_COLUMNS):]
            _, finished, out, _, position, collided, outside, lap, faults = row[:_INT_COLUMNS.index("faults") + 1]
            contact = row[pair["contact"]:pair["contact"] + num]
            per_car.append(
                {
                    "s": s[i],
                    "lap": lap,
                    "position": position,
                    "collided": collided == 1,
                    "contact_with": [name for name, touching in zip(names, contact) if touching],
                    "off_track": outside == 1,
                    "finished": finished == 1,
                    # None until finished (not NaN: NaN != NaN breaks equality checks and JSON)
                    "finish_time": finish_time if finished else None,
                    "out": out == 1,
                    "penalty": penalty,
                    "faults": faults,
                    "incidents": [
                        {"with": names[j], "verdict": VERDICTS[row[pair["rule"] + j]],
                         "at_fault": row[pair["fault"] + j] == 1, "closing_speed": closing[j]}
                        for j in range(num) if row[pair["incident"] + j]],
                    "reward_terms": dict(zip(REWARD_TERMS, values[terms_at])) if with_terms else {},
                }
            )
        return per_car

    def state(self) -> np.ndarray:
        """Joint state ``(N, 6)`` = ``[s, V, n, chi, ax, ay]`` per car (a copy)."""
        return self._x.copy()

    @property
    def positions(self) -> np.ndarray:
        """Every car's race position after the last step, ``(N,)`` int (1 = leading; the
        finished cars by finish time plus penalties), including the cars no longer racing,
        whose last infos hold their position when they left (a copy)."""
        return self._position.copy()

    @property
    def active(self) -> np.ndarray:
        """Which cars are still racing, ``(N,)`` bool (a copy)."""
        return self._active.copy()

    @property
    def race_laps(self) -> int | None:
        """The race's laps when it is raced over laps (a closed track, no ``race_distance``),
        else None: a race over a distance, to :attr:`finish_s`."""
        if self.config.race_distance is not None or not self.track.closed:
            return None
        return int(self.config.laps)

    # --- rendering ------------------------------------------------------------------------
    @property
    def renderer(self):
        """The race's :class:`racing_env.render.Renderer` (made at first use, with the
        config's ``render_size`` and ``camera``)."""
        from racing_env.render import Renderer

        if self._renderer is None:
            self._renderer = Renderer(self.track, self.game.vehicles, size=self.config.render_size,
                                      camera=self.config.camera, laps=self.race_laps, finish_s=self.finish_s,
                                      follow_car=self.config.follow_car)
        return self._renderer

    def scene(self, labels=None, plans=None):
        """What a frame of the race now shows (:class:`racing_env.render.Scene`): the joint
        state, time, each car's status and position, ``labels`` (default: the agents'
        names) and ``plans`` (per car: None or its plan ``(H, N, 2)`` of ``[s, n]``)."""
        from racing_env.render import Scene, car_status

        return Scene(x=self._x.copy(), time=self._steps * self.config.dt,
                     status=car_status(self._finished, self._out), position=self._position.copy(),
                     labels=tuple(self.possible_agents) if labels is None else tuple(labels), plans=plans)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        frame = self.renderer.draw(self.scene())
        if self.render_mode == "human":
            self._renderer.show(frame)
            return None
        return frame

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def parallel_env(**config: Any) -> RacingParallelEnv:
    """Create a ``RacingParallelEnv`` from :class:`racing_env.config.RaceConfig` keyword
    arguments, e.g. ``parallel_env(track="trefoil", num_agents=2, laps=1)``.

    ``env.game`` is the race's game, which planners racing in the env use. Its cost weights
    are ``weights``; left out, every car has the racing jerk weight
    :data:`racing_env.costs.RACING_JERK_WEIGHT` (0.01), as in tournaments, sweeps and
    training, and the other ``CostWeights`` at their defaults. Pass
    ``weights=CostWeights(...)`` (one for all cars, or one per car) to plan with others.
    Guide: docs/env.md."""
    return RacingParallelEnv(RaceConfig(**config))
