"""B races in one compiled call: a Gymnasium ``VectorEnv`` and a gymnax-style face.

:class:`RaceVectorEnv` is the vectorised form of :class:`racing_env.RaceEnv` (one learner
against opponents), made by::

    envs = gymnasium.make_vec("racing_env/Race-v0", num_envs=1024, vectorization_mode="vector_entry_point",
                              opponents=["lane-keeping"], track="trefoil")

with the keyword arguments of ``gymnasium.make`` (the :class:`racing_env.RaceConfig` fields,
``opponents``, ``learner``). Every step advances all B races with one jitted, vmapped call of
the race core (:mod:`racing_env.race`). Observations are ``(B, O)`` float32, actions ``(B, 2)``
normalised jerks (clipped to ``[-1, 1]``), rewards ``(B,)`` and the flags ``(B,)`` bool.

Opponents, one per opponent car (in car order, skipping the learner; one entry is reused for
every opponent car; an agent's actions are rounded to float32, as the single agents round
theirs): the entries of :mod:`racing_env.opponents`, as ``gymnasium.make`` takes them
(``None``: a coasting car; an agent spec such as ``"lane-keeping"``,
``"ilqgame-fb:replan_every=5"``, ``"rl:PATH"``; a list of specs: a pool, each race draws its
driver at every reset; an agent factory such as ``FeedbackGameAgent``; a plain callable
policy), or an object with the batched opponent interface
(:class:`planners.agents.batched.BatchedOpponent`). Specs are made by
:func:`planners.agents.batched.make_batched_opponent` and factories by
:func:`planners.agents.batched.batched_from_factory`: the scripted drivers become JAX
functions inside the compiled step, the planners one batched, warm-started solve per
re-plan for all races, before it. An agent object keeps one race's state: it is refused in
more than one race.

Autoreset (Gymnasium 1.x): ``autoreset_mode="next_step"`` (the default,
:attr:`gymnasium.vector.AutoresetMode.NEXT_STEP`): the step after a race ended resets it,
ignores its action and returns its start observation with reward 0 and both flags False.
``"same_step"``: a race that ends is reset within the same step; the observation returned is
the new race's, and the last one is in ``infos["final_obs"]`` (with ``infos["final_info"]``).

Seeding: ``reset(seed=s)`` gives race b the seed ``s + b`` (or ``seed=[s_0, ..., s_{B-1}]``),
and race b then runs exactly the episodes of ``gymnasium.make("racing_env/Race-v0", ...)``
reset with seed ``s + b`` and autoreset after, whatever B: every race carries its own JAX
key, and each episode's start is drawn from it (:mod:`racing_env.starts`) inside the
compiled step, for every scenario, as the single env draws its own. The states agree to a
few ulps rather than bit for bit: XLA:CPU evaluates sin and cos with a vectorised kernel
across races (docs/env.md).

:class:`GymnaxRace` is the same race for JAX learners as a gymnax environment (a subclass
of gymnax's ``Environment`` where gymnax is installed: ``reset(key, params)``, ``step(key,
state, action, params)`` with autoreset, pure functions that jit and vmap), with
JAX-function opponents inside the step, float32 at its face and JAX spaces (:class:`Box`).
Guides: docs/env.md, "Vectorised races (`racing_env.vector`)"; docs/rl.md, "Third-party
JAX learners".
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple, Sequence

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from racing_env import race
from racing_env.config import RaceConfig
from racing_env.env import RacingParallelEnv, agent_name
from racing_env.opponents import (
    LEARNER_OFF_TRACK,
    SHARED_AGENT_HINT,
    check_keywords,
    is_agent,
    is_factory,
    is_spec_list,
    learner_config,
    opponent_cars,
    planners_function,
)
from racing_env.packing import pack, unpack
from racing_env.precision import default_float, require_x64
from racing_env.race import RaceParams, RaceState
from racing_env.referee import REWARD_TERMS
from racing_env.single_agent import OpponentPool
from racing_env.starts import fresh_key, key_from_seed

__all__ = ["Box", "GYMNAX_INSTALLED", "GymnaxRace", "LEARNER_OFF_TRACK", "PlannedRace", "RaceVectorEnv", "SIX_VALUE_STEP", "coasting",
           "learner_action", "make_opponent"]

JaxPolicy = Callable[[jax.Array], jax.Array]
"""A JAX driver: ``policy(x (N, 6)) -> action (2,)``, normalised, for one car of one race."""

_AUTORESET = {"next_step": AutoresetMode.NEXT_STEP, "same_step": AutoresetMode.SAME_STEP}
_OPPONENT_FACTORY = "planners.agents.batched:make_batched_opponent"
_FROM_FACTORY = "planners.agents.batched:batched_from_factory"


def policy_action(policy: JaxPolicy, x: jax.Array, active: jax.Array) -> jax.Array:
    """A JAX driver's action ``(2,)`` at the joint state ``x (N, 6)``: a policy marked
    ``takes_racing`` (the racing-line driver's law, whose rules ignore the cars out of the
    race) is also handed the race's ``active (N,)`` flags, any other ``policy(x)`` alone."""
    if getattr(policy, "takes_racing", False):
        return policy(x, active)
    return policy(x)


def coasting(x: jax.Array) -> jax.Array:
    """The coasting driver as a JAX policy: zero jerk (keeps its accelerations)."""
    return jnp.zeros(2, x.dtype)


class _JaxOpponent:
    """A stateless JAX driver of one car, run inside the compiled step."""

    def __init__(self, policy: JaxPolicy, index: int, num_races: int, spec: str = "coasting") -> None:
        self.jax_policy, self.index, self.num_races, self.spec = policy, index, num_races, spec

    def reset(self, races: np.ndarray, seeds: np.ndarray) -> None:
        pass

    def act(self, observations, x, racing):  # pragma: no cover - the env fuses jax_policy instead
        return np.asarray(jax.vmap(self.jax_policy)(jnp.asarray(x))), {}


