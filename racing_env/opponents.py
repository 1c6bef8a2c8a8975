"""What the learner faces take: their keyword arguments and their ``opponents`` entries.

The Gymnasium view (``gymnasium.make("racing_env/Race-v0", ...)``, :class:`racing_env.RaceEnv`),
the vectorised env (``gymnasium.make_vec``, :class:`racing_env.vector.RaceVectorEnv`) and the
gymnax face (:class:`racing_env.vector.GymnaxRace`) take the same keywords: the
:class:`racing_env.RaceConfig` fields, ``opponents`` and ``learner`` (and each face's own:
the vectorised env's ``num_envs`` and ``autoreset_mode``). An unknown keyword is refused
with a ``TypeError`` naming the allowed ones.

``opponents`` holds one entry per opponent car, in car order skipping the learner's (one
entry serves every opponent car). Every face takes these entries:

* ``None``: a coasting car (zero jerk);
* an agent spec (``"lane-keeping"``, ``"ilqgame-fb:replan_every=5"``, ``"rl:PATH"``), made by
  :func:`planners.agents.make_agent` once per car (and per race in a batch);
* a list of specs: a pool, each episode's driver drawn from it;
* an agent factory: a zero-argument callable that makes an agent (an agent class such as
  ``planners.FeedbackGameAgent``, ``functools.partial(LaneKeepingAgent, target_n=1.5)``,
  ``lambda: ILQRAgent(...)``), called once per car (and per race where a batch needs one
  agent per race);
* a callable ``policy(observation, joint_state) -> action`` (stateless; the gymnax face
  takes JAX policies ``policy(x (N, 6)) -> action (2,)`` instead).

An agent object (with ``reset(seed, index, env_info)`` and ``act``) keeps the state of the
one race it is reset for, so it drives one car of one race: the single env takes one per
car, and a batch of races refuses it, naming a spec or a factory instead. Each face adds
its own kinds (the single env an :class:`racing_env.OpponentPool`, the vectorised env a
batched opponent).

Specs and factories are made by the planners package, looked up by name, so that importing
``racing_env`` never imports it.

The learner faces share one default of their own: a learner that leaves the track is out
(:data:`LEARNER_OFF_TRACK`, the rule ``racing train`` trains with), where the PettingZoo env,
tournaments and evaluations keep :class:`racing_env.RaceConfig`'s penalty.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import numbers
from typing import Any, Callable, Iterable, Mapping, Sequence

from racing_env.config import MAX_CARS, RaceConfig

MAKE_AGENT = "planners.agents.registry:make_agent"
"""The planners' agent factory of a spec (:func:`planners.agents.make_agent`), by name."""

RACE_KEYWORDS = tuple(field.name for field in dataclasses.fields(RaceConfig))
"""The :class:`racing_env.RaceConfig` fields: keywords of every face."""

LEARNER_KEYWORDS = ("opponents", "learner")
"""The keywords every learner face adds to the race's."""

LEARNER_OFF_TRACK = "terminate"
"""What leaving the track does in a learner face unless its config says otherwise: the
learner's car is out of its race (the rule ``racing train`` trains with). Under
``RaceConfig``'s ``penalty`` a learner that leaves the track is charged every step until
``max_steps`` and a standard learner never learns to stay on (docs/rl.md, "The training
race"); pass ``on_off_track="penalty"`` for the tournaments' rule."""


