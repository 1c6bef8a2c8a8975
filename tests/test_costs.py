"""Tests of racing_env.costs and RaceGame's cost functions against the paper (NumPy oracle)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from racing_env import track as tr
from racing_env.costs import CostWeights, input_cost, state_cost_terms
from racing_env.game import RaceGame
from racing_env.vehicle import VehicleParams

VEHICLES = [
    VehicleParams(length=4.7, width=2.0, v_max=20.0),
    VehicleParams(length=5.2, width=1.8, v_max=25.0, ax_max_0=7.0, rho_0=11.0, rho_aero=0.005,
                  min_turn_radius=3.0),
    VehicleParams(length=4.2, width=2.1, v_max=30.0, ax_max_0=9.0, rho_0=13.0, rho_aero=0.003,
                  min_turn_radius=8.0),
]
WEIGHTS = [
    CostWeights(r_jx=0.01, r_jy=0.02, c_collision=10.0, c_track=100.0, c_ax=50.0, c_acc=80.0, c_gap=0.5,
                c_reverse=100.0),
    CostWeights(r_jx=0.03, r_jy=0.01, c_collision=20.0, c_track=60.0, c_ax=90.0, c_acc=40.0, c_gap=0.0,
                c_reverse=30.0),
    CostWeights(r_jx=0.02, r_jy=0.05, c_collision=5.0, c_track=30.0, c_ax=20.0, c_acc=70.0, c_gap=-0.3,
                c_reverse=200.0),
]


# --- an independent NumPy implementation of the paper's stage and terminal costs ---------
def np_interp_closed(track: tr.Track, values: np.ndarray, s: np.ndarray) -> np.ndarray:
    grid = track.ds * np.arange(track.num_points + 1)
    return np.interp(np.mod(s, track.length), grid, np.append(values, values[0]))


def np_stage_terms(x, u, track, vehicles, weights):
    """Per-player stage-cost terms of the paper, as a dict of (N,) arrays.

    Track term with the usable half-width w_tr - w_veh/2 (documented in racing_env.costs);
    collision term with l, w the mean length/width of the pair and the wrapped gap in s.
    """
    n_cars = x.shape[0]
    terms = {k: np.zeros(n_cars) for k in ("jerk", "collision", "track", "ax_limit", "gg_limit", "turn_limit",
                                           "reverse")}
    for i in range(n_cars):
        veh, w = vehicles[i], weights[i]
        s, v, n, _, ax, ay = x[i]
        terms["jerk"][i] = u[i] @ np.diag([w.r_jx, w.r_jy]) @ u[i]
        for j in range(n_cars):
            if j == i:
                continue
            ds = np.mod(x[j, 0] - s + 0.5 * track.length, track.length) - 0.5 * track.length
            dn = x[j, 2] - n
            l_veh = 0.5 * (veh.length + vehicles[j].length)
            w_veh = 0.5 * (veh.width + vehicles[j].width)
            terms["collision"][i] += w.c_collision * np.exp(1.0 - (ds / l_veh) ** 2 - (dn / w_veh) ** 2) ** 2
        wl = np_interp_closed(track, track.width_left, s) - 0.5 * veh.width
        wr = np_interp_closed(track, track.width_right, s) - 0.5 * veh.width
        if n >= wl:
            terms["track"][i] += w.c_track * (n - wl) ** 2
        if -n >= wr:
            terms["track"][i] += w.c_track * (-n - wr) ** 2
        ax_max = veh.ax_max_0 * (1.0 - (v / veh.v_max) ** 2)
        if ax >= ax_max:
            terms["ax_limit"][i] = w.c_ax * (ax - ax_max) ** 2
        rho = veh.rho_0 + veh.rho_aero * v**2
        a_norm = np.sqrt(ax**2 + ay**2)
        if a_norm >= rho:
            terms["gg_limit"][i] = w.c_acc * (a_norm - rho) ** 2
        # The turn limit (steering lock) and reversing are the project's additions to the paper.
        ay_turn = v**2 / veh.min_turn_radius
        if abs(ay) >= ay_turn:
            terms["turn_limit"][i] = w.c_acc * (abs(ay) - ay_turn) ** 2
        if v < 0:
            terms["reverse"][i] = w.c_reverse * v**2
    return terms


@pytest.fixture(scope="module")
def varying_track() -> tr.Track:
    """The trefoil with widths that vary along s (left and right differently)."""
    base = tr.trefoil()
    phase = 2.0 * np.pi * base.s / base.length
    return dataclasses.replace(
        base, width_left=5.0 + 1.5 * np.sin(3.0 * phase), width_right=5.5 + 1.0 * np.cos(5.0 * phase)
    )


@pytest.fixture(scope="module")
def game3(varying_track) -> RaceGame:
    return RaceGame.create(varying_track, VEHICLES, WEIGHTS, dt=0.1, horizon=6)


@pytest.fixture(scope="module")
def game2() -> RaceGame:
    """Two players on the constant-width trefoil: width lookups have zero s-derivative, so
    the cost is smooth in s (no kinks of the piecewise-linear width interpolation)."""
    return RaceGame.create(tr.trefoil(), VEHICLES[:2], WEIGHTS[:2], dt=0.1, horizon=6)


def random_joint_states(rng, count, track, n_cars=3):
    """Joint states with cars close together (some across the lap line), speeds around the
    v_max of the cars and large accelerations, so that every penalty is active sometimes."""
    xs = np.empty((count, n_cars, 6))
    for k in range(count):
        s0 = rng.uniform(-20.0, 20.0) if k % 3 == 0 else rng.uniform(0.0, track.length)
        xs[k, :, 0] = s0 + rng.uniform(-8.0, 8.0, n_cars) + track.length * rng.integers(0, 2, n_cars)
        xs[k, :, 1] = rng.uniform(-3.0, 32.0, n_cars)  # some reversing (planned, never driven)
        xs[k, :, 2] = rng.uniform(-6.5, 6.5, n_cars)
        xs[k, :, 3] = rng.uniform(-0.5, 0.5, n_cars)
        xs[k, :, 4] = rng.uniform(-12.0, 9.0, n_cars)
        xs[k, :, 5] = rng.uniform(-16.0, 16.0, n_cars)
    us = rng.uniform(-30.0, 30.0, (count, n_cars, 2))
    return xs, us


def test_stage_cost_terms_match_paper(game3, varying_track):
    """Each stage-cost term and the total g^i equal the NumPy paper formulas at random states."""
    rng = np.random.default_rng(0)
    xs, us = random_joint_states(rng, 60, varying_track)
    terms_fn = jax.jit(lambda x: state_cost_terms(x, game3.vehicles, game3.weights, game3.track))
    stage_fn = jax.jit(jax.vmap(game3.stage_cost, in_axes=(0, None, 0)))
    active = {k: 0 for k in ("collision", "track", "ax_limit", "gg_limit", "turn_limit", "reverse")}
    for x, u in zip(xs, us):
        expected = np_stage_terms(x, u, varying_track, VEHICLES, WEIGHTS)
        got = {k: np.asarray(v) for k, v in terms_fn(jnp.asarray(x)).items()}
        got["jerk"] = np.asarray(input_cost(jnp.asarray(u), game3.weights))
        assert set(got) == set(expected)
        for name in expected:
            # Same closed-form expressions in another order: rounding only. The gg norm uses
            # sqrt(a^2 + 1e-12), off by <= 1e-12 / (2 |a|) ~ 1e-13 m/s^2 for |a| ~ rho.
            np.testing.assert_allclose(got[name], expected[name], rtol=1e-10, atol=1e-10, err_msg=name)
            if name in active:
                active[name] += int(np.sum(expected[name] > 1e-3))
        total = sum(expected.values())
        np.testing.assert_allclose(np.asarray(game3.stage_costs(jnp.asarray(x), jnp.asarray(u))), total,
                                   rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(np.asarray(stage_fn(jnp.arange(3), jnp.asarray(x), jnp.asarray(u))),
                                   total, rtol=1e-10, atol=1e-10)
    # The sample exercises every penalty (else the comparison above would be vacuous).
    assert all(count >= 5 for count in active.values()), active


def test_collision_term_uses_wrapped_gap_and_mean_size(game3, varying_track):
    """Two cars 3 m apart across the lap line feel the same collision cost as 3 m apart mid-lap."""
    L = varying_track.length
    far = np.array([1e4, 1e4 + 5e3])  # third car far away (wrapped gap ~ L/2-ish)
    def collision(s0, s1):
        x = np.zeros((3, 6))
        x[:, 0] = [s0, s1, far[0]]
        x[:, 1] = 10.0
        x[:, 2] = [0.0, 1.0, -5.0]
        return np.asarray(state_cost_terms(jnp.asarray(x), game3.vehicles, game3.weights, game3.track)["collision"])

    across = collision(L - 1.0, 2.0 * L + 2.0)  # laps apart, 3 m ahead after wrapping
    mid = collision(500.0, 503.0)
    np.testing.assert_allclose(across[:2], mid[:2], rtol=1e-12)
    l01 = 0.5 * (4.7 + 5.2)
    w01 = 0.5 * (2.0 + 1.8)
    expected = 10.0 * np.exp(1.0 - (3.0 / l01) ** 2 - (1.0 / w01) ** 2) ** 2
    assert mid[0] == pytest.approx(expected, rel=1e-6)  # third car contributes < 1e-300


def test_terminal_cost_matches_paper(game3):
    """g_K^i = -s_K^i + c_g^i sum_{j != i} s_K^j for every player (raw cumulative s)."""
    rng = np.random.default_rng(1)
    c_gap = np.array([w.c_gap for w in WEIGHTS])
    for _ in range(5):
        x = rng.uniform(-50.0, 3000.0, (3, 6))
        s = x[:, 0]
        expected = np.array([-s[i] + c_gap[i] * sum(s[j] for j in range(3) if j != i) for i in range(3)])
        # Sums of three terms of size <= 3e3: rounding <= ~1e-12 relative.
        np.testing.assert_allclose(np.asarray(game3.terminal_costs(jnp.asarray(x))), expected, rtol=1e-12)
        for i in range(3):
            assert float(game3.terminal_cost(i, jnp.asarray(x))) == pytest.approx(expected[i], rel=1e-12)


def _designed_states(game):
    """Joint states of two cars where each max(z, 0)^2 argument z is clearly != 0 (|z| > 0.05),
    so the cost is smooth there; together they make every penalty active at least once."""
    L = game.track.length
    return {
        # car_0: beyond the left boundary, above ax_max, outside the gg circle; car_1 close by
        "all_active": np.array([[100.0, 19.0, 5.4, 0.1, 3.0, 17.0],
                                [103.0, 20.0, 3.0, -0.05, 1.0, -2.0]]),
        # car_0 beyond the right boundary and slow, turning harder than its steering allows;
        # car_1 above v_max braking, far away
        "right_boundary": np.array([[300.0, 3.0, -5.3, -0.2, -2.0, 3.0],
                                    [340.0, 27.0, 0.5, 0.0, -5.0, 16.0]]),
        # no boundary/limit penalties; cars 6 m apart across the lap line
        "inactive": np.array([[2.0, 15.0, 1.0, 0.05, 1.0, -2.0],
                              [L - 4.0, 15.0, -1.0, 0.0, 0.5, 4.0]]),
        # car_0 planned in reverse (-1.5 m/s), other limits inactive; car_1 far away
        "reversing": np.array([[500.0, -1.5, 0.5, 0.1, 1.0, 0.1],
                               [560.0, 12.0, 0.0, 0.0, 0.0, 1.0]]),
    }


def _penalty_arguments(x, track):
    """The arguments z of the max(z, 0)^2 penalties of each car, shape (N, 6)."""
    z = []
    for i, veh in enumerate(VEHICLES[: x.shape[0]]):
        s, v, n, _, ax, ay = x[i]
        wl = np_interp_closed(track, track.width_left, s) - 0.5 * veh.width
        wr = np_interp_closed(track, track.width_right, s) - 0.5 * veh.width
        z.append([n - wl, -n - wr, ax - veh.ax_max_0 * (1 - (v / veh.v_max) ** 2),
                  np.hypot(ax, ay) - veh.rho_0 - veh.rho_aero * v**2, abs(ay) - v**2 / veh.min_turn_radius, -v])
    return np.array(z)


def test_designed_states_cover_every_penalty(game2):
    """The derivative-test states are away from the kinks and activate every penalty term."""
    z = np.stack([_penalty_arguments(x, game2.track) for x in _designed_states(game2).values()])
    assert np.abs(z).min() > 0.05
    assert np.all((z > 0).any(axis=(0, 1)))  # left, right, ax, gg, turn and reverse penalties each active somewhere


@pytest.mark.parametrize("name", ["all_active", "right_boundary", "inactive", "reversing"])
def test_stage_cost_gradient_and_hessian_match_finite_differences(game2, name):
    """jax.grad and jax.hessian of game.stage_cost(i, x, u_i) w.r.t. x and u_i equal central FDs."""
    x0 = _designed_states(game2)[name]
    u_all = np.array([[12.0, -7.0], [-3.0, 20.0]])
    cost = jax.jit(game2.stage_cost)
    grad = jax.jit(jax.grad(game2.stage_cost, argnums=(1, 2)))
    hess = jax.jit(jax.hessian(game2.stage_cost, argnums=(1, 2)))
    for i in range(2):
        u0 = u_all[i]
        gx, gu = (np.asarray(g) for g in grad(i, jnp.asarray(x0), jnp.asarray(u0)))
        (hxx, hxu), (hux, huu) = ((np.asarray(b) for b in row) for row in hess(i, jnp.asarray(x0), jnp.asarray(u0)))
        value = float(cost(i, jnp.asarray(x0), jnp.asarray(u0)))

        def perturbed(fn, which, idx, h):
            xp, xm, up, um = x0.copy(), x0.copy(), u0.copy(), u0.copy()
            if which == "x":
                xp[idx] += h
                xm[idx] -= h
            else:
                up[idx] += h
                um[idx] -= h
            return fn(i, jnp.asarray(xp), jnp.asarray(up)), fn(i, jnp.asarray(xm), jnp.asarray(um))

        # Gradient: FD of the cost, h = 1e-6. Truncation h^2 |g'''| / 6 < 1e-9 (|g'''| <~ 1e3),
        # rounding ~ a few eps |g| / h (<= 1e-15 |g| / h, i.e. 1e-6 for |g| ~ 1e3).
        h = 1e-6
        scale = max(1.0, value)
        fd_gx = np.zeros_like(gx)
        for idx in np.ndindex(x0.shape):
            p, m = perturbed(cost, "x", idx, h)
            fd_gx[idx] = (float(p) - float(m)) / (2 * h)
        fd_gu = np.array([(float(p) - float(m)) / (2 * h)
                          for p, m in (perturbed(cost, "u", (k,), h) for k in range(2))])
        np.testing.assert_allclose(gx, fd_gx, rtol=1e-6, atol=1e-15 * scale / h + 1e-8)
        np.testing.assert_allclose(gu, fd_gu, rtol=1e-6, atol=1e-6)

        # Hessian: FD of the (just verified) JAX gradient, h = 1e-5. Truncation
        # h^2 |g''''| / 6 ~ 1e-7 and rounding eps |grad| / h ~ 1e-8: rtol 1e-5 on the scale.
        h = 1e-5
        fd_hxx = np.zeros(x0.shape + x0.shape)
        fd_hux = np.zeros((2,) + x0.shape)
        for idx in np.ndindex(x0.shape):
            (gxp, gup), (gxm, gum) = perturbed(grad, "x", idx, h)
            fd_hxx[(...,) + idx] = (np.asarray(gxp) - np.asarray(gxm)) / (2 * h)
            fd_hux[(...,) + idx] = (np.asarray(gup) - np.asarray(gum)) / (2 * h)
        fd_huu = np.zeros((2, 2))
        for k in range(2):
            (_, gup), (_, gum) = perturbed(grad, "u", (k,), h)
            fd_huu[:, k] = (np.asarray(gup) - np.asarray(gum)) / (2 * h)
        hscale = max(1.0, np.abs(hxx).max())
        np.testing.assert_allclose(hxx, fd_hxx, rtol=1e-5, atol=1e-5 * hscale)
        np.testing.assert_allclose(huu, fd_huu, rtol=1e-6, atol=1e-6)
        # u^i' R^i u^i is the only input term: Hessian 2 R^i, no mixed x-u terms (as in the paper).
        r = [WEIGHTS[i].r_jx, WEIGHTS[i].r_jy]
        np.testing.assert_allclose(huu, 2.0 * np.diag(r), rtol=1e-14)
        assert np.all(hxu == 0.0) and np.all(hux == 0.0) and np.all(np.abs(fd_hux) < 1e-6)
        if name == "all_active" and i == 0:
            # each penalty contributes curvature: the Hessian in car_0's own (n, V, ax, ay) is non-trivial
            assert np.abs(hxx[0, 2, 0, 2]) > 1.0 and np.abs(hxx[0, 4, 0, 4]) > 1.0


def test_total_costs_are_stage_plus_terminal_sums(game3, varying_track):
    """game.costs(xs, U) equals sum_k g_k^i(x_k, u_k^i) + g_K^i(x_K) for every player."""
    rng = np.random.default_rng(2)
    x0 = np.array([[10.0, 18.0, 1.0, 0.0, 0.0, 0.0],
                   [4.0, 20.0, -1.5, 0.02, 1.0, 0.0],
                   [-3.0, 22.0, 3.0, -0.03, 0.0, 2.0]])
    K = game3.horizon
    U = rng.uniform(-20.0, 20.0, (K, 3, 2))
    xs = np.asarray(game3.rollout(jnp.asarray(x0), jnp.asarray(U)))
    assert xs.shape == (K + 1, 3, 6)
    total = np.asarray(game3.costs(jnp.asarray(xs), jnp.asarray(U)))
    assert total.shape == (3,)
    expected = np.zeros(3)
    for i in range(3):
        expected[i] = sum(float(game3.stage_cost(i, jnp.asarray(xs[k]), jnp.asarray(U[k, i]))) for k in range(K))
        expected[i] += float(game3.terminal_cost(i, jnp.asarray(xs[-1])))
    # Sum of K + 1 terms of size <~ 1e3: rounding ~1e-12 relative.
    np.testing.assert_allclose(total, expected, rtol=1e-11, atol=1e-9)


def _close_scene() -> np.ndarray:
    """Three cars within a car length or two of each other: every pair's collision term is large."""
    return np.array([[100.0, 18.0, 0.0, 0.0, 0.0, 0.0],
                     [102.0, 19.0, 0.8, 0.02, 1.0, 0.0],
                     [98.5, 17.0, -0.7, -0.01, 0.0, 1.0]])