class _LoopedCallable:
    """A plain ``policy(observation, joint_state) -> action`` (as :class:`racing_env.RaceEnv`
    takes) called once per race: correct for any callable, and as slow as B single envs."""

    jax_policy = None

    def __init__(self, policy: Callable, index: int, num_races: int) -> None:
        self.policy, self.index, self.num_races = policy, index, num_races
        self.spec = getattr(policy, "name", getattr(policy, "__name__", "policy"))

    def reset(self, races: np.ndarray, seeds: np.ndarray) -> None:
        pass

    def act(self, observations: np.ndarray, x: np.ndarray, racing: np.ndarray):
        actions = np.array([np.asarray(self.policy(o, s), dtype=np.float64) for o, s in zip(observations, x)])
        return actions.reshape(self.num_races, 2), {}


def make_opponent(opponent: Any, game, index: int, num_races: int):
    """The batched driver of car ``index`` in ``num_races`` races from an ``opponents`` entry
    of :class:`RaceVectorEnv` (see the module docstring and :mod:`racing_env.opponents`);
    ``game``: the races' :class:`RaceGame` or an env that has it.

    Raises ``ValueError`` for an agent object in more than one race (it keeps one race's
    state: a spec or a factory makes one per race) and for an entry of no known kind."""
    if opponent is None:
        return _JaxOpponent(coasting, index, num_races)
    if isinstance(opponent, str) or is_spec_list(opponent):
        # specs name the planners' agents: made by the planners package, looked up by name so
        # that importing racing_env never imports it
        return planners_function(_OPPONENT_FACTORY)(list(opponent) if not isinstance(opponent, str) else opponent,
                                                    game, index, num_races)
    if callable(getattr(opponent, "act", None)) and callable(getattr(opponent, "reset", None)) \
            and hasattr(opponent, "num_races"):
        if opponent.num_races != num_races or opponent.index != index:
            raise ValueError(f"a batched opponent for car {opponent.index} of {opponent.num_races} races cannot "
                             f"drive car {index} of {num_races} races")
        return opponent
    if is_factory(opponent):
        return planners_function(_FROM_FACTORY)(opponent, game, index, num_races)
    if is_agent(opponent):
        if num_races > 1:
            raise ValueError(f"the agent object {opponent!r} of car {index} keeps the state of one race and cannot "
                             f"drive {num_races}; {SHARED_AGENT_HINT}")
        return planners_function(_FROM_FACTORY)(lambda: opponent, game, index, num_races)
    if isinstance(opponent, OpponentPool):
        raise ValueError("an OpponentPool is the single env's; a batch of races takes a list of specs as its pool, "
                         "e.g. [\"lane-keeping\", \"ilqgame-fb\"]")
    if callable(opponent):
        return _LoopedCallable(opponent, index, num_races)
    raise ValueError(f"an opponent must be None, an agent spec (str), a list of specs (a pool), a batched "
                     f"opponent, an agent factory or a callable policy(observation, joint_state); got {opponent!r}")


VECTOR_KEYWORDS = ("num_envs", "autoreset_mode", "max_episode_steps", "disable_env_checker")
"""The keywords :class:`RaceVectorEnv` takes besides the learner faces' (:mod:`racing_env.opponents`)."""