def learner_config(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (:class:`racing_env.RaceConfig` fields) with the learner faces' default:
    ``on_off_track`` :data:`LEARNER_OFF_TRACK` unless given."""
    return {"on_off_track": LEARNER_OFF_TRACK, **config}


def planners_function(path: str) -> Callable:
    """The function ``"module:name"`` of the planners package (imported on first use)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def is_agent(opponent: Any) -> bool:
    """Whether ``opponent`` follows the agent protocol (resettable as a car of a race)."""
    return callable(getattr(opponent, "reset", None)) and callable(getattr(opponent, "act", None))


def is_factory(opponent: Any) -> bool:
    """Whether ``opponent`` is an agent factory: a class, a ``functools.partial`` of one, or
    a callable that takes no arguments (and cannot be called as a policy with two)."""
    if isinstance(opponent, type):
        return True
    if isinstance(opponent, functools.partial) and isinstance(opponent.func, type):
        return True
    if not callable(opponent) or is_agent(opponent) or isinstance(opponent, str):
        return False
    try:
        signature = inspect.signature(opponent)
    except (TypeError, ValueError):  # builtins without a signature: not a factory we can tell
        return False
    return _binds(signature) and not _binds(signature, None, None)


def _is_index(value: Any) -> bool:
    """Whether ``value`` is an integer (a bool is not)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _binds(signature: inspect.Signature, *args: Any) -> bool:
    try:
        signature.bind(*args)
    except TypeError:
        return False
    return True


def is_spec_list(opponent: Any) -> bool:
    """Whether ``opponent`` is a non-empty list (or tuple) of agent specs: a pool."""
    return isinstance(opponent, (list, tuple)) and bool(opponent) and all(isinstance(o, str) for o in opponent)


def make_from_factory(factory: Callable[[], Any], car: int) -> Any:
    """The agent (or policy) ``factory()`` makes for car ``car``; refuses anything else."""
    made = factory()
    if not callable(made) and not is_agent(made):
        raise TypeError(f"the opponent factory {factory!r} of car {car} made {made!r}: a factory must make an agent "
                        "(with reset(seed, index, env_info) and act) or a policy(observation, joint_state)")
    return made


SHARED_AGENT_HINT = ("pass its spec string (e.g. \"lane-keeping\", \"ilqgame-fb:replan_every=5\") or a zero-argument "
                     "factory (its class, e.g. FeedbackGameAgent, functools.partial(LaneKeepingAgent, target_n=1.5) or "
                     "lambda: ILQRAgent(...)), which makes one agent per car")
"""How to give an agent that must drive more than one car or race."""


def check_keywords(config: Mapping[str, Any], face: str, own: Iterable[str] = ()) -> None:
    """Refuse keywords that are neither :class:`racing_env.RaceConfig` fields nor the face's
    ``own`` (with ``TypeError``, naming the allowed ones)."""
    allowed = set(RACE_KEYWORDS) | set(LEARNER_KEYWORDS) | set(own)
    unknown = sorted(set(config) - allowed)
    if unknown:
        raise TypeError(f"{face} got unknown keyword argument(s) {unknown}; allowed: {sorted(allowed)}")


def opponent_cars(opponents: Sequence[Any] | None, learner: int, config: dict[str, Any]
                  ) -> tuple[int, list[tuple[int, Any]]]:
    """The number of cars N and ``(car, opponents entry)`` for every car but the learner's,
    in car order.

    N is ``config``'s ``num_agents`` (popped), else one more than the entries (2 without
    any). ``opponents`` holds one entry per opponent car or one for all; None: coasting
    cars. Raises ``ValueError`` for a number of cars outside ``[1, MAX_CARS]``, a count of
    entries that is neither, or a learner index outside the cars; ``TypeError`` for an
    ``opponents`` that is not a list."""
    if isinstance(opponents, (str, bytes)) or (opponents is not None and not isinstance(opponents, Sequence)):
        raise TypeError(f"opponents must be a list with one entry per opponent car (or one for all), e.g. "
                        f"[\"lane-keeping\"]; got {opponents!r}")
    opponents = None if opponents is None else list(opponents)
    num = config.pop("num_agents", 2 if opponents is None else len(opponents) + 1)
    if not _is_index(num) or not 1 <= num <= MAX_CARS:
        raise ValueError(f"num_agents must be an integer in [1, {MAX_CARS}] (the learner and its opponents), "
                         f"got {num!r}")
    num = int(num)
    if opponents is None:
        opponents = [None] * (num - 1)
    if len(opponents) == 1 and num > 2:
        opponents = opponents * (num - 1)
    if len(opponents) != num - 1:
        entries = "entry" if num == 2 else "entries"
        raise ValueError(f"opponents must have {num - 1} {entries} for {num} cars (or one entry for all), "
                         f"got {len(opponents)}")
    if not _is_index(learner) or not 0 <= learner < num:
        raise ValueError(f"learner must be a car index in [0, {num - 1}], got {learner!r}")
    return num, list(zip([j for j in range(num) if j != learner], opponents))
