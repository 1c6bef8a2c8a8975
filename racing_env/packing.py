"""Pass a pytree of constants to a jitted function as one flat array.

A jitted call pays a cost per argument leaf before any work is done (docs/performance.md),
so a call with a few dozen leaves costs several times one with a single leaf. The env's
per-race constants (the ``RaceGame``'s track and vehicle arrays, the finish line, the
preview distances, the rules) are most of those leaves and never change during a race, so
they travel as one float vector and are unpacked inside the compiled function, where the
slices cost nothing. The :class:`Layout` is hashable (a static argument): envs with the
same shapes and static metadata share one compiled function.

The vector is in JAX's widest float: float64 with ``jax_enable_x64`` on, float32 with it
off (the race then runs in float32, as the rest of JAX does), so that neither packing nor
unpacking asks JAX for a dtype it does not have (which it answers with a warning).
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
    """Flatten ``tree`` into one device array of JAX's widest float (module docstring) and
    its :class:`Layout`.

    Raises:
        TypeError: a leaf's dtype cannot round-trip through float64 exactly (e.g. int64),
            or, in float32, an integer leaf's value cannot (beyond 2^24).
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    arrays = [np.asarray(leaf) for leaf in leaves]
    wide = jax.dtypes.canonicalize_dtype(np.float64)
    for array in arrays:
        if array.dtype.name not in _EXACT_IN_FLOAT64:
            raise TypeError(f"cannot pack a {array.dtype} leaf into float64 exactly")
        if array.dtype.kind in "iub" and not np.array_equal(array.astype(wide).astype(array.dtype), array):
            raise TypeError(f"cannot pack {array.dtype} values beyond {wide}'s integers exactly (turn on "
                            "jax_enable_x64 for float64)")
    flat = np.concatenate([a.astype(wide).ravel() for a in arrays]) if arrays else np.zeros(0, wide)
    layout = Layout(treedef, tuple(a.shape for a in arrays), tuple(a.dtype.name for a in arrays))
    return jax.device_put(flat), layout


def unpack(flat: jax.Array, layout: Layout) -> Any:
    """The pytree :func:`pack` flattened, from its flat vector (inside or outside jit)."""
    leaves, start = [], 0
    for shape, dtype in zip(layout.shapes, layout.dtypes):
        size = math.prod(shape)
        # a float64 leaf comes back in the float JAX has (float32 with x64 off)
        leaves.append(flat[start : start + size].reshape(shape).astype(jax.dtypes.canonicalize_dtype(dtype)))
        start += size
    return jax.tree_util.tree_unflatten(layout.treedef, leaves)