class RaceVectorEnv(VectorEnv):
    """B races of one learner (``car_<learner>``) against opponents, stepped in one compiled call.

    Args:
        num_envs: the number of races B (>= 1).
        opponents: one entry per opponent car, or one for all (module docstring); default:
            coasting cars (one when ``num_agents`` is not given).
        learner: index of the learner's car.
        autoreset_mode: ``"next_step"`` (default) or ``"same_step"`` (module docstring).
        max_episode_steps: accepted from ``gymnasium.make_vec`` only when None: a race's
            length is ``max_steps``.
        disable_env_checker: Gymnasium's keyword, accepted and without effect: ``make_vec``
            wraps no checker around a vector entry point.
        **config: :class:`racing_env.RaceConfig` fields (``render_mode`` must be None); as in
            :class:`racing_env.RaceEnv`, ``on_off_track`` defaults to :data:`LEARNER_OFF_TRACK`
            (``terminate``). Any other keyword is refused (``TypeError``, naming the allowed
            ones).

    ``infos`` hold, per race, the learner's ``s``, ``lap``, ``position``, ``collided``,
    ``off_track``, ``finished``, ``finish_time`` (NaN until finished), ``out`` and
    ``reward_terms`` (a dict of arrays), and ``infos["opponents"][agent][name]`` the batched
    opponents' diagnostics (a planner's ``replanned``, ``converged``, ``iterations``,
    ``fallback``).
    """

    def __init__(
        self,
        num_envs: int = 1,
        opponents: Sequence[Any] | None = None,
        learner: int = 0,
        autoreset_mode: str | AutoresetMode = "next_step",
        max_episode_steps: int | None = None,
        disable_env_checker: bool | None = None,
        **config: Any,
    ) -> None:
        check_keywords(config, "racing_env/Race-v0 (RaceVectorEnv)", own=VECTOR_KEYWORDS)
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if max_episode_steps is not None:
            raise ValueError("the race's length is max_steps (a RaceConfig field), not max_episode_steps")
        modes = {**_AUTORESET, **{mode: mode for mode in _AUTORESET.values()}}
        if autoreset_mode not in modes:
            raise ValueError(f"autoreset_mode must be one of {sorted(_AUTORESET)}, got {autoreset_mode!r}")
        if config.get("render_mode") is not None:
            raise ValueError("the vectorised env does not render: race a recorded start in racing_env.parallel_env")
        self.num_envs = int(num_envs)
        self.autoreset_mode = modes[autoreset_mode]
        self.metadata = {"autoreset_mode": self.autoreset_mode}
        num, drivers = opponent_cars(opponents, learner, config)
        # one race built the usual way: its checks, its game and its params serve every race
        self.race = RacingParallelEnv(RaceConfig(num_agents=num, **learner_config(config)))
        self.config, self.game, self.params = self.race.config, self.race.game, self.race.params
        self.learner = int(learner)
        self.num_cars = num
        # the race env (not just its game): a trained model finds the units of its observations
        self.opponents = {j: make_opponent(o, self.race, j, self.num_envs) for j, o in drivers}
        self._jax_cars = tuple(j for j, o in self.opponents.items() if o.jax_policy is not None)
        self._host_cars = tuple(j for j, o in self.opponents.items() if o.jax_policy is None)
        learner_agent = agent_name(self.learner)
        self.single_observation_space = self.race.observation_space(learner_agent)
        self.single_action_space = self.race.action_space(learner_agent)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        # the params as one flat array: a call then pays for one argument leaf, not dozens
        constants, layout = pack(self.params)
        shardings = _race_shardings(self.num_envs)
        self._constants = constants if shardings is None else jax.device_put(constants, shardings[1])
        self._step = _compile_step(tuple(self.opponents[j].jax_policy for j in self._jax_cars), self._jax_cars,
                                   self.learner, self.autoreset_mode == AutoresetMode.SAME_STEP, layout, shardings)
        self._start = _compile_start(self.learner, layout, shardings)
        self._keys: jax.Array | None = None  # (B, 2) uint32: each race's key (racing_env.starts)
        self._state: RaceState | None = None
        self._obs_all = None
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)

    # --- starts ----------------------------------------------------------------------------
    def _seed_keys(self, seed: int | Sequence[int] | None) -> None:
        """Each race's key from ``seed`` (race b: ``seed + b``, or the b-th of B seeds)."""
        if seed is None:
            keys = [fresh_key() for _ in range(self.num_envs)]
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            keys = [key_from_seed(int(seed) + b) for b in range(self.num_envs)]
        elif isinstance(seed, Sequence) and len(seed) == self.num_envs:
            keys = [key_from_seed(s) for s in seed]
        else:
            raise ValueError(f"seed must be None, an int or {self.num_envs} ints, got {seed!r}")
        self._keys = jnp.asarray(np.stack(keys))

    # --- episode ---------------------------------------------------------------------------
    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None):
        """Start every race (or those of ``options["reset_mask"]`` (B,) bool). ``options`` may
        hold ``x0``: start states ``(B, N, 6)``, or ``(N, 6)`` for every race."""
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, dtype=bool)), dtype=bool)
        if mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask'] must have shape ({self.num_envs},), got {mask.shape}")
        x0_given = options.pop("x0", None)
        if options:
            raise ValueError(f"unknown reset options {sorted(options)}; allowed: ['reset_mask', 'x0']")
        if self._state is None and not mask.all():
            raise RuntimeError("the first reset must start every race (no reset_mask)")
        given = x0_given is not None
        if given:
            x0_given = np.broadcast_to(np.asarray(x0_given, dtype=np.float64), (self.num_envs, self.num_cars, 6))
            if not np.all(np.isfinite(x0_given)):
                raise ValueError("options['x0'] must be finite")
        else:
            x0_given = np.zeros((self.num_envs, self.num_cars, 6))
        if seed is not None or self._keys is None:
            self._seed_keys(seed)
        keys, state, obs_all, _, ints, floats, seeds, free = self._start(self._keys, mask, x0_given, given,
                                                                         self._constants)
        if not given:
            if not np.asarray(free)[mask].all():
                raise ValueError(f"scenario {self.config.scenario!r} found no start without overlapping cars")
            # as the single env's reset: a jittered grid may reach the finish line
            race.check_starts_behind(self.race.finish_s, np.asarray(state.x)[mask].reshape(-1, 6),
                                     self.config.scenario)
        self._keys = keys
        seeds = np.asarray(seeds).astype(np.int64)
        for opponent in self.opponents.values():
            opponent.reset(mask, seeds)
        if self._state is None:
            self._state, self._obs_all = state, obs_all
        else:
            keep = jnp.asarray(~mask)
            self._state = jax.tree_util.tree_map(
                lambda old, new: jnp.where(keep.reshape((-1,) + (1,) * (new.ndim - 1)), old, new), self._state, state)
            self._obs_all = jnp.where(keep[:, None, None], self._obs_all, obs_all)
        self._needs_reset = np.where(mask, False, self._needs_reset)
        obs = np.array(self._obs_all[:, self.learner])
        infos = self._infos(np.asarray(ints), np.asarray(floats), {}, with_terms=False)
        # infos describe the races that were reset (Gymnasium's masks)
        infos.update({key: value & mask for key, value in infos.items() if key.startswith("_")})
        return obs, infos

    def state(self) -> np.ndarray:
        """The joint states of the races, ``(B, N, 6)`` (a copy), as
        :meth:`racing_env.RacingParallelEnv.state` gives one race's."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return np.array(self._state.x)

    def _checked_actions(self, actions: Any) -> np.ndarray:
        """The learner's actions as ``(B, 2)`` float64; raises before anything changes."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        array = np.asarray(actions)
        if array.dtype.kind not in "fiu":
            raise TypeError(f"actions must be real numbers (B, 2) = ({self.num_envs}, 2), got dtype {array.dtype}")
        if array.shape != (self.num_envs, 2):
            raise ValueError(f"actions must have shape (num_envs, 2) = ({self.num_envs}, 2), got {array.shape}")
        array = array.astype(np.float64)
        if not np.isfinite(array).all():
            bad = np.flatnonzero(~np.isfinite(array).all(axis=1)).tolist()
            raise ValueError(f"actions must be finite; races {bad[:10]} have NaN or inf")
        return array

    def _host_actions(self, obs_all: np.ndarray, x: np.ndarray, racing: np.ndarray) -> list[tuple[int, tuple]]:
        """``(car, (actions, diagnostics))`` of every host-side opponent, in car order. Opponents
        of one class with ``act_together`` (the batched planners: a field's re-plans in one
        solve) act in one call of it; the others one by one."""
        by_class: dict[type, list[int]] = {}
        for j in self._host_cars:
            by_class.setdefault(type(self.opponents[j]), []).append(j)
        out = {}
        for cls, cars in by_class.items():
            together = getattr(cls, "act_together", None)
            if together is None or len(cars) == 1:
                out.update({j: self.opponents[j].act(obs_all[:, j], x, racing) for j in cars})
            else:
                results = together([self.opponents[j] for j in cars], [obs_all[:, j] for j in cars], x, racing)
                out.update(zip(cars, results))
        return [(j, out[j]) for j in self._host_cars]

    def step(self, actions: Any):
        learner_actions = self._checked_actions(actions)
        resetting = self._needs_reset.copy()
        all_actions = np.zeros((self.num_envs, self.num_cars, 2))
        all_actions[:, self.learner] = learner_actions
        diagnostics: dict[str, dict[str, np.ndarray]] = {}
        if self._host_cars:
            x = np.asarray(self._state.x)
            # a car no longer racing in a race gets no action there (the core ignores it)
            racing = np.asarray(self._state.status.active)
            obs_all = np.asarray(self._obs_all)
            for j, (act, diag) in self._host_actions(obs_all, x, racing):
                # an agent's actions are float32 (planners.agents.BaseAgent), a plain callable's as given
                all_actions[:, j] = act if isinstance(self.opponents[j], _LoopedCallable) else np.float32(act)
                diagnostics[agent_name(j)] = {k: np.asarray(v) for k, v in diag.items()}
        out = self._step(self._state, self._keys, all_actions, resetting, self._constants)
        self._state, self._keys, self._obs_all, obs, reward, ints, floats, seeds, final = out
        obs, reward, ints, floats = np.array(obs), np.asarray(reward), np.asarray(ints), np.asarray(floats)
        terminated, truncated = ints[:, 7].astype(bool), ints[:, 8].astype(bool)
        infos = self._infos(ints, floats, diagnostics, with_terms=True)
        done = terminated | truncated
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        # the races that began a new episode in this step: their opponents start it afresh
        restarted = done if same_step else resetting
        if restarted.any() and self._host_cars:
            for j in self._host_cars:
                self.opponents[j].reset(restarted, np.asarray(seeds).astype(np.int64))
        if not same_step:
            self._needs_reset = done
        elif done.any():
            final_obs, final_ints, final_floats = (np.asarray(a) for a in final)
            infos["final_obs"] = np.full(self.num_envs, None, dtype=object)
            for b in np.flatnonzero(done):
                infos["final_obs"][b] = final_obs[b]
            infos["_final_obs"] = done
            infos["final_info"] = self._infos(final_ints, final_floats, diagnostics, with_terms=True)
            infos["_final_info"] = done
        return obs, reward, terminated, truncated, infos

    def _infos(self, ints: np.ndarray, floats: np.ndarray, diagnostics: dict, with_terms: bool) -> dict[str, Any]:
        """The learner's infos from the packed rows of :func:`_learner_rows` (with ``_key``
        masks, Gymnasium's vector convention)."""
        every = np.ones(self.num_envs, dtype=bool)
        finished = ints[:, 4].astype(bool)
        infos: dict[str, Any] = {
            "s": floats[:, 0],
            "lap": ints[:, 0],
            "position": ints[:, 1],
            "collided": ints[:, 2].astype(bool),
            "off_track": ints[:, 3].astype(bool),
            "finished": finished,
            "out": ints[:, 5].astype(bool),
            "finish_time": floats[:, 1],
            "faults": ints[:, 9],
            "penalty": floats[:, 2 + len(REWARD_TERMS)],
        }
        masks = {f"_{key}": every for key in infos}
        masks["_finish_time"] = finished
        if with_terms:
            infos["reward_terms"] = {name: floats[:, 2 + k] for k, name in enumerate(REWARD_TERMS)}
            masks["_reward_terms"] = every
        if diagnostics:
            infos["opponents"] = diagnostics
            masks["_opponents"] = every
        return {**infos, **masks}

    def close_extras(self, **kwargs: Any) -> None:
        self.race.close()


