"""The flop counter of `racing bench` against counts done by hand."""

import jax
import jax.numpy as jnp
import numpy as np

from planners.flops import FlopCount, count_flops


def test_a_matrix_product_is_two_flops_per_multiply_add():
    count = count_flops(lambda a, b: a @ b, jnp.ones((3, 4)), jnp.ones((4, 5)))
    assert count == FlopCount(dot=2 * 3 * 5 * 4)


def test_batch_dimensions_of_a_vmapped_product_multiply_the_count():
    count = count_flops(jax.vmap(jnp.dot), jnp.ones((7, 3, 4)), jnp.ones((7, 4)))
    assert count.dot == 2 * 7 * 3 * 4 and count.total == count.dot


def test_a_scan_body_counts_once_per_step():
    M, b = jnp.ones((12, 12)), jnp.ones(12)

    def run(x0):
        return jax.lax.scan(lambda x, _: (jnp.tanh(M @ x + b), None), x0, None, length=50)[0]

    # per step: the product (2 * 12 * 12), the addition (12), tanh (12)
    assert count_flops(run, b) == FlopCount(dot=50 * 288, elementwise=50 * 24)


def test_reductions_count_one_operation_per_element_merged():
    x = jnp.ones((5, 6))
    assert count_flops(lambda x: jnp.sum(x, axis=1), x) == FlopCount(reduction=5 * 5)
    assert count_flops(jnp.max, x) == FlopCount(reduction=29)


def test_integer_arithmetic_is_not_counted_and_a_while_body_counts_per_trip():
    def loop(x, n):
        return jax.lax.while_loop(lambda c: c[0] < n, lambda c: (c[0] + 1, 2.0 * c[1]), (0, x))[1]

    assert count_flops(loop, jnp.ones(8), 5) == FlopCount(elementwise=8)


def test_cond_counts_its_costliest_branch_and_inner_jaxprs_are_walked():
    def branchy(p, x):
        return jax.lax.cond(p, lambda x: x * 2.0, lambda x: jnp.exp(x) * x + 1.0, x)

    assert count_flops(branchy, True, jnp.ones(4)) == FlopCount(elementwise=12)
    # jit inside jit, and relu's custom derivative rule: max(x, 0) then the product
    assert count_flops(jax.jit(lambda x: jax.jit(jax.nn.relu)(x) * 2.0), jnp.ones(10)) == FlopCount(elementwise=20)


def test_library_calls_are_named_as_uncounted():
    count = count_flops(jnp.linalg.cholesky, jnp.eye(4))
    assert "cholesky" in count.uncounted


def test_an_iteration_of_the_game_solver_is_linear_in_the_horizon():
    """Every part of an iLQGame iteration runs once per stage, so its count is a T + b; a
    counter that saw a scan's body only once would give equal counts for every horizon."""
    from experiments.bench import _iteration_flops
    from experiments.paper import PAPER_WEIGHTS
    from racing_env import RaceGame
    from racing_env.scenarios import paper_overtake
    from racing_env.track import straight

    track = straight(length=400.0, width_left=6.0, width_right=6.0)
    scene = paper_overtake(track)
    x0, counts = scene.x0, []
    for horizon in (10, 20, 30):
        game = RaceGame.create(track, scene.vehicles, PAPER_WEIGHTS, dt=0.1, horizon=horizon)
        counts.append(_iteration_flops(game, x0, "feedback"))
    steps = np.diff(counts)
    assert steps[0] > 0 and steps[0] == steps[1]
