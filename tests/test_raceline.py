"""The racing-line driver (``raceline``, :class:`planners.RacelineAgent`): alone it laps a circuit
on the track within 3% of the lap-time limit; it races as a JAX law in the vectorised env and
as a compiled opponent of the JAX learner; its options are checked; in traffic it keeps to its
rules (:mod:`planners.traffic`), where the old driver (``yield=false``) runs into cars."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from planners import RacelineAgent, make_agent
from planners.agents.batched import BatchedScripted, make_batched_opponent
from planners.scripted import BRAKE_ACTION, RacelineDriver, jax_policy
from racing_env import limits
from racing_env.track import circuit_names


def time_trial(track: str, spec: str = "raceline", max_steps: int = 4000) -> tuple[float | None, int, float]:
    """One lap alone from the grid: (finish time [s], steps off the track, the lap-time limit [s]
    of the default car on the shipped racing line, or the centre line where none is shipped)."""
    env = racing_env.parallel_env(track=track, num_agents=1, laps=1, max_steps=max_steps)
    observations, infos = env.reset(seed=0)
    agent = make_agent(spec)
    agent.reset(0, 0, env)
    off = 0
    finish = None
    while env.agents:
        action = agent.act(observations["car_0"], env.state())
        observations, _, _, _, infos = env.step({"car_0": action})
        off += int(infos["car_0"]["off_track"])
        finish = infos["car_0"]["finish_time"]
    line = "raceline" if limits.has_raceline(env.track) else "centerline"
    return finish, off, limits.lap_time_limit(env.track, line=line)


@pytest.mark.parametrize("track", ["Monza", pytest.param("Suzuka", marks=pytest.mark.slow)])
def test_alone_it_laps_a_circuit_on_the_track_within_3_percent_of_the_limit(track):
    """The limit is a flying lap; the driver starts rolling at about 15 m/s from the grid (about
    0.3% of a lap) and lags the limit by its acceleration lag and jerk limits."""
    finish, off, limit = time_trial(track)
    assert finish is not None and off == 0
    assert limit < finish < 1.03 * limit


@pytest.mark.slow
@pytest.mark.parametrize("track", circuit_names() + ["trefoil"])
def test_alone_it_laps_every_shipped_circuit_on_the_track_within_3_percent_of_the_limit(track):
    finish, off, limit = time_trial(track)
    assert finish is not None and off == 0
    assert limit < finish < 1.03 * limit


def test_a_slower_pace_laps_slower():
    """pace=0.9 drives 90% of the limit's speeds: about 1/0.9 of the lap time (the start and
    the controller's lag make it a little less or more)."""
    finish, off, limit = time_trial("trefoil", "raceline:pace=0.9")
    fast, _, _ = time_trial("trefoil")
    assert off == 0 and fast < finish
    assert finish == pytest.approx(limit / 0.9, rel=0.03)


def test_options_are_checked_before_the_race():
    for spec, match in (("raceline:pace=0", r"pace must be in \(0, 1\]"), ("raceline:pace=1.2", "pace must be"),
                        ("raceline:margin=-1", "margin must be a finite distance >= 0"),
                        ("raceline:line=apex", "line must be 'raceline' or 'centerline'"),
                        ("raceline:target_n=1", "has no option"), ("raceline:yield=maybe", "expected true or false"),
                        ("raceline:time_gap=-0.5", "time_gap must be a finite time >= 0"),
                        ("raceline:standstill=0", "standstill must be a finite distance > 0"),
                        ("raceline:time_gap=nan", "time_gap must be")):
        with pytest.raises(ValueError, match=match):
            make_agent(spec)
    assert isinstance(make_agent("raceline:pace=0.95,margin=1.5"), RacelineAgent)
    assert isinstance(make_agent("raceline:yield=false,time_gap=0,standstill=2"), RacelineAgent)
    with pytest.raises(ValueError, match="yield must be true"):
        RacelineDriver(racing_env.track.trefoil(), 0, yielding="no")


