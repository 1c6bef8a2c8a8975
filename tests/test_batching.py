"""planners.batching: batching rules that change how a function runs under vmap, not what it computes."""

import jax
import jax.numpy as jnp
import numpy as np

from planners.batching import one_at_a_time, with_batched_form


def _fn(A, x):
    """A small loop, like the solvers' building blocks: ``A (T, n, n)``, ``x (n,)``."""
    def step(y, A_t):
        return jnp.tanh(A_t @ y), jnp.sum(y**2)

    return jax.lax.scan(step, x, A)


def _batched_fn(A, x):
    """The same function of a batch ``A (B, T, n, n)``, ``x (B, n)``, written batched."""
    calls.append(A.shape[0])
    return jax.vmap(_fn)(A, x)


calls: list[int] = []
RNG = np.random.default_rng(0)
A = jnp.asarray(RNG.normal(size=(5, 4, 3, 3)))  # a batch of 5
X = jnp.asarray(RNG.normal(size=(5, 3)))


def _assert_same(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-14, atol=1e-14)


def test_batched_form_runs_once_per_batch_with_unbatched_arguments_broadcast():
    wrapped = with_batched_form(_fn, _batched_fn)
    calls.clear()
    _assert_same(jax.vmap(wrapped)(A, X), jax.vmap(_fn)(A, X))
    _assert_same(jax.vmap(wrapped, in_axes=(None, 0))(A[0], X), jax.vmap(_fn, in_axes=(None, 0))(A[0], X))
    _assert_same(wrapped(A[1], X[1]), _fn(A[1], X[1]))  # unbatched: fn itself
    assert calls == [5, 5]
    nested = jax.vmap(jax.vmap(wrapped))(A.reshape(5, 1, 4, 3, 3), X.reshape(5, 1, 3))
    _assert_same(nested, jax.vmap(jax.vmap(_fn))(A.reshape(5, 1, 4, 3, 3), X.reshape(5, 1, 3)))


def test_one_at_a_time_matches_vmap_with_unbatched_arguments_shared():
    wrapped = one_at_a_time(_fn)
    _assert_same(jax.vmap(wrapped)(A, X), jax.vmap(_fn)(A, X))
    _assert_same(jax.vmap(wrapped, in_axes=(None, 0))(A[0], X), jax.vmap(_fn, in_axes=(None, 0))(A[0], X))


def test_derivatives_are_those_of_the_function():
    def loss(f):
        return lambda A, X: jnp.sum(jax.vmap(f)(A, X)[1] ** 2)

    expected = jax.grad(loss(_fn), argnums=(0, 1))(A, X)
    for wrapped in (with_batched_form(_fn, _batched_fn), one_at_a_time(_fn)):
        _assert_same(jax.grad(loss(wrapped), argnums=(0, 1))(A, X), expected)