# --- the compiled calls ------------------------------------------------------------------------
def _learner_rows(state: RaceState, info: race.RaceInfo, learner: int, terminated, truncated):
    """The learner's per-race results as two arrays: int32 ``(B, 10)`` lap, position, collided,
    off_track, finished, out, active, terminated, truncated, faults; float64 ``(B, 11)`` s,
    finish_time, the reward terms and the time penalty."""
    status = state.status
    ints = jnp.stack([info.lap[:, learner], info.position[:, learner], info.collided[:, learner],
                      info.off_track[:, learner], status.finished[:, learner], status.out[:, learner],
                      status.active[:, learner], terminated, truncated, status.faults[:, learner]],
                     axis=1).astype(jnp.int32)
    floats = jnp.concatenate([info.s[:, learner, None], status.finish_time[:, learner, None],
                              info.terms[:, learner], status.penalty[:, learner, None]], axis=1)
    return ints, floats


def _select(mask: jax.Array, a, b):
    """Per race (axis 0): ``a`` where ``mask`` else ``b``, for every leaf."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)


def _restarted(restart: jax.Array, keys: jax.Array, params: RaceParams, fresh: tuple) -> tuple:
    """``fresh = (state, obs_all, info)`` of B races with the races ``restart (B,)`` replaced by
    the next episodes of their keys ``keys (B, 2)``: ``(races, keys, episode seeds (B,))``.

    The restarting races are drawn and raced in batches of :func:`restart_batch` races,
    scattered back, as many batches as needed (none in a step where no race restarts): a
    step pays for the races that restart, not for all B.
    """
    num = restart.shape[0]
    size = restart_batch(num)

    def next_batch(carry):
        races, keys, seeds, pending = carry
        rows = jnp.nonzero(pending, size=size, fill_value=num)[0]  # num: no race (dropped below)
        carried, x0, _, drawn = jax.vmap(race.next_start, in_axes=(0, None))(keys[jnp.minimum(rows, num - 1)], params)
        started = jax.vmap(race.start, in_axes=(0, None))(x0, params)
        put = lambda into, new: into.at[rows].set(new, mode="drop")
        return (jax.tree_util.tree_map(put, races, started), put(keys, carried), put(seeds, drawn),
                put(pending, jnp.zeros(size, bool)))

    seeds = jnp.zeros(num, jnp.int32)
    races, keys, seeds, _ = jax.lax.while_loop(lambda carry: carry[3].any(), next_batch,
                                               (fresh, keys, seeds, restart))
    return races, keys, seeds


def restart_batch(num_races: int) -> int:
    """How many of ``num_races`` races a step restarts per batch (:func:`_restarted`): an
    eighth of them, which covers the episode ends of races a few dozen steps long in one
    batch."""
    return max(1, -(-num_races // 8))


def _race_shardings(num_races: int):
    """``(per_race, replicated)`` shardings that split the races evenly over the local
    accelerators, or None on one device, on CPUs and when the devices do not divide
    ``num_races``. The races never interact, so the split needs no communication; on a CPU
    split into one device per core (:func:`planners.devices.use_cpu_cores`) it made the step
    slower at every batch size (docs/performance.md), so CPU races stay on one device."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.local_devices()
    if len(devices) < 2 or num_races % len(devices) or devices[0].platform == "cpu":
        return None
    mesh = Mesh(np.asarray(devices), ("races",))
    return NamedSharding(mesh, PartitionSpec("races")), NamedSharding(mesh, PartitionSpec())


