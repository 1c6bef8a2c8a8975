"""racing_env.packing: a pytree of constants as one flat float64 array."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env  # noqa: F401  (float64: tests/conftest.py)
from racing_env.packing import pack, unpack


def _tree(scale):
    return {
        "track": np.linspace(0.0, scale, 7),
        "flags": np.array([True, False, True]),
        "index": np.arange(4, dtype=np.int32),
        "scalar": np.float64(scale) / 3.0,
        "nested": (np.full((2, 3), -scale), np.asarray(False)),
    }


def test_round_trip_is_exact_with_dtypes_and_shapes():
    tree = _tree(1.7)
    flat, layout = pack(tree)
    assert flat.shape == (7 + 3 + 4 + 1 + 6 + 1,) and flat.dtype == jnp.float64
    for unpacked in (unpack(flat, layout), jax.jit(unpack, static_argnames="layout")(flat, layout=layout)):
        for got, want in zip(jax.tree_util.tree_leaves(unpacked), jax.tree_util.tree_leaves(tree)):
            got = np.asarray(got)
            assert got.dtype == np.asarray(want).dtype and got.shape == np.shape(want)
            np.testing.assert_array_equal(got, want)
        assert jax.tree_util.tree_structure(unpacked) == jax.tree_util.tree_structure(tree)


def test_equal_shapes_give_equal_layouts():
    # the layout is the static argument: equal layouts mean one compiled function
    assert pack(_tree(1.0))[1] == pack(_tree(2.5))[1]
    assert hash(pack(_tree(1.0))[1]) == hash(pack(_tree(2.5))[1])
    assert pack(_tree(1.0))[1] != pack({**_tree(1.0), "track": np.zeros(8)})[1]


def test_leaves_float64_cannot_hold_exactly_are_refused():
    with pytest.raises(TypeError, match="int64"):
        pack({"big": np.array([2**60], dtype=np.int64)})


def test_with_x64_off_the_vector_is_float32_and_jax_warns_of_no_dtype():
    """With ``jax_enable_x64`` off (JAX's default, a script's first race) the constants pack
    into float32 and unpack to the dtypes JAX has, without JAX's "float64 requested ...
    truncated" warning; an integer float32 cannot hold exactly is refused."""
    import warnings

    tree = {"track": np.linspace(0.0, 1.5, 5), "index": np.arange(3, dtype=np.int32), "flag": np.array([True])}
    with jax.enable_x64(False), warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        flat, layout = pack(tree)
        unpacked = jax.jit(unpack, static_argnames="layout")(flat, layout=layout)
        assert flat.dtype == jnp.float32
        assert [leaf.dtype for leaf in jax.tree_util.tree_leaves(unpacked)] == [np.bool_, np.int32, np.float32]
        np.testing.assert_array_equal(unpacked["track"], np.linspace(0.0, 1.5, 5).astype(np.float32))
        with pytest.raises(TypeError, match="beyond float32's integers"):
            pack({"steps": np.int32(2**24 + 1)})
