"""Agent specs: the strings that name a competitor on the command line and in config files.

A spec is an agent name, optionally followed by ``:`` and comma-separated ``option=value``
pairs::

    ilqgame-fb                                       a planner with its defaults
    ilqgame-fb:max_iterations=100,replan_every=2     constructor and solver options
    ilqr:c_collision=1                               the agent's own cost weights
    ilqgame-fb:leading.c_collision=10,trailing.c_collision=1    weights by race position
    lane-keeping:target_speed=20,target_n=1.5
    rl:path/to/model.zip                             a saved stable-baselines3 policy

Values are converted to the option's type (``int``, ``float``, ``bool`` as true/false) and
checked by the agent's constructor, so a bad spec fails when the agent is made, before any
race. This module only parses; :func:`planners.agents.make_agent` builds the agent.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

__all__ = ["convert_options", "describe_options", "split_spec", "split_spec_list", "with_options"]

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
            if specs and "=" in piece and ":" not in piece and ":" in specs[-1] and not specs[-1].startswith("rl:"):
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