def _jit(fn, shardings, races: int, shared: int):
    """``jax.jit(fn)``; with ``shardings``, its first ``races`` arguments split by race and the
    next ``shared`` replicated, every output split by race."""
    if shardings is None:
        return jax.jit(fn)
    per_race, replicated = shardings
    return jax.jit(fn, in_shardings=(per_race,) * races + (replicated,) * shared, out_shardings=per_race)


@functools.lru_cache(maxsize=None)
def _compile_start(learner: int, layout, shardings):
    def start(keys, mask, x0_given, given, constants):
        """The next episodes of the races ``mask (B,)`` (their keys carried on), from
        ``x0_given (B, N, 6)`` when ``given``, else drawn; every race's start state."""
        params = unpack(constants, layout)
        carried, x0, free, seeds = jax.vmap(race.next_start, in_axes=(0, None))(keys, params)
        x0 = jnp.where(given, x0_given, x0)
        state, obs_all, info = jax.vmap(race.start, in_axes=(0, None))(x0, params)
        none = jnp.zeros(x0.shape[0], dtype=bool)
        ints, floats = _learner_rows(state, info, learner, none, none)
        keys = _select(mask, carried, keys)
        return keys, state, obs_all, obs_all[:, learner], ints, floats, seeds, free

    return _jit(start, shardings, races=3, shared=2)


@functools.lru_cache(maxsize=None)
def _compile_step(policies: tuple, cars: tuple[int, ...], learner: int, same_step: bool, layout, shardings):
    """The jitted step of B races: JAX opponents' actions, the race core, autoreset (the
    races that restart draw their next starts from their keys, :mod:`racing_env.starts`)."""

    def step(state: RaceState, keys, actions, resetting, constants):
        params = unpack(constants, layout)
        for policy, car in zip(policies, cars):
            # rounded to float32, as the single agents round their actions
            own = jax.vmap(functools.partial(policy_action, policy))(state.x, state.status.active)
            actions = actions.at[:, car].set(own.astype(jnp.float32).astype(actions.dtype))
        stepped, obs_all, rewards, terms, truncs, info = jax.vmap(race.step, in_axes=(None, 0, 0, None))(
            None, state, actions, params)
        terminated = terms[:, learner] & state.status.active[:, learner]
        truncated = truncs[:, learner]
        done = terminated | truncated
        restart = done if same_step else resetting
        # the races that restart draw their starts from their keys (only those races)
        (new_state, new_obs_all, new_info), keys, seeds = _restarted(restart, keys, params,
                                                                     (stepped, obs_all, info))
        if same_step:
            ints, floats = _learner_rows(stepped, info, learner, terminated, truncated)
            final = (obs_all[:, learner], ints, floats)
            reward = rewards[:, learner]
        else:
            final = ()
            terminated, truncated = terminated & ~resetting, truncated & ~resetting
            ints, floats = _learner_rows(new_state, new_info, learner, terminated, truncated)
            reward = jnp.where(resetting, 0.0, rewards[:, learner])
        return new_state, keys, new_obs_all, new_obs_all[:, learner], reward, ints, floats, seeds, final

    return _jit(step, shardings, races=4, shared=1)


# --- the gymnax face ---------------------------------------------------------------------------
try:  # gymnax is optional: where it is installed, GymnaxRace is one of its environments
    from gymnax.environments import environment as _gymnax_environment
    from gymnax.environments import spaces as _gymnax_spaces
except ImportError:  # pragma: no cover - exercised in an environment without gymnax
    _gymnax_environment = _gymnax_spaces = None

