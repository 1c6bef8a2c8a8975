"""Floating-point operations of a JAX function, counted from its jaxpr.

XLA's own ``cost_analysis()`` counts the body of a loop once, whatever its trip count, so
a solver written as ``lax.scan`` over 50 stages shows the arithmetic of one stage. This
counter walks the jaxpr instead and multiplies a ``scan`` body by its length. It is what
`racing bench` uses to state the arithmetic rate a solver reaches and the rate a batch
target would need (to be read against the machine's dgemm rate).

Counting rules (the usual conventions of roofline estimates):

* ``dot_general``: 2 flops per multiply-add, ``2 * output size * contracted size``;
* an arithmetic element-wise primitive (``add``, ``mul``, ``div``, ``tanh``, ``max``, ...):
  one flop per output element;
* a reduction (``reduce_sum``, ``reduce_max``, ...): ``input size - output size``;
* ``scan``: its body times ``length``; ``while``: its condition and body once (the count is
  per trip; the caller knows how many trips a loop makes); ``cond``: the costliest branch;
* any other primitive with inner jaxprs (``jit``, custom derivatives, ``custom_vmap``,
  ...): the inner jaxprs once;
* only floating-point operands count (integer counters and indices do not);
* data movement and comparisons (``select_n``, ``gather``, ``lt``, ...) count nothing;
  primitives that do arithmetic this counter cannot see into (LAPACK calls, custom calls)
  are named in :attr:`FlopCount.uncounted`, so a caller can tell that a count is a lower
  bound.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.extend import core as jex_core

_ELEMENTWISE = frozenset({
    "add", "add_any", "sub", "mul", "div", "rem", "neg", "abs", "sign", "max", "min",
    "exp", "exp2", "expm1", "log", "log1p", "sqrt", "rsqrt", "cbrt", "square", "reciprocal",
    "pow", "integer_pow", "sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh",
    "cosh", "tanh", "asinh", "acosh", "atanh", "logistic", "erf", "erfc", "erf_inv",
})
_REDUCTIONS = frozenset({"reduce_sum", "reduce_max", "reduce_min", "reduce_prod", "argmax", "argmin"})
_CUMULATIVE = frozenset({"cumsum", "cumprod", "cummax", "cummin", "cumlogsumexp"})
_ARITHMETIC = _ELEMENTWISE | _REDUCTIONS | _CUMULATIVE | {"dot_general"}
_OPAQUE = frozenset({
    "cholesky", "lu", "eigh", "eig", "svd", "qr", "geqrf",
    "householder_product", "triangular_solve", "schur", "hessenberg", "tridiagonal",
    "tridiagonal_solve", "fft", "custom_call", "ffi_call", "pure_callback", "io_callback",
})


@dataclasses.dataclass(frozen=True)
class FlopCount:
    """Flops by kind; ``uncounted`` names primitives whose arithmetic was not counted."""

    dot: int = 0
    elementwise: int = 0
    reduction: int = 0
    uncounted: frozenset[str] = frozenset()

    @property
    def total(self) -> int:
        return self.dot + self.elementwise + self.reduction

    def __add__(self, other: "FlopCount") -> "FlopCount":
        return FlopCount(self.dot + other.dot, self.elementwise + other.elementwise,
                         self.reduction + other.reduction, self.uncounted | other.uncounted)

    def __mul__(self, times: int) -> "FlopCount":
        return FlopCount(self.dot * times, self.elementwise * times, self.reduction * times, self.uncounted)


def count_flops(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> FlopCount:
    """The flops of one call ``fn(*args, **kwargs)`` (traced, not run), by the rules above."""
    return jaxpr_flops(jax.make_jaxpr(fn)(*args, **kwargs).jaxpr)


def jaxpr_flops(jaxpr: jex_core.Jaxpr | jex_core.ClosedJaxpr) -> FlopCount:
    """The flops of one evaluation of ``jaxpr`` (open or closed), by the rules above."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    total = FlopCount()
    for eqn in jaxpr.eqns:
        total = total + _equation_flops(eqn)
    return total


def _size(var: Any) -> int:
    return math.prod(var.aval.shape)


def _is_floating(var: Any) -> bool:
    return jnp.issubdtype(var.aval.dtype, jnp.inexact)


def _equation_flops(eqn: Any) -> FlopCount:
    name, params = eqn.primitive.name, eqn.params
    if name in _ARITHMETIC and not _is_floating(eqn.invars[0]):
        return FlopCount()  # integer arithmetic (indices, counters) is not floating point
    if name == "dot_general":
        (lhs_contract, _), _ = params["dimension_numbers"]
        contracted = math.prod(eqn.invars[0].aval.shape[d] for d in lhs_contract)
        return FlopCount(dot=2 * _size(eqn.outvars[0]) * contracted)
    if name in _ELEMENTWISE:
        return FlopCount(elementwise=_size(eqn.outvars[0]))
    if name in _REDUCTIONS:
        return FlopCount(reduction=_size(eqn.invars[0]) - _size(eqn.outvars[0]))
    if name in _CUMULATIVE:
        return FlopCount(reduction=_size(eqn.invars[0]))
    if name in _OPAQUE:
        return FlopCount(uncounted=frozenset({name}))
    if name == "scan":
        return jaxpr_flops(params["jaxpr"]) * params["length"]
    if name == "while":
        return jaxpr_flops(params["cond_jaxpr"]) + jaxpr_flops(params["body_jaxpr"])
    if name == "cond":
        return max((jaxpr_flops(branch) for branch in params["branches"]), key=lambda c: c.total)
    total = FlopCount()
    for inner in _inner_jaxprs(params):
        total = total + jaxpr_flops(inner)
    return total


def _inner_jaxprs(params: dict[str, Any]) -> list[Any]:
    """The jaxprs among a higher-order primitive's parameters (``jit``'s ``jaxpr``,
    ``custom_jvp_call``'s ``call_jaxpr``, ``custom_vmap_call``'s ``call``, ...); the rules
    that derive other jaxprs from them (``jvp_jaxpr_fun``, ...) are not jaxprs and are skipped."""
    found = []
    for value in params.values():
        for item in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(item, (jex_core.Jaxpr, jex_core.ClosedJaxpr)):
                found.append(item)
    return found