def test_cars_out_of_the_race_are_ghosts(game3):
    """A car out of the race neither causes nor feels collision cost, and its progress leaves
    the others' terminal costs; every other term is unchanged. All cars racing is the
    unmasked game, bit for bit."""
    x = jnp.asarray(_close_scene())
    full = {k: np.asarray(v) for k, v in state_cost_terms(x, game3.vehicles, game3.weights, game3.track).items()}
    assert np.all(full["collision"] > 1.0)  # every car feels the others: the masks below have work to do
    ghost = game3.with_racing([True, False, True])
    masked = {k: np.asarray(v) for k, v in
              state_cost_terms(x, ghost.vehicles, ghost.weights, ghost.track, ghost.racing).items()}
    # The collision term of the racing cars equals the unmasked one with car 1 far away.
    far = x.at[1, 0].set(x[1, 0] + 0.5 * game3.track.length)
    alone = np.asarray(state_cost_terms(far, game3.vehicles, game3.weights, game3.track)["collision"])
    np.testing.assert_array_equal(masked["collision"][[0, 2]], alone[[0, 2]])
    assert masked["collision"][1] == 0.0
    for name in full:
        if name != "collision":
            np.testing.assert_array_equal(masked[name], full[name], err_msg=name)
    s = np.asarray(x[:, 0])
    c_gap = np.array([w.c_gap for w in WEIGHTS])
    expected = -s + c_gap * np.array([s[2], s[0] + s[2], s[0]])  # no one counts car 1's progress
    np.testing.assert_allclose(np.asarray(ghost.terminal_costs(x)), expected, rtol=1e-14)
    everyone = game3.with_racing([True, True, True])
    u = jnp.asarray(np.random.default_rng(4).uniform(-5.0, 5.0, (3, 2)))
    assert np.array_equal(np.asarray(everyone.stage_costs(x, u)), np.asarray(game3.stage_costs(x, u)))
    assert np.array_equal(np.asarray(everyone.terminal_costs(x)), np.asarray(game3.terminal_costs(x)))
    assert game3.with_racing(None).racing is None