def test_its_jax_law_is_its_action_and_races_vmapped_in_the_vector_env():
    game = racing_env.parallel_env(track="Monza", num_agents=2).game
    opponent = make_batched_opponent("raceline:pace=0.95", game, 1, 4)
    assert isinstance(opponent, BatchedScripted)
    driver = RacelineDriver(game.track, 1, game.vehicles.car(1), pace=0.95)
    rng = np.random.default_rng(0)
    x = np.zeros((4, 2, 6))
    x[:, :, 0] = rng.uniform(0, game.track.length, (4, 2))
    x[:, :, 1] = rng.uniform(5, 25, (4, 2))
    x[:, :, 2] = rng.uniform(-3, 3, (4, 2))
    x[:, :, 3:] = rng.uniform(-0.2, 0.2, (4, 2, 3)) * [1, 20, 20]
    x[2, 1, 1] = np.nan  # its own state not finite: it brakes
    batched = np.asarray(jax.jit(jax.vmap(opponent.jax_policy))(x))
    for b in range(4):
        single = np.asarray(jax.jit(jax_policy(driver))(x[b]))
        np.testing.assert_array_equal(batched[b], single)
        np.testing.assert_allclose(driver(None, x[b]), single, rtol=1e-6, atol=1e-7)  # float32 of the same law
    np.testing.assert_array_equal(batched[2], BRAKE_ACTION)
    assert np.all(np.abs(batched) <= 1.0)


def test_it_is_a_compiled_opponent_of_the_jax_learner():
    from experiments.rl.train import TrainConfig
    from experiments.rl.train_jax import compiled_races

    races = compiled_races(TrainConfig(learner="jax", opponents=("raceline",), track="Monza", race_distance=300.0))
    assert races is not None


# --------------------------------------------------------------------------------------
# The rules in traffic (planners.traffic): scenes driven by the laws alone, through the
# env's car physics (racing_env.physics.drive), contact judged by the env's footprint test.
# --------------------------------------------------------------------------------------


