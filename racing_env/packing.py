"""Pass a pytree of constants to a jitted function as one flat array.

A jitted call pays a cost per argument leaf before any work is done (docs/performance.md),
so a call with a few dozen leaves costs several times one with a single leaf. The env's
per-race constants (the ``RaceGame``'s track and vehicle arrays, the finish line, the
preview distances, the rules) are most of those leaves and never change during a race, so
they travel as one float64 vector and are unpacked inside the compiled function, where the
slices cost nothing. The :class:`Layout` is hashable (a static argument): envs with the
same shapes and static metadata share one compiled function.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import numpy as np

# Dtypes whose values float64 holds exactly (int32 and below, booleans).
_EXACT_IN_FLOAT64 = {"float64", "float32", "float16", "int32", "int16", "int8", "uint8", "uint16", "uint32", "bool"}


class Layout(NamedTuple):
    """Where each leaf of a packed pytree lies in the flat vector."""

    treedef: Any
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[str, ...]


def pack(tree: Any) -> tuple[jax.Array, Layout]:
    """Flatten ``tree`` into one float64 device array and its :class:`Layout`.

    Raises:
        TypeError: a leaf's dtype cannot round-trip through float64 exactly (e.g. int64).
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    arrays = [np.asarray(leaf) for leaf in leaves]
    for array in arrays:
        if array.dtype.name not in _EXACT_IN_FLOAT64:
            raise TypeError(f"cannot pack a {array.dtype} leaf into float64 exactly")
    flat = np.concatenate([a.astype(np.float64).ravel() for a in arrays]) if arrays else np.zeros(0)
    layout = Layout(treedef, tuple(a.shape for a in arrays), tuple(a.dtype.name for a in arrays))
    return jax.device_put(flat), layout


def unpack(flat: jax.Array, layout: Layout) -> Any:
    """The pytree :func:`pack` flattened, from its flat vector (inside or outside jit)."""
    leaves, start = [], 0
    for shape, dtype in zip(layout.shapes, layout.dtypes):
        size = math.prod(shape)
        leaves.append(flat[start : start + size].reshape(shape).astype(dtype))
        start += size
    return jax.tree_util.tree_unflatten(layout.treedef, leaves)