def test_a_ghost_does_not_couple_the_players(game3):
    """With car 1 out of the race, the racing cars' total costs do not depend on car 1's start
    state or inputs, nor car 1's on theirs (exactly: the cars interact through costs only)."""
    ghost = game3.with_racing(np.array([True, False, True]))
    U = jnp.asarray(np.random.default_rng(5).uniform(-10.0, 10.0, (game3.horizon, 3, 2)))
    x0 = jnp.asarray(_close_scene())

    def total(x0, U):
        return ghost.costs(ghost.rollout(x0, U), U)

    dx0, dU = jax.jacrev(total, argnums=(0, 1))(x0, U)  # (3, 3, 6), (3, K, 3, 2)
    assert np.all(np.asarray(dx0)[[0, 2]][:, 1] == 0.0) and np.all(np.asarray(dU)[[0, 2]][:, :, 1] == 0.0)
    assert np.all(np.asarray(dx0)[1][[0, 2]] == 0.0) and np.all(np.asarray(dU)[1][:, [0, 2]] == 0.0)
    # ...while the racing cars 0 and 2 still interact (else the zeros above prove nothing)
    assert np.abs(np.asarray(dU)[0][:, 2]).max() > 1e-3


def test_with_racing_refuses_malformed_flags(game3):
    for bad in ([True, False], [1, 0, 1], np.ones((3, 1), dtype=bool), "all"):
        with pytest.raises(ValueError, match="racing must be 3 booleans"):
            game3.with_racing(bad)


