"""Cost weights of a planning agent: its beliefs of the others', its private own weights.

A receding-horizon agent plans in a copy of the race's game whose stacked weights ``(N,)``
differ from the race's where the agent is told so: its belief of the other cars' weights
(``belief_weights``, ``opponent_weights``), its own private weights (``own_weights``) and
weights that depend on its place in the race (``leading_weights``, ``trailing_weights``).
These helpers build and check those weights; see :class:`planners.agents.RecedingHorizonAgent`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from racing_env.costs import CostWeights, stack_weights

__all__ = ["PLACE_PREFIXES", "WEIGHT_PREFIXES", "checked_weight_changes", "weight_names", "weights_for",
           "with_player_weights"]


def weights_for(game, index: int, belief) -> CostWeights:
    """The game's weights with the agent's belief about the others (``None``: the truth).

    ``belief`` is one ``CostWeights`` (scalars) assumed for every opponent (the agent keeps
    its own true weights), a sequence of N ``CostWeights`` (one per car, used as given), or a
    stacked ``CostWeights`` with ``(N,)`` fields.
    """
    if belief is None:
        return game.weights
    n = game.num_players
    if isinstance(belief, CostWeights):
        if np.ndim(belief.r_jx) == 0:  # one belief for every opponent, own weights kept
            own = CostWeights(**{k: float(np.asarray(getattr(game.weights, k))[index]) for k in weight_names()})
            return stack_weights([own if j == index else belief for j in range(n)])
        if np.shape(belief.r_jx) != (n,):
            raise ValueError(f"stacked belief_weights must have fields of shape ({n},)")
        return belief
    belief = list(belief)
    if len(belief) != n:
        raise ValueError(f"belief_weights needs {n} CostWeights (one per car), got {len(belief)}")
    return stack_weights(belief)


def weight_names() -> list[str]:
    """The fields of :class:`racing_env.CostWeights`: the weights a spec may set."""
    return [f.name for f in dataclasses.fields(CostWeights)]


def checked_weight_changes(label: str, changes: Any) -> dict[str, float]:
    """``{field: value}`` of :class:`racing_env.CostWeights` changes, checked like the weights."""
    changes = dict(changes or {})
    unknown = sorted(set(changes) - set(weight_names()))
    if unknown:
        raise ValueError(f"{label}: unknown cost weights {unknown}; the fields are {weight_names()}")
    values = {k: float(v) for k, v in changes.items()}
    try:
        CostWeights(**values)  # refuses e.g. a negative collision weight, with the field's rule
    except ValueError as err:
        raise ValueError(f"{label}: {err}") from None
    return values


def with_player_weights(weights: CostWeights, players: int | Sequence[int], changes: dict[str, float]) -> CostWeights:
    """Stacked weights ``(N,)`` with the fields in ``changes`` replaced for ``players``."""
    if not changes:
        return weights
    n = np.shape(weights.r_jx)[0]
    fields = {}
    for name in weight_names():
        column = np.array(np.broadcast_to(np.asarray(getattr(weights, name), dtype=np.float64), (n,)))
        if name in changes:
            column[players] = changes[name]
        fields[name] = column
    return type(weights)(**fields)


PLACE_PREFIXES = ("leading", "trailing")
"""Spec prefixes of own weights by race position: ``leading.c_collision=10``."""
WEIGHT_PREFIXES = {"leading": "leading_weights", "trailing": "trailing_weights", "belief": "opponent_weights"}
"""Spec prefix -> the agent argument it fills: ``belief.c_collision=100`` sets ``opponent_weights``."""