GYMNAX_INSTALLED = _gymnax_environment is not None
"""Whether gymnax is importable: :class:`GymnaxRace` then subclasses its ``Environment``."""

SIX_VALUE_STEP = GYMNAX_INSTALLED and hasattr(_gymnax_environment.Environment, "is_truncated")
"""Whether the installed gymnax's ``step`` returns six values ``(obs, state, reward,
terminated, truncated, info)`` (gymnax 1.x) rather than five ``(obs, state, reward, done,
info)`` (gymnax 0.0.x, and :class:`GymnaxRace` without gymnax)."""

_Environment = _gymnax_environment.Environment if GYMNAX_INSTALLED else object
_BoxBase = _gymnax_spaces.Box if GYMNAX_INSTALLED else object


def _check_key(key: Any, what: str) -> None:
    """Raise ``TypeError`` unless ``key`` is a JAX random key (a typed key, or a raw uint32
    key array such as ``jax.random.PRNGKey(0)``), eager or traced."""
    hint = f"{what} needs a JAX random key: pass one, e.g. {what}(jax.random.key(0)) or a split of your key"
    if key is None:
        raise TypeError(f"{hint} (got none)")
    dtype = getattr(key, "dtype", None)
    if dtype is None or isinstance(key, (bool, int, float, np.generic)):
        raise TypeError(f"{hint}; got {key!r}")
    if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        return
    if dtype != jnp.uint32 or np.ndim(key) != 1:
        raise TypeError(f"{hint}; got an array of {dtype} with shape {np.shape(key)}")


class Box(_BoxBase):
    """A box of arrays for JAX learners: ``sample(key)`` and ``contains(x)`` are JAX functions
    (eager, under ``jit`` and under ``vmap``).

    Where gymnax is installed this is a ``gymnax.environments.spaces.Box`` (gymnax's wrappers
    and learners that check for one accept it); without gymnax it stands alone with the same
    attributes.

    Args:
        low, high: the bounds, finite, broadcast to ``shape``.
        shape: the arrays' shape.
        dtype: the arrays' dtype (float32 for the race's observations and actions).
    """

    def __init__(self, low: Any, high: Any, shape: Sequence[int], dtype: Any = jnp.float32) -> None:
        self.shape = tuple(int(d) for d in shape)
        self.dtype = np.dtype(dtype)
        self.low = np.broadcast_to(np.asarray(low, self.dtype), self.shape).copy()
        self.high = np.broadcast_to(np.asarray(high, self.dtype), self.shape).copy()
        if not (np.all(np.isfinite(self.low)) and np.all(np.isfinite(self.high)) and np.all(self.low <= self.high)):
            raise ValueError("a Box needs finite bounds with low <= high")

    def __repr__(self) -> str:
        return f"Box(shape={self.shape}, dtype={self.dtype.name}, low={self.low.min():g}, high={self.high.max():g})"

    def sample(self, key: jax.Array | None = None) -> jax.Array:
        """An array drawn uniformly from the box with ``key`` (a JAX random key; required)."""
        _check_key(key, "Box.sample")
        u = jax.random.uniform(key, self.shape, jnp.float32)
        # low (1 - u) + high u: finite for bounds near float32's limits, where high - low overflows
        low, high = jnp.asarray(self.low, jnp.float32), jnp.asarray(self.high, jnp.float32)
        return jnp.clip(low * (1.0 - u) + high * u, low, high).astype(self.dtype)

    def contains(self, x: jax.Array) -> jax.Array:
        """Whether ``x`` has the box's shape and lies inside its bounds (a bool scalar)."""
        if np.shape(x) != self.shape:
            return jnp.asarray(False)
        return jnp.all((x >= self.low) & (x <= self.high))


def _is_jax_policy(policy: Any, state_shape: tuple[int, ...]) -> bool:
    """Whether ``policy`` traces as a JAX function of the joint state to an action ``(2,)``."""
    if policy is None or not callable(policy):
        return False
    try:
        out = jax.eval_shape(policy, jax.ShapeDtypeStruct(state_shape, default_float()))
    except Exception:  # noqa: BLE001 - anything that does not trace (NumPy code, wrong arguments)
        return False
    return getattr(out, "shape", None) == (2,)


def learner_action(action: Any) -> jax.Array:
    """The learner's action of one race as a JAX array ``(2,)`` (normalised jerks ``[jx,
    jy]``): checked when the step is traced, so a jitted or vmapped step refuses a wrong
    action before it runs.

    Raises:
        TypeError: the action is not an array of real numbers (a bool, complex or string
            dtype).
        ValueError: its shape is not ``(2,)`` (a scalar is not broadcast; a batch of races
            is stepped by ``vmap`` over the step).
    """
    dtype = getattr(action, "dtype", None)
    if dtype is None:
        dtype = np.asarray(action).dtype
    if dtype == np.bool_ or not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
        raise TypeError(f"the learner's action must be an array of real numbers of shape (2,) (normalised jerks "
                        f"[jx, jy]), got dtype {dtype}")
    if np.shape(action) != (2,):
        raise ValueError(f"the learner's action must have shape (2,) (normalised jerks [jx, jy] of one race; "
                         f"vmap the step over races), got shape {np.shape(action)}")
    return jnp.asarray(action)