def test_rollout_shapes_and_consistency_with_step(game3):
    """rollout(x0, U) has shape (K+1, N, 6), starts at x0 and follows game.step."""
    rng = np.random.default_rng(3)
    x0 = np.array([[0.0, 15.0, 0.0, 0.0, 0.0, 0.0], [-8.0, 16.0, 2.0, 0.0, 0.0, 0.0],
                   [-16.0, 17.0, -2.0, 0.0, 0.0, 0.0]])
    for K in (1, 4):
        U = rng.uniform(-10.0, 10.0, (K, 3, 2))
        xs = np.asarray(game3.rollout(jnp.asarray(x0), jnp.asarray(U)))
        assert xs.shape == (K + 1, 3, 6) and xs.dtype == np.float64
        assert np.array_equal(xs[0], x0)
        for k in range(K):
            # scan and a standalone step may fuse differently: rounding-level agreement.
            np.testing.assert_allclose(xs[k + 1], np.asarray(game3.step(jnp.asarray(xs[k]), jnp.asarray(U[k]))),
                                       rtol=1e-13, atol=1e-12)


def test_cost_weights_validation():
    """CostWeights refuses a non-positive-definite R and negative penalty weights."""
    with pytest.raises(ValueError, match="r_jx must be > 0"):
        CostWeights(r_jx=0.0)
    with pytest.raises(ValueError, match="c_track must be >= 0"):
        CostWeights(c_track=-1.0)
