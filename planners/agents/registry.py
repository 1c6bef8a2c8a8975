"""The agent registry: one name per method, the specs that name a competitor, and their help text.

A spec is the string that names a competitor on the command line, in config files and in
Python (:func:`make_agent`): an agent name, optionally followed by ``:`` and comma-separated
``option=value`` pairs::

    ilqgame-fb                                       a planner with its defaults
    ilqgame-fb:max_iterations=100,replan_every=2     constructor and solver options
    ilqr:c_collision=1                               the agent's own cost weights
    ilqgame-fb:leading.c_collision=10,trailing.c_collision=1    weights by race position
    lane-keeping:target_speed=20,target_n=1.5
    rl:path/to/model.zip                             a saved stable-baselines3 policy
    rl:path/to/model.npz                             a policy saved by the JAX learner
    ilqgame-fb:car=av21                              the agent in a car of another class
    rl:car=f1tenth:path/to/model.zip                 (an rl: spec takes it before its path)

The names are those of :mod:`planners.methods`, and :data:`AGENTS` maps each to its class,
whose ``spec`` attribute is that name. Values are converted to the option's type (``int``,
``float``, ``bool`` as true/false) and checked by the agent's constructor, so a bad spec
fails when the agent is made, before any race. The meaning of every option, for
``racing agents`` and the docs, is :data:`OPTION_HELP`. See docs/agents.md.

``car=NAME`` (:data:`CAR_OPTION`) is not the agent's but the race's: the class of the car
the agent drives in a lineup (:mod:`racing_env.car_classes`). The commands that race a
lineup read it with :func:`split_car` and build each car of its class, so that every
planner plans with its own car's limits and knows its rivals' (the game's per-car
vehicles); :func:`make_agent` checks the name and leaves it out of the agent's options.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Mapping

from planners.agents.protocol import Agent, BaseAgent
from planners.agents.receding_horizon import (
    RECOVERED_SPEED,
    STOPPED_SPEED,
    FeedbackGameAgent,
    FollowerGameAgent,
    ILQRAgent,
    LeaderGameAgent,
    OpenLoopGameAgent,
)
from planners.agents.scripted import ConstantSpeedAgent, LaneKeepingAgent, RacelineAgent, RandomAgent
from planners.agents.weights import PLACE_PREFIXES, weight_names
from planners.methods import (
    AGENT_METHODS,
    CONSTANT_SPEED,
    CONSTANT_VELOCITY,
    FEEDBACK_GAME,
    ILQR,
    LANE_KEEPING,
    OPEN_LOOP_GAME,
    RACELINE,
    RANDOM,
    RL,
    STACKELBERG_FOLLOWER,
    STACKELBERG_LEADER,
)

__all__ = [
    "AGENTS",
    "AGENT_SPECS",
    "AGENT_SUMMARIES",
    "OPTION_HELP",
    "CAR_OPTION",
    "agent_options",
    "check_specs",
    "convert_options",
    "describe_options",
    "make_agent",
    "option_help",
    "split_car",
    "split_spec",
    "split_spec_list",
    "with_options",
]

# --------------------------------------------------------------------------------------
# The registry.
# --------------------------------------------------------------------------------------

_CLASSES = {cls.spec: cls for cls in (ILQRAgent, OpenLoopGameAgent, FeedbackGameAgent, LeaderGameAgent,
                                      FollowerGameAgent, RacelineAgent, LaneKeepingAgent, ConstantSpeedAgent,
                                      RandomAgent)}
AGENTS: dict[str, type[BaseAgent]] = {name: _CLASSES[name] for name in AGENT_METHODS}
"""Agent name -> class (each class's ``spec`` is its name). ``rl:`` specs are not in it: they
name a saved model (:class:`planners.agents.sb3.SB3Agent`, loaded with stable-baselines3)."""

AGENT_SPECS = AGENTS
"""A compatibility alias of :data:`AGENTS` (the same dict) for scripts written against it;
the package itself uses ``AGENTS``."""

AGENT_SUMMARIES = {
    ILQR: "iLQR against predictions of the opponents (the paper's: constant velocity and offset)",
    OPEN_LOOP_GAME: "open-loop Nash iLQGame, re-planned every step",
    FEEDBACK_GAME: "feedback Nash iLQGame, re-planned every step, its feedback law applied in between",
    STACKELBERG_LEADER: ("feedback Stackelberg iLQGame with the nearest rival (the others predicted), this car "
                         "leading (role=follower: following; role=auto: the car ahead leads), its feedback law "
                         "applied in between"),
    STACKELBERG_FOLLOWER: (f"{STACKELBERG_LEADER} with this car following by default (role=leader, role=auto as "
                           f"there)"),
    RACELINE: ("scripted: the circuit's racing line at its lap-time limit's speeds (pace=0.95: slower), keeping a "
               "gap to a car ahead and passing where clear (yield=false: no avoidance)"),
    LANE_KEEPING: "scripted: holds a lateral offset at a cruise speed, slowing for curves within grip",
    CONSTANT_SPEED: "scripted: the centre line at a constant speed (slowing only for curves)",
    RANDOM: "uniform random actions every step, seeded by the race (a rival no planner can predict)",
}
"""One line per agent name, for help text."""


def make_agent(spec: str, **kwargs: Any) -> Agent:
    """An agent from a spec: ``ilqr``, ``ilqgame-ol``, ``ilqgame-fb``, ``ilqgame-leader``,
    ``ilqgame-follower``, ``raceline``, ``lane-keeping``,
    ``constant-speed``, ``random`` or ``rl:path/to/model.zip`` (``rl:sac:path`` names the algorithm).

    A non-RL spec may carry options, ``name:option=value,...`` (see :func:`split_spec` and
    :func:`agent_options`), e.g. ``ilqgame-fb:max_iterations=100,c_collision=1``. ``kwargs``
    go to the agent's constructor and win over the spec's options. Raises ``ValueError`` for
    an unknown spec, an unknown option or a bad value.
    """
    valid = list(AGENTS) + [f"{RL}:<path/to/model.zip>", f"{RL}:<algo>:<path>"]
    if not isinstance(spec, str):
        raise ValueError(f"agent spec must be a string, one of {valid}; got {spec!r}")
    if not spec.strip():
        raise ValueError(f"agent spec is empty; valid specs: {', '.join(valid)}")
    key, _ = split_car(spec)  # the car's class is the race's (the lineup's builder reads it)
    if key.lower().startswith(f"{RL}:"):
        from planners.agents.sb3 import SB3_ALGOS, SB3Agent  # the RL layer, only for RL specs

        rest = key[len(RL) + 1:]
        head, sep, tail = rest.partition(":")
        if sep and head.lower() in SB3_ALGOS:
            kwargs.setdefault("algo", head.lower())
            rest = tail
        if not rest:
            raise ValueError(
                f"agent spec {spec!r} needs a model path (rl:path/to/model.zip); valid specs: {', '.join(valid)}"
            )
        from planners.agents.jax_policy import JaxPolicyAgent, is_jax_model

        if is_jax_model(rest):  # a JAX learner's model file
            if kwargs.get("algo") not in (None, "ppo"):
                raise ValueError(f"agent spec {spec!r}: a JAX learner's model is a PPO policy, not {kwargs['algo']}")
            return JaxPolicyAgent(rest)
        return SB3Agent(rest, **kwargs)
    name, raw = split_spec(key)
    if name not in AGENTS:
        raise ValueError(f"unknown agent spec {spec!r}; valid specs: {', '.join(valid)}")
    cls = AGENTS[name]
    return cls.from_spec_options(convert_options(name, raw, cls.spec_options()), **kwargs)


CAR_OPTION = "car"
"""The spec option that names the class of the agent's car in a lineup (:func:`split_car`)."""


def split_car(spec: str) -> tuple[str, str | None]:
    """``(spec without its car, the car's class)`` of a spec with a ``car=NAME`` option
    (``ilqgame-fb:car=av21,max_iterations=50`` -> ``("ilqgame-fb:max_iterations=50",
    "av21")``), or ``(spec, None)`` without one. An ``rl:`` spec gives it before the model's
    path, as it gives the algorithm: ``rl:car=av21:path`` or ``rl:sac:car=av21:path``.

    Raises:
        ValueError: for a name that is no car class (listing the classes) or a spec that
            gives ``car`` twice.
    """
    from racing_env.car_classes import CAR_CLASSES, car_names

    if not isinstance(spec, str):
        return spec, None
    key = spec.strip()

    def checked(name: str) -> str:
        lowered = name.strip().lower()
        if lowered not in CAR_CLASSES:
            raise ValueError(f"agent spec {spec!r}: unknown car class {name.strip()!r}; the classes are "
                             f"{car_names()} (racing cars lists them)")
        return lowered

    if key.lower().startswith(f"{RL}:"):
        heads, rest, car = [], key[len(RL) + 1:], None
        while True:  # the prefixes before the path: an algorithm name and the car
            head, sep, tail = rest.partition(":")
            option, eq, value = head.partition("=")
            if sep and eq and option.strip().lower() == CAR_OPTION:
                if car is not None:
                    raise ValueError(f"agent spec {spec!r} gives {CAR_OPTION} twice")
                car, rest = checked(value), tail
            elif sep and not eq and not heads and head.strip().lower() in _rl_algos():
                heads.append(head)
                rest = tail
            else:
                break
        return ":".join([RL, *heads, rest]), car
    name, options = split_spec(key)
    if CAR_OPTION not in options:
        return spec, None
    car = checked(options.pop(CAR_OPTION))
    return (f"{name}:" + ",".join(f"{k}={v}" for k, v in options.items())) if options else name, car


def _rl_algos() -> tuple[str, ...]:
    from planners.agents.sb3 import SB3_ALGOS  # the RL layer, only for rl: specs

    return SB3_ALGOS


def check_specs(specs: Iterable[str]) -> None:
    """Make each distinct spec once, so an unknown spec, a bad option or a missing model
    raises before any race or training step."""
    for spec in dict.fromkeys(specs):
        make_agent(spec)


def agent_options(name: str) -> list[tuple[str, str, str, str]]:
    """``(option, type, default, meaning)`` rows of the options a spec of agent ``name`` may set."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; agents with options: {', '.join(AGENTS)}")
    cls = AGENTS[name]
    return describe_options(cls.spec_options(), cls.spec_defaults(), option_help(cls.spec_options()))


# --------------------------------------------------------------------------------------
# Help text: what each option of a spec does.
# --------------------------------------------------------------------------------------

_LOOP_HELP = {
    "max_iterations": "solver iterations per re-plan; the last iterate is used if it has not converged",
    "replan_every": "re-plan every this many steps and follow the stored plan in between",
    "pad": "end of the shifted warm start: repeat (the last input) or zeros",
    "warm_start": "start each re-plan from the previous plan (false: from zero inputs)",
    "restore_accelerations": ("correct the warm start's first jerks so the accelerations are back on the "
                              "previous plan after one step (the env projects them onto their limits); "
                              "default: on with iterations or budget_ms"),
    "iterations": ("real-time re-plan: at most this many iterations, the last iterate adopted "
                   "(replaces max_iterations)"),
    "budget_ms": ("wall-clock budget per re-plan [ms]: iterations stop when it runs out, the last "
                  "iterate adopted (not batched; iLQR only with a one-solve prediction)"),
    "require_converged": "treat a re-plan that did not converge as a failure (previous plan, else brake)",
    "recovery_track_scale": f"factor on own c_track from a standstill (< {STOPPED_SPEED} m/s) until "
                            f"{RECOVERED_SPEED} m/s, to rejoin across the edge (0: no track term then; 1: off)",
    "responsibility": ("the collision weight every car carries towards a car ahead of it over that towards a car "
                       "behind, judged at each re-plan's start (finite, >= 1; 1: the paper's symmetric cost)"),
}

_GAME_HELP = {
    "rivals": ("in a field, the game is this car's with its nearest rivals (by track distance, chosen at "
               "every re-plan), the others predicted at constant velocity; rivals >= cars - 1: the whole game "
               f"({ILQR}: the game of prediction={FEEDBACK_GAME} or {OPEN_LOOP_GAME})"),
    "obstacles": ("in a local game, the nearest other cars after the rivals predicted as moving obstacles; the cars "
                  "further away are left out of its costs, so it costs the same in any field"),
    "certify": ("certify every adopted re-plan as a local Nash equilibrium or not (cheap form, ~17 ms for "
                "2 cars at T=50; the leader-follower games: a local Stackelberg solution or not): diagnostics' "
                "certified and verdict, the race record's certified_share"),
    "role": (f"{STACKELBERG_LEADER}, {STACKELBERG_FOLLOWER}: this car's part in its game with the nearest rival: "
             "leader, follower, or auto (the car ahead in race distance leads, judged at every re-plan; "
             "equal distances: the lower car index)"),
}

_SOLVER_HELP = {
    "tolerance": "convergence: largest state change of a full step [m, m/s, ...]",
    "precision": ("float64 (the default) or float32: the floats the solve runs in, whatever jax_enable_x64 says "
                  "(float32: about twice as fast in batches; tolerance at least 1.19e-7)"),
    "step_control": (f"trust_region (shrink the step to stay inside trust_radius), residual ({OPEN_LOOP_GAME} "
                     "only: also until the open-loop Nash residual decreases) or none (fixed step)"),
    "trust_radius": "largest accepted change of the state trajectory per iteration",
    "initial_step": "the first step size tried, in (0, 1]",
    "step_decay": "factor by which the step size shrinks per trial, in (0, 1)",
    "max_backtracks": "step-size trials after the first before the search gives up",
    "oscillation_damping": "start shorter after a step that reverses the recent direction",
    "damping_memory": "decay of the running sum of step directions, in [0, 1)",
    "state_regularization": "added to the diagonal of every Q",
    "control_regularization": ("added to the diagonal of every R^ii, or with feedforward_regularization "
                               "to the feed-forward rows of the step (with adaptive_regularization: "
                               "its start and floor after a reversal)"),
    "adaptive_regularization": ("shrink control_regularization while the iterates keep their "
                                f"direction, raise it when they reverse ({FEEDBACK_GAME}: with "
                                "feedforward_regularization only)"),
    "feedforward_regularization": (f"{FEEDBACK_GAME} and {ILQR} (not {OPEN_LOOP_GAME}): control_regularization "
                                   "damps the feed-forward terms only, so the plans stay feedback "
                                   "equilibria"),
    "regularization_factor": "factor of each change of the adaptive regularization, > 1",
    "convexify": "auto, gauss_newton, eig, diag or none: how the cost Hessians are made convex",
    "best_iterate": ("adopt the iterate whose first-stage LQ step is smallest instead of the last "
                     "one when a re-plan stops unconverged (races worse: docs/agents.md)"),
    "player_steps": ("a step size per car, each cut by the trust region on its own states (default: on for "
                     f"{FEEDBACK_GAME}'s real-time re-plans, iterations or budget_ms): a rival whose plan needs a "
                     "long step no longer shortens the ego's"),
    "dynamics_curvature": ("give each car's local game the curvature of its progress in its "
                           "heading, which linearising the dynamics drops (false: the plain iLQ model)"),
}

_PREDICTION_HELP = {
    "prediction": (f"how the opponents are predicted: {CONSTANT_VELOCITY} (the paper's), "
                   f"{LANE_KEEPING} (driven by the scripted lane keeper's law), {ILQR} (each one's own "
                   f"iLQR plan), {FEEDBACK_GAME} or {OPEN_LOOP_GAME} (the game's feedback / open-loop Nash "
                   "equilibrium)"),
    "levels": (f"levels of reasoning of prediction={ILQR}: each opponent's plan against everyone's plans "
               "one level down, level 0 being constant velocity"),
}

_SCRIPTED_HELP = {"target_speed": "cruise speed [m/s]", "target_n": "lateral offset to hold [m], positive left",
                  "pace": "fraction of the lap-time limit's speed profile driven, in (0, 1]",
                  "margin": "the racing line is kept this far inside the track boundaries [m]",
                  "line": "raceline (the circuit's; the centre line where none is shipped) or centerline",
                  "yield": ("raceline: keep to the rules of traffic (keep a gap to a car ahead on its line, pass "
                            "only where clear, never move across into a car alongside); false: drive the line "
                            "whoever is on it (the old driver, for robustness tests)"),
                  "time_gap": "raceline: the time gap kept to a car ahead on its path [s], >= 0",
                  "standstill": "raceline: the bumper-to-bumper gap kept behind a car ahead, also at rest [m], > 0",
                  "scale": "random: actions drawn uniformly from [-scale, scale]^2, a fraction of the action box in (0, 1]"}

_WEIGHT_MEANINGS = {
    "r_jx": "longitudinal jerk weight",
    "r_jy": "lateral jerk weight",
    "c_collision": "collision weight c_c",
    "c_track": "track-boundary weight c_w",
    "c_ax": "weight on exceeding ax_max(V)",
    "c_acc": "weight on exceeding the gg radius and the turn limit",
    "c_gap": "weight c_g of the others' progress at the horizon",
    "c_reverse": "weight on negative speed (the cars have no reverse gear)",
}


def _weight_help() -> dict[str, str]:
    lines = {name: f"{_WEIGHT_MEANINGS.get(name, name)} of this car in its own plans only" for name in weight_names()}
    for place in PLACE_PREFIXES:
        lines.update({f"{place}.{name}": f"{name} in re-plans made while the car is {place}" for name in weight_names()})
    lines.update({f"belief.{name}": f"the {name} this agent believes every other car has" for name in weight_names()})
    return lines


OPTION_HELP: dict[str, str] = {**_LOOP_HELP, **_GAME_HELP, **_SOLVER_HELP, **_PREDICTION_HELP, **_SCRIPTED_HELP, **_weight_help()}
"""Spec option -> one line on what it does, for every option of the registered agents."""


def option_help(options: Iterable[str]) -> dict[str, str]:
    """The lines of :data:`OPTION_HELP` for ``options`` (an option it lacks is left out)."""
    return {key: OPTION_HELP[key] for key in options if key in OPTION_HELP}


# --------------------------------------------------------------------------------------
# Parsing specs.
# --------------------------------------------------------------------------------------

_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def split_spec(spec: str) -> tuple[str, dict[str, str]]:
    """``"name:key=value,..."`` -> ``(name, {key: value})`` with the raw value strings.

    Raises ``ValueError`` for an option without ``=``, an empty name or value, or an option
    given twice. ``rl:`` specs are not split here (their remainder is a path).
    """
    name, sep, rest = spec.strip().partition(":")
    name = name.strip().lower()
    if not name:
        raise ValueError(f"agent spec {spec!r} has no agent name before ':'")
    options: dict[str, str] = {}
    if not sep:
        return name, options
    if not rest.strip():
        raise ValueError(f"agent spec {spec!r} ends in ':' with no options after it")
    for item in rest.split(","):
        key, eq, value = (part.strip() for part in item.partition("="))
        if not eq or not key or not value:
            raise ValueError(f"agent spec {spec!r}: option {item.strip()!r} is not key=value")
        if key in options:
            raise ValueError(f"agent spec {spec!r} sets {key!r} twice")
        options[key] = value
    return name, options


def split_spec_list(parts: list[str]) -> list[str]:
    """Specs from command-line words, each of which may hold several comma-separated specs.

    A comma also separates a spec's options, so a piece with ``=`` and no ``:`` continues
    the spec before it: ``["ilqr,ilqgame-fb:max_iterations=100,pad=zeros", "lane-keeping"]``
    is ``["ilqr", "ilqgame-fb:max_iterations=100,pad=zeros", "lane-keeping"]``.
    """
    specs: list[str] = []
    for part in parts:
        for piece in (p.strip() for p in part.split(",")):
            if not piece:
                continue
            if specs and "=" in piece and ":" not in piece and ":" in specs[-1] and not specs[-1].lower().startswith(f"{RL}:"):
                specs[-1] = f"{specs[-1]},{piece}"
            elif "=" in piece and ":" not in piece:
                raise ValueError(f"{piece!r} is an option with no agent spec before it; "
                                 "write options after the agent name, e.g. ilqgame-fb:max_iterations=100")
            else:
                specs.append(piece)
    return specs


def with_options(spec: str, options: Mapping[str, Any]) -> str:
    """``spec`` with ``options`` added (replacing the spec's own value of an option).

    ``with_options("ilqgame-fb:pad=zeros", {"max_iterations": 100})`` is
    ``"ilqgame-fb:pad=zeros,max_iterations=100"``; no options returns ``spec`` unchanged.
    """
    if not options:
        return spec
    name, raw = split_spec(spec)
    raw.update({key: _format(value) for key, value in options.items()})
    return f"{name}:" + ",".join(f"{key}={value}" for key, value in raw.items())


def _format(value: Any) -> str:
    return ("true" if value else "false") if isinstance(value, bool) else str(value)


def _to_bool(text: str) -> bool:
    lowered = text.lower()
    if lowered in _TRUE:
        return True
    if lowered in _FALSE:
        return False
    raise ValueError(f"expected true or false, got {text!r}")


def _to_int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"expected an integer, got {text!r}") from None


def _to_float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"expected a number, got {text!r}") from None


_CONVERTERS: dict[type, Callable[[str], Any]] = {bool: _to_bool, int: _to_int, float: _to_float, str: str}


def convert_options(name: str, raw: Mapping[str, str], types: Mapping[str, type]) -> dict[str, Any]:
    """Convert raw option strings to the types an agent declares; refuse unknown options."""
    unknown = sorted(set(raw) - set(types))
    if unknown:
        plain = sorted(key for key in types if "." not in key)
        prefixes = sorted({key.split(".", 1)[0] for key in types if "." in key})
        allowed = ", ".join(plain + [f"{prefix}.<weight>" for prefix in prefixes]) or "none"
        raise ValueError(f"agent {name!r} has no option {', '.join(map(repr, unknown))}; its options: {allowed}")
    out = {}
    for key, text in raw.items():
        try:
            out[key] = _CONVERTERS[types[key]](text)
        except ValueError as err:
            raise ValueError(f"agent {name!r}, option {key!r}: {err}") from None
    return out


def describe_options(types: Mapping[str, type], defaults: Mapping[str, Any],
                     meanings: Mapping[str, str]) -> list[tuple[str, str, str, str]]:
    """``(option, type name, default, meaning)`` rows for help text, sorted by option."""
    return [(key, types[key].__name__, str(defaults.get(key, "-")), meanings.get(key, ""))
            for key in sorted(types)]