def drive_scene(track, drivers: list[dict], x0: np.ndarray, steps: int = 300, racing: np.ndarray | None = None,
                parked: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Every car driven by a :class:`RacelineDriver` with the keyword arguments ``drivers[i]``
    from ``x0 (N, 6)`` for ``steps`` steps of the env's physics (one compiled scan), but the
    ``parked`` cars, which stay where they are: the states ``(steps, N, 6)`` after each step
    and whether car 0's footprint overlaps car 1's in each. ``racing (N,)``: the drivers'
    racing flags (None: all race)."""
    from racing_env.game import RaceGame
    from racing_env.physics import drive, footprint_overlap
    from racing_env.vehicle import VehicleParams

    game = RaceGame.create(track, [VehicleParams()] * len(drivers))
    laws = [RacelineDriver(track, i, game.vehicles.car(i), fleet=game.vehicles, **kw).jax_law()
            for i, kw in enumerate(drivers)]
    flags = jnp.ones(len(drivers), dtype=bool) if racing is None else jnp.asarray(racing)
    held = jnp.isin(jnp.arange(len(drivers)), jnp.asarray(parked, dtype=int))[:, None]

    def step(x, _):
        x = jnp.where(held, x, drive(game, x, jnp.stack([law(x, flags) for law in laws])))
        return x, (x, footprint_overlap(x, game.vehicles, track)[0, 1])

    xs, overlap = jax.jit(lambda x: jax.lax.scan(step, x, None, length=steps)[1])(jnp.asarray(x0, jnp.float64))
    return np.asarray(xs), np.asarray(overlap)


def start(s, v, n=(0.0, 0.0)) -> np.ndarray:
    x0 = np.zeros((len(s), 6))
    x0[:, 0], x0[:, 1], x0[:, 2] = s, v, n
    return x0


def test_behind_a_slower_car_on_its_line_it_passes_without_contact_where_the_old_driver_runs_into_it():
    """Trefoil: a car at 60% of the limit's pace drives the line 30 m ahead. The old driver
    (yield=false) drives its line through it; the new one pulls out to the side with room
    and passes, its footprint never touching the slower car's in 300 steps (30 s)."""
    from racing_env import track

    x0 = start([10.0, 40.0], [20.0, 12.0])
    slow = dict(pace=0.6, yielding=False)
    xs_old, overlap_old = drive_scene(track.trefoil(), [dict(yielding=False), slow], x0)
    xs_new, overlap_new = drive_scene(track.trefoil(), [{}, slow], x0)
    assert overlap_old.sum() > 0
    assert overlap_new.sum() == 0
    assert xs_new[-1, 0, 0] > xs_new[-1, 1, 0] + 100.0  # passed, and long gone
    assert np.abs(xs_new[:, 0, 2]).max() > 2.0  # beside the slower car, not through it


def test_a_pass_begins_within_its_reach_and_not_before():
    """A 2 km straight, a car at 12 m/s on the line ahead of one at 20 m/s: 200 m behind it
    the driver keeps to its line (where the car ahead is now says nothing of where it will be);
    it pulls out once the bumper gap is within standstill + PASS_LOOKAHEAD V (3 + 1.5 x 20 =
    33 m) and passes."""
    from planners.traffic import PASS_LOOKAHEAD, RACELINE_STANDSTILL
    from racing_env import track

    wide = track.straight(length=2000.0, width_left=6.0, width_right=6.0)
    xs, overlap = drive_scene(wide, [{}, dict(pace=0.6, yielding=False)], start([0.0, 205.0], [20.0, 12.0]),
                              steps=400)
    gap = xs[:, 1, 0] - xs[:, 0, 0] - 4.7
    moved = np.flatnonzero(np.abs(xs[:, 0, 2]) > 0.05)
    assert overlap.sum() == 0 and moved.size > 0
    assert gap[moved[0]] < RACELINE_STANDSTILL + PASS_LOOKAHEAD * xs[moved[0], 0, 1] + 1.0
    assert gap[moved[0]] > 5.0  # out before it had to brake for the car ahead
    assert xs[-1, 0, 0] > xs[-1, 1, 0]  # passed


@pytest.mark.slow  # two AV-21 duels of the law (about 12 s)
def test_behind_an_equal_av21_it_keeps_to_the_track():
    """Two AV-21s driven by the racing-line driver, a lap of Suzuka from the grid, both seeds:
    the car behind keeps to the track. Before a pass began within its reach, and before the
    driver slowed for the corners of a path off its line, it left the track for 12-14 s a lap
    (a pass begun 200 m behind held it off its line into the esses at the line's speeds)."""
    from experiments.race_spec import RaceSpec
    from experiments.tournament import race_lineup

    race = RaceSpec(track="Suzuka", car="av21").to_race_config(2)
    for seed in (0, 1):
        record, _ = race_lineup(race, ["raceline", "raceline"], seed, replay=False)
        assert [car["time_off_track"] for car in record["cars"]] == [0.0, 0.0], seed
        assert all(car["finish_time"] is not None for car in record["cars"])


def test_where_there_is_no_room_to_pass_it_follows_at_its_time_gap():
    """A 7 m wide straight: no room beside a car on the centre line (the pass would need the
    car's centre 3 m off it, 1.25 m inside a boundary 3.5 m off). Behind a car at 12.5 m/s the
    driver settles at the gap standstill + time_gap V = 3 + 0.5 * 12.5 = 9.25 m; it never
    touches it; behind a stopped car it stops at the standstill gap, from 25 m/s."""
    from racing_env import track

    narrow = track.straight(length=2000.0, width_left=3.5, width_right=3.5)
    xs, overlap = drive_scene(narrow, [{}, dict(pace=0.5, yielding=False)], start([0.0, 30.0], [20.0, 12.0]))
    gap = xs[:, 1, 0] - xs[:, 0, 0] - 4.7
    assert overlap.sum() == 0 and gap.min() > 3.0
    assert np.abs(xs[:, 0, 2]).max() < 0.05  # it stayed on its line
    assert gap[-1] == pytest.approx(3.0 + 0.5 * 12.5, abs=0.1)
    assert xs[-1, 0, 1] == pytest.approx(12.5, abs=0.01)

    # a car at rest 80 m ahead
    xs, overlap = drive_scene(narrow, [{}, {}], start([0.0, 80.0], [25.0, 0.0]), parked=(1,))
    gap = xs[:, 1, 0] - xs[:, 0, 0] - 4.7
    assert overlap.sum() == 0 and xs[-1, 0, 1] == pytest.approx(0.0, abs=1e-6)
    assert gap[-1] == pytest.approx(3.0, abs=0.05) and gap.min() > 2.9


def test_it_does_not_move_across_into_a_car_alongside():
    """The old driver's incident: beside a car on its line, 2 m behind it, it steered onto
    its line into it. The new one holds its lane while alongside, drops back and merges
    behind."""
    from racing_env import track

    x0 = start([10.0, 12.0], [20.0, 20.0], n=(-2.6, 0.0))
    line = dict(yielding=False)
    _, overlap_old = drive_scene(track.trefoil(), [line, line], x0, steps=100)
    xs, overlap_new = drive_scene(track.trefoil(), [{}, line], x0, steps=100)
    assert overlap_old.sum() > 0 and overlap_new.sum() == 0
    assert xs[-1, 1, 0] > xs[-1, 0, 0] + 4.7 and abs(xs[-1, 0, 2]) < 0.2  # behind it, on its line


def test_cars_out_of_the_race_are_not_traffic():
    """The env freezes a car that finished or retired, and nobody collides with it: with its
    racing flag off the driver drives its line through it, as the old driver does (to the last
    bits: the two laws are different programs)."""
    from racing_env import track

    narrow = track.straight(length=2000.0, width_left=3.5, width_right=3.5)
    x0 = start([0.0, 60.0], [20.0, 0.0])
    out = np.array([True, False])
    xs_new, _ = drive_scene(narrow, [{}, {}], x0, steps=100, racing=out, parked=(1,))
    xs_old, _ = drive_scene(narrow, [dict(yielding=False), {}], x0, steps=100, racing=out, parked=(1,))
    assert xs_new[-1, 0, 0] > xs_new[-1, 1, 0] + 100.0
    np.testing.assert_allclose(xs_new, xs_old, rtol=0, atol=1e-9)


def test_with_no_car_near_its_action_is_the_old_drivers():
    """With no car near, the rules change no number of the law (a select of the line's target,
    a minimum with +inf): at 200 random states of Monza with the other car beyond the
    look-ahead ahead or more than a car behind, or out of the race, the action is the old
    driver's. Bit for bit under XLA's default optimisations (a lap of Monza alone: every
    action equal); the test run's quick compile fuses the larger program's multiply-adds
    differently, so here to the last bits. A lap of the trefoil with the other car half a
    lap away gives the old driver's states to rounding."""
    from racing_env import track

    game = racing_env.parallel_env(track="Monza", num_agents=2).game
    new = jax.jit(RacelineDriver(game.track, 0, game.vehicles.car(0), fleet=game.vehicles).jax_law())
    old = jax.jit(RacelineDriver(game.track, 0, game.vehicles.car(0), yielding=False).jax_law())
    rng = np.random.default_rng(1)
    x = np.zeros((200, 2, 6))
    x[:, 0, 0] = rng.uniform(0, game.track.length, 200)
    x[:, 1, 0] = x[:, 0, 0] + rng.choice([-1, 1], 200) * rng.uniform(120.0, 0.5 * game.track.length, 200)
    x[:, :, 1] = rng.uniform(0, 25, (200, 2))
    x[:, :, 2] = rng.uniform(-4, 4, (200, 2))
    x[:, :, 3:] = rng.uniform(-0.2, 0.2, (200, 2, 3)) * [1, 20, 20]
    out = np.array([True, False])
    both = np.ones(2, dtype=bool)
    for b in range(200):
        np.testing.assert_allclose(new(x[b], both), old(x[b], both), rtol=0, atol=1e-12)
        x_near = x[b].copy()
        x_near[1, :3] = x_near[0, :3] + [5.0, 0.0, 0.0]  # right in front, but out of the race
        np.testing.assert_allclose(new(x_near, out), old(x_near, out), rtol=0, atol=1e-12)

    trefoil = track.trefoil()
    x0 = start([10.0, 10.0 + 0.5 * trefoil.length], [15.0, 15.0])
    xs_new, _ = drive_scene(trefoil, [{}, {}], x0, steps=600)
    xs_old, _ = drive_scene(trefoil, [dict(yielding=False), dict(yielding=False)], x0, steps=600)
    np.testing.assert_allclose(xs_new, xs_old, rtol=0, atol=1e-9)


def test_the_vectorised_env_hands_its_law_the_racing_flags():
    """The vectorised env's compiled step calls the law with the race's ``active`` flags
    (:func:`racing_env.vector.policy_action`): a car stopped 8 m ahead on the line makes it
    brake only while that car races; a plain JAX policy gets the state alone."""
    from racing_env import track
    from racing_env.vector import coasting, policy_action

    trefoil = track.trefoil()
    law = jax.jit(RacelineDriver(trefoil, 0).jax_law())  # the jitted law keeps the mark
    x = start([10.0, 22.7], [20.0, 0.0])
    racing, out = np.ones(2, dtype=bool), np.array([True, False])
    np.testing.assert_array_equal(policy_action(law, x, racing), law(x, racing))
    np.testing.assert_array_equal(policy_action(law, x, out), law(x, out))
    assert float(law(x, racing)[0]) == -1.0 and float(law(x, out)[0]) > -0.5
    np.testing.assert_array_equal(policy_action(coasting, x, out), coasting(x))