class GymnaxRace(_Environment):
    """One learner against JAX opponents, as a gymnax environment.

    Where gymnax is installed this subclasses ``gymnax.environments.environment.Environment``
    and implements its ``reset_env``/``step_env``: the installed gymnax supplies ``reset`` and
    ``step`` (jitted, with its autoreset) and its wrappers (``LogWrapper``,
    ``FlattenObservationWrapper``) apply. gymnax 0.0.x's ``step(key, state, action, params)``
    returns ``(obs, state, reward, done, info)``; gymnax 1.x's returns ``(obs, state, reward,
    terminated, truncated, info)`` and adds ``info["final_observation"]``
    (:data:`SIX_VALUE_STEP` says which). Without gymnax, ``reset(key, params) -> (obs,
    state)`` and ``step`` are this class's own, in the five-value form. Whichever:

    * ``done`` (``terminated | truncated``) marks the step that ended the learner's race, and
      ``obs`` is then the new race's (the race is reset within the step);
    * ``info`` holds ``terminated``, ``truncated`` and the learner's ``position`` (int32),
      ``finished``, ``out`` (retired), ``finish_time`` (float32 [s], NaN until finished),
      whether it ``collided`` or was ``off_track`` in the step, and ``nonfinite_action``;
    * the learner's action is one race's ``(2,)``, finite values clipped to ``[-1, 1]``; a
      wrong shape or dtype is refused when the step is traced (:func:`learner_action`), and
      an action with a NaN or inf is replaced by zero jerk, with ``info["nonfinite_action"]``
      True (the race goes on as if the learner had not acted);
    * observations ``(O,)``, rewards and float info fields are float32 whatever
      ``jax_enable_x64`` says (the race itself runs in JAX's widest float: float64 with x64
      on, float32 with it off);
    * the spaces are :class:`Box` (JAX ``sample(key)``), ``default_params`` are the race's
      :class:`racing_env.race.RaceParams` (``max_steps_in_episode`` is ``max_steps``), and
      params of another race (other cars, track or shapes) are refused.

    :meth:`race_step` is the five-value step whatever gymnax is installed. Starts are drawn
    with :func:`racing_env.race.draw_start` from the race's scenario (any of them).

    Args:
        opponents: one :data:`JaxPolicy` per opponent car (or one for all); default coasting.
            A batched opponent made from a spec (``"lane-keeping"``) carries its JAX policy
            as ``jax_policy``. Planners (``"ilqgame-fb:iterations=2"``, ``ilqgame-ol``,
            ``ilqgame-leader``, ``ilqgame-follower``, ``ilqr`` with the constant-velocity
            prediction) race with their compiled step
            (:mod:`planners.agents.compiled_planner`): their plans are then part of the
            state (:class:`PlannedRace`), a race that restarts re-plans cold in its first
            step, and their actions are the host batched planner's to rounding. They need
            ``jax_enable_x64`` on (their solver's tolerances assume float64).
        learner: index of the learner's car.
        **config: :class:`racing_env.RaceConfig` fields. One default differs from
            ``RaceConfig``'s: ``on_off_track`` is :data:`LEARNER_OFF_TRACK` (``terminate``: a car
            that leaves the track is out of its race), the rule ``racing train`` trains with.
            Under ``RaceConfig``'s ``penalty`` a learner that leaves the track is charged
            every step until ``max_steps``, and a standard learner never learns to stay on
            (docs/experiments/rl-third-party.md); pass ``on_off_track="penalty"`` for the
            tournaments' rule.
    """

    def __init__(self, opponents: Sequence[Any] | None = None, learner: int = 0, **config: Any) -> None:
        check_keywords(config, "GymnaxRace")
        num, drivers = opponent_cars(opponents, learner, config)
        self.race = RacingParallelEnv(RaceConfig(num_agents=num, **learner_config(config)))
        self.learner = int(learner)
        self._policies, self._planners = [], []
        for car, opponent in drivers:
            if isinstance(opponent, str) or is_factory(opponent) or is_agent(opponent):
                opponent = make_opponent(opponent, self.race.game, car, 1)
            planner = getattr(opponent, "jax_planner", None) if getattr(opponent, "jax_policy", None) is None else None
            if planner is not None:
                require_x64(f"the planner opponent {getattr(opponent, 'spec', opponent)!r} of car {car}")
                self._planners.append((car, planner))
                continue
            policy = getattr(opponent, "jax_policy", opponent) if opponent is not None else coasting
            if not _is_jax_policy(policy, self.race.state_space.shape):
                raise ValueError(f"opponent {opponent!r} of car {car} is neither a JAX policy x (N, 6) -> action (2,) "
                                 "nor a planner with a compiled step (ilqgame-fb, ilqgame-ol, ilqgame-leader, "
                                 "ilqgame-follower, ilqr with the constant-velocity prediction)")
            self._policies.append((car, policy))
        self.num_cars = num
        params = self.race.params
        self._structure = jax.tree_util.tree_structure(params)
        self._shapes = tuple(np.shape(leaf) for leaf in jax.tree_util.tree_leaves(params))
        learner_agent = agent_name(self.learner)
        observations, actions = self.race.observation_space(learner_agent), self.race.action_space(learner_agent)
        self._observation_space = Box(observations.low, observations.high, observations.shape, np.float32)
        self._action_space = Box(actions.low, actions.high, actions.shape, np.float32)

    @property
    def default_params(self) -> RaceParams:
        """The race's params (gymnax's ``max_steps_in_episode`` is their ``max_steps``)."""
        return self.race.params

    @property
    def name(self) -> str:
        return "racing_env/Race-v0"

    @property
    def num_actions(self) -> int:
        return 2

    def observation_space(self, params: RaceParams | None = None) -> Box:
        """The learner's observations: :class:`Box` of shape ``(O,)``, float32."""
        return self._observation_space

    def action_space(self, params: RaceParams | None = None) -> Box:
        """The learner's actions: normalised jerks, :class:`Box` ``[-1, 1]^2``, float32."""
        return self._action_space

    def _check_params(self, params: RaceParams) -> None:
        """Raise ``ValueError`` unless ``params`` are this race's (same structure, static
        fields and leaf shapes; their values may differ). Checked when traced."""
        if jax.tree_util.tree_structure(params) != self._structure:
            raise ValueError("params of another race (another track, scenario kind or structure): "
                             "pass this env's default_params, or a copy of them with other values")
        shapes = tuple(np.shape(leaf) for leaf in jax.tree_util.tree_leaves(params))
        if shapes != self._shapes:
            raise ValueError(f"params of another race (other shapes: another number of cars, track grid or "
                             f"preview); this race has {self.num_cars} cars: pass this env's default_params")
        if self._planners:
            require_x64("a GymnaxRace with planner opponents")

    def _with_plans(self, state: RaceState) -> RaceState | PlannedRace:
        """A race just started: with the planner opponents' plan states (no plan yet)."""
        if not self._planners:
            return state
        return PlannedRace(state, tuple(planner.initial(state.x.dtype) for _, planner in self._planners))

    def reset_env(self, key: jax.Array, params: RaceParams) -> tuple[jax.Array, RaceState | PlannedRace]:
        """A new race from a start drawn with ``key``: ``(learner's obs (O,) float32, state)``."""
        self._check_params(params)
        state, obs = race.reset(key, params)
        return obs[self.learner], self._with_plans(state)

    def _transition(self, key: jax.Array, state: RaceState | PlannedRace, action: jax.Array, params: RaceParams):
        """One step of the race, no reset: ``(obs (O,), state, reward, terminated, truncated,
        info)``, floats float32."""
        self._check_params(params)
        race_state, plans = (state.race, state.plans) if self._planners else (state, ())
        dtype = race_state.x.dtype
        action = learner_action(action)
        finite = jnp.all(jnp.isfinite(action))
        # a non-finite action is no action: zero jerk, flagged in the info
        action = jnp.where(finite, action, jnp.zeros_like(action))
        actions = jnp.zeros((self.num_cars, 2), dtype).at[self.learner].set(action.astype(dtype))
        for car, policy in self._policies:
            actions = actions.at[car].set(policy_action(policy, race_state.x, race_state.status.active).astype(dtype))
        planned = []
        for (car, planner), plan in zip(self._planners, plans):
            act, plan = planner.act(plan, race_state.x, race_state.status.active)
            # rounded to float32, as the agents round their actions
            actions = actions.at[car].set(act.astype(jnp.float32).astype(dtype))
            planned.append(plan)
        stepped, obs, rewards, terms, truncs, race_info = race.step(key, race_state, actions, params)
        info = {
            "terminated": terms[self.learner],
            "truncated": truncs[self.learner],
            "position": race_info.position[self.learner],
            "finished": stepped.status.finished[self.learner],
            "out": stepped.status.out[self.learner],
            "finish_time": stepped.status.finish_time[self.learner].astype(jnp.float32),
            "collided": race_info.collided[self.learner],
            "off_track": race_info.off_track[self.learner],
            "faults": stepped.status.faults[self.learner],
            "penalty": stepped.status.penalty[self.learner].astype(jnp.float32),
            "nonfinite_action": ~finite,
        }
        carried = PlannedRace(stepped, tuple(planned)) if self._planners else stepped
        return (obs[self.learner], carried, rewards[self.learner].astype(jnp.float32), info["terminated"],
                info["truncated"], info)

    def step_env(self, key: jax.Array, state: RaceState | PlannedRace, action: jax.Array, params: RaceParams):
        """gymnax's step without the reset: ``(obs, state, reward, flag, info)``; ``flag`` is
        ``terminated`` for gymnax 1.x (which asks :meth:`is_truncated` for the truncation)
        and ``done`` (``terminated | truncated``) otherwise."""
        obs, carried, reward, terminated, truncated, info = self._transition(key, state, action, params)
        return obs, carried, reward, terminated if SIX_VALUE_STEP else terminated | truncated, info

    def is_truncated(self, state: RaceState | PlannedRace, params: RaceParams) -> jax.Array:
        """Whether the learner's race in ``state`` (just stepped) was cut at ``max_steps``
        while the learner was still racing (gymnax 1.x's truncation)."""
        race_state = state.race if self._planners else state
        return race_state.status.active[self.learner] & (race_state.steps >= params.max_steps)

    def race_step(self, key: jax.Array, state: RaceState | PlannedRace, action: jax.Array,
                  params: RaceParams | None = None):
        """The step with autoreset in the five-value form, whatever gymnax is installed:
        ``(obs (O,), state, reward, done, info)`` (class docstring). Pure: jit and vmap it.
        ``key`` is split as gymnax splits it: the step's key, and the next race's."""
        params = self.default_params if params is None else params
        key_step, key_reset = jax.random.split(key)
        obs, stepped, reward, terminated, truncated, info = self._transition(key_step, state, action, params)
        done = terminated | truncated
        start_obs, restarted = self.reset_env(key_reset, params)
        new_state = jax.tree_util.tree_map(lambda a, b: jnp.where(done, a, b), restarted, stepped)
        return jnp.where(done, start_obs, obs), new_state, reward, done, info

    if not GYMNAX_INSTALLED:

        def reset(self, key: jax.Array, params: RaceParams | None = None
                  ) -> tuple[jax.Array, RaceState | PlannedRace]:
            """A new race: ``(learner's obs (O,) float32, state)``. Pure: jit and vmap it."""
            return self.reset_env(key, self.default_params if params is None else params)

        def step(self, key: jax.Array, state: RaceState | PlannedRace, action: jax.Array,
                 params: RaceParams | None = None):
            """:meth:`race_step`: ``(obs, state, reward, done, info)`` with autoreset."""
            return self.race_step(key, state, action, params)


class PlannedRace(NamedTuple):
    """The state of a :class:`GymnaxRace` with planner opponents: the race and each planner's
    plan state (:class:`planners.agents.compiled_planner.PlanState`, in car order)."""

    race: RaceState
    plans: tuple
