"""Contact physics (racing_env.contact) and the steward (racing_env.steward) on canonical scenes.

Each scene starts two cars on a straight (6 m either side of the centre line) and lets them
coast (zero jerk keeps their accelerations), so where and how they meet is known from the
start: the expected verdicts are those docs/rules.md states for such a scene. The physics
checks are exact identities of an impulse (momentum) and inequalities that hold for any
restitution in [0, 1] with friction that only opposes sliding (energy, speed).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from experiments.rules_figure import defend
from racing_env import contact as contact_lib
from racing_env import track as tr
from racing_env.dynamics import CHI, N_LAT, S, V
from racing_env.scenarios import START_MARGIN, grid_starts
from racing_env.steward import DEFAULT_RULES, RULES
from racing_env.vehicle import VehicleParams

STRAIGHT = tr.straight(length=400.0)
FAST = VehicleParams(v_max=60.0)  # so a coasting car holds 45 m/s: a 40 m/s closing speed
COAST = np.zeros(2)


def _x0(*cars):
    """``(N, 6)`` from ``(s, V, n, chi, ax)`` per car."""
    x = np.zeros((len(cars), 6))
    for i, car in enumerate(cars):
        x[i, :len(car)] = car
    return x


def _race(x0, steps=40, **config):
    """Coast the cars of ``x0`` for up to ``steps`` steps: the joint states ``(T+1, N, 6)`` and
    every incident as ``(step, car, incident dict)`` seen from each car."""
    env = racing_env.parallel_env(track=STRAIGHT, num_agents=len(x0), race_distance=390.0, **config)
    env.reset(seed=0, options={"x0": x0})
    xs, incidents, last = [env.state()], [], {}
    for k in range(steps):
        if not env.agents:
            break
        _, _, _, _, infos = env.step({a: COAST for a in env.agents})
        xs.append(env.state())
        incidents += [(k + 1, agent, i) for agent, info in infos.items() for i in info["incidents"]]
        last.update(infos)
    return np.stack(xs), incidents, last


def _verdicts(incidents):
    """``{car: (verdict, at_fault)}`` of the first incident, from each car's side."""
    first = min(step for step, _, _ in incidents)
    return {agent: (i["verdict"], i["at_fault"]) for step, agent, i in incidents if step == first}


@pytest.mark.parametrize("closing, vehicles", [(5.0, VehicleParams()), (40.0, FAST)])
def test_a_rear_end_is_the_fault_of_the_car_behind(closing, vehicles):
    """The car behind runs into the car ahead on the same line: it answers, and the cars
    leave the contact apart, the one behind never ahead of the one in front."""
    xs, incidents, infos = _race(_x0((10.0, 5.0 + closing), (20.0, 5.0)), vehicles=vehicles)
    assert _verdicts(incidents) == {"car_0": ("rear-end", True), "car_1": ("rear-end", False)}
    speed = next(i["closing_speed"] for _, _, i in incidents)
    assert speed == pytest.approx(closing, rel=1e-9)  # coasting: the speeds are the start's
    assert np.all(xs[:, 1, S] - xs[:, 0, S] >= float(vehicles.length))  # never through, never overlapping
    assert infos["car_0"]["penalty"] == 5.0 and infos["car_1"]["penalty"] == 0.0
    assert infos["car_0"]["faults"] == 1 and infos["car_1"]["faults"] == 0


def test_a_car_that_moves_across_into_a_car_alongside_answers():
    """The car ahead, alongside, moves across (3 m/s to the right) into the car on its right,
    which holds its line."""
    _, incidents, _ = _race(_x0((10.0, 20.0, -2.0), (12.0, 20.0, 1.0, -0.15)))
    assert _verdicts(incidents) == {"car_0": ("moved-across", False), "car_1": ("moved-across", True)}


def test_squeezing_a_car_alongside_off_the_track_answers():
    """The same move against a car with less than a car's width between it and the edge."""
    _, incidents, _ = _race(_x0((10.0, 20.0, -3.9), (12.0, 20.0, -1.0, -0.15)))
    assert _verdicts(incidents) == {"car_0": ("squeeze", False), "car_1": ("squeeze", True)}


def test_a_faster_car_from_behind_into_the_rear_corner_of_a_car_moving_across_answers_for_a_rear_end():
    """A car 4 m/s faster, 1.5 m to the side and a car's length behind, runs into the rear
    corner of a car ahead that moves across its path at 1 m/s: the corners meet, but the
    car behind was never alongside; the footprints meet end to end and the car behind
    answers (not a move across by the car ahead)."""
    _, incidents, _ = _race(_x0((14.5, 24.0, -1.5), (20.0, 20.0, 0.0, -0.05)), steps=10)
    assert _verdicts(incidents) == {"car_0": ("rear-end", True), "car_1": ("rear-end", False)}


def test_a_brake_test_is_the_fault_of_the_car_ahead():
    """The car ahead brakes at 10 m/s^2 at 12 m/s on a straight that asks for no braking (its
    line's speed there is its top speed, 25 m/s): the car behind runs into it, and the car
    ahead answers."""
    _, incidents, _ = _race(_x0((10.0, 20.0, 0.0, 0.0, 0.0), (16.5, 12.0, 0.0, 0.0, -10.0)))
    assert _verdicts(incidents) == {"car_0": ("brake-test", False), "car_1": ("brake-test", True)}


def test_cars_touching_side_by_side_without_moving_across_are_a_racing_incident():
    _, incidents, infos = _race(_x0((10.0, 20.0, -0.9), (11.0, 20.0, 0.9)), steps=5)
    assert _verdicts(incidents) == {"car_0": ("racing-incident", False), "car_1": ("racing-incident", False)}
    assert infos["car_0"]["penalty"] == infos["car_1"]["penalty"] == 0.0


@pytest.mark.parametrize("moves, rules, verdict, weaver_answers", [
    (5, RULES, "weaving", True),
    (5, DEFAULT_RULES, "rear-end", False),
    (2, RULES, "rear-end", False),
])
def test_a_defender_that_changes_direction_more_than_once_answers_under_the_weaving_rule(
        moves, rules, verdict, weaver_answers):
    """The car ahead moves across the straight left, right, left... with the car behind
    closing: after its second change of direction, a rear-end is its fault under the
    optional ``weaving`` rule; one move and back (one change) is allowed, and without the
    rule the car behind answers."""
    _, incidents, _ = defend(moves, rules)
    assert _verdicts(incidents) == {"car_0": (verdict, not weaver_answers), "car_1": (verdict, weaver_answers)}


def test_direction_changes_count_only_while_defending_on_a_straight():
    """A car that moves left, right and left again with a car 10 m behind on a straight
    makes two changes of direction; with nobody within the defending gap (20 m) behind, or
    on a curve, it makes none."""
    from racing_env.steward import count_direction_changes, make_steward

    def count(track, behind, at=100.0):
        steward = make_steward(track, VehicleParams(), 2)
        last, changes = jnp.zeros(2, dtype=jnp.int32), jnp.zeros(2, dtype=jnp.int32)
        for lateral in (1.0, -1.0, 1.0):
            x = jnp.asarray(_x0((at - behind, 20.0), (at, 20.0, 0.0, np.arcsin(lateral / 20.0))))
            last, changes = count_direction_changes(x, jnp.ones(2, dtype=bool), last, changes, steward, track)
        return int(changes[1])

    assert count(STRAIGHT, behind=10.0) == 2
    assert count(STRAIGHT, behind=30.0) == 0
    assert count(tr.trefoil(), behind=10.0, at=150.0) == 0  # a curve of 90 m radius


def test_a_rule_left_out_makes_its_cases_racing_incidents():
    _, incidents, _ = _race(_x0((10.0, 10.0), (20.0, 5.0)), rules=("moved-across", "squeeze"))
    assert _verdicts(incidents) == {"car_0": ("racing-incident", False), "car_1": ("racing-incident", False)}


def test_cars_meeting_head_on_at_twice_the_top_speed_do_not_pass_through():
    """A car driving backwards (chi = pi) at the top speed meets one driving forwards at it:
    50 m/s, more than a car's length per step, yet they meet and stay on their sides."""
    xs, incidents, _ = _race(_x0((10.0, 25.0), (18.0, 25.0, 0.0, np.pi)), steps=10)
    assert incidents
    assert np.all(xs[:, 1, S] - xs[:, 0, S] > 0.0)


def test_ghost_cars_drive_through_each_other():
    xs, incidents, _ = _race(_x0((10.0, 10.0), (20.0, 5.0)), contact="ghost", penalties="none")
    assert incidents  # still judged
    assert xs[-1, 0, S] > xs[-1, 1, S]  # but the car behind drove through


def test_a_drive_through_slows_the_car_at_fault_to_pit_speed():
    xs, incidents, infos = _race(_x0((10.0, 15.0), (20.0, 10.0)), steps=60, penalties="drive-through")
    first = min(step for step, _, _ in incidents)
    pit = 0.5 * 25.0
    assert np.all(xs[first + 2:, 0, V] <= pit + 1e-12)
    assert infos["car_0"]["penalty"] == 0.0


def test_disqualification_retires_the_car_at_its_kth_incident():
    _, incidents, infos = _race(_x0((10.0, 15.0), (20.0, 10.0)), steps=20, penalties="disqualify", disqualify_after=1)
    assert incidents and infos["car_0"]["out"] and not infos["car_1"]["out"]


def test_a_penalised_car_is_placed_by_its_race_time():
    """The car ahead moves across into the car alongside and crosses the line first; with a
    20 s time penalty it is placed second."""
    env = racing_env.parallel_env(track=STRAIGHT, num_agents=2, race_distance=100.0, penalty_seconds=20.0)
    env.reset(seed=0, options={"x0": _x0((10.0, 20.0, -2.0), (12.0, 22.0, 1.0, -0.15))})
    result = {}
    while env.agents:
        _, _, _, _, infos = env.step({a: COAST for a in env.agents})
        result.update(infos)
    assert result["car_1"]["faults"] == 1 and result["car_1"]["penalty"] == 20.0
    assert result["car_1"]["finish_time"] < result["car_0"]["finish_time"] < result["car_1"]["finish_time"] + 20.0
    assert result["car_1"]["position"] == 1  # on the road, until the other car finishes
    assert result["car_0"]["position"] == 1 and env.positions.tolist() == [1, 2]


# --- the impulse itself ---------------------------------------------------------------------------
def _random_meeting(rng, num=2):
    """Two cars that meet in the step from x0 to x1 (coasting straight ahead at their heading)."""
    x0 = np.zeros((num, 6))
    x0[:, S] = 50.0 + rng.uniform(-3.0, 3.0, num)
    x0[:, N_LAT] = rng.uniform(-2.0, 2.0, num)
    x0[:, V] = rng.uniform(0.0, 40.0, num)
    x0[:, CHI] = rng.uniform(-0.6, 0.6, num)
    x1 = x0.copy()
    x1[:, S] += 0.1 * x0[:, V] * np.cos(x0[:, CHI])
    x1[:, N_LAT] += 0.1 * x0[:, V] * np.sin(x0[:, CHI])
    return x0, x1


@jax.jit
def _collide(x0, x1, masses, restitution, friction):
    vehicles = VehicleParams(mass=masses)
    model = contact_lib.ContactModel(True, restitution, friction, jnp.float64(0.02))
    hit = contact_lib.sweep(x0, x1, jnp.ones(2, bool), vehicles, STRAIGHT)
    return hit, contact_lib.collide(x0, x1, hit, vehicles, model, STRAIGHT, 0.1)


def _velocities(x):
    return x[:, V, None] * np.stack([np.cos(x[:, CHI]), np.sin(x[:, CHI])], axis=-1)


@pytest.mark.parametrize("masses", [(800.0, 800.0), (600.0, 1000.0)])
def test_an_impulse_conserves_momentum_and_adds_no_kinetic_energy(masses):
    rng = np.random.default_rng(0)
    met = 0
    for _ in range(200):
        x0, x1 = _random_meeting(rng)
        e, mu = rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)
        hit, after = _collide(x0, x1, np.asarray(masses), e, mu)
        if not bool(hit.touch[0, 1]):
            continue
        met += 1
        m = np.asarray(masses)[:, None]
        before_v, after_v = _velocities(x1), _velocities(np.asarray(after))
        # equal and opposite impulses: the pair's momentum, along the normal and across it
        np.testing.assert_allclose((m * after_v).sum(0), (m * before_v).sum(0), rtol=0, atol=1e-9 * 1000 * 40)
        energy = lambda v: 0.5 * float(np.sum(m * v**2))  # noqa: E731
        assert energy(after_v) <= energy(before_v) * (1 + 1e-12)
    assert met >= 50  # the scenes are close enough that many meet


def test_in_a_rear_end_no_car_gains_more_speed_than_the_other_loses():
    rng = np.random.default_rng(1)
    for _ in range(50):
        v_ahead = rng.uniform(0.0, 40.0)
        v_behind = v_ahead + rng.uniform(1.0, 10.0)
        x0 = _x0((50.0, v_behind), (54.75, v_ahead))
        x1 = x0.copy()
        x1[:, S] += 0.1 * x0[:, V]
        hit, after = _collide(x0, x1, np.asarray([800.0, 800.0]), rng.uniform(0.0, 1.0), 0.5)
        after = np.asarray(after)
        gained, lost = after[1, V] - x1[1, V], x1[0, V] - after[0, V]
        assert bool(hit.touch[0, 1]) and gained >= 0.0 and gained <= lost + 1e-12


def test_cars_that_do_not_meet_keep_their_step_bit_for_bit():
    x0 = _x0((10.0, 20.0), (40.0, 20.0))
    x1 = x0.copy()
    x1[:, S] += 2.0
    hit, after = _collide(x0, x1, np.asarray([800.0, 800.0]), 0.3, 0.5)
    assert not bool(hit.touch.any())
    np.testing.assert_array_equal(np.asarray(after), x1)


# --- starts and configuration ---------------------------------------------------------------------
def test_no_grid_starts_two_cars_closer_than_the_margin():
    with pytest.raises(ValueError, match="under the 0.5 m every start keeps"):
        grid_starts(STRAIGHT, 3, row_spacing=4.0)
    starts = grid_starts(STRAIGHT, 20)
    slots = np.asarray(starts.slots)
    gaps = [max(abs(a[S] - b[S]) - 2.0 - 4.7, abs(a[N_LAT] - b[N_LAT]) - 0.6 - 2.0)
            for k, a in enumerate(slots) for b in slots[k + 1:]]
    assert min(gaps) >= START_MARGIN


@pytest.mark.parametrize("field, value, message", [
    ("contact", "soft", "contact must be one of"),
    ("restitution", -0.1, "restitution must be a number in"),
    ("contact_friction", -1.0, "contact_friction must be"),
    ("penalties", "fine", "penalties must be one of"),
    ("penalty_seconds", -5.0, "penalty_seconds must be"),
    ("disqualify_after", 0, "disqualify_after must be"),
    ("rules", ("rear-end", "blocking"), "unknown rule"),
    ("severity_speed", 0.0, "severity_speed must be"),
])
def test_bad_contact_and_steward_settings_are_refused_with_the_allowed_values(field, value, message):
    with pytest.raises(ValueError, match=message):
        racing_env.RaceConfig(**{field: value})


# --- the fuzz ---------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("track, actions", [("Monza", "uniform"), ("Spa", "saturated"), ("Suzuka", "uniform")])
def test_twenty_car_scenes_race_without_pass_through_and_every_incident_judged(track, actions):
    """A third of 10^6 race-steps per case: 20-car close-quarters scenes (``anywhere``) on a
    real circuit, 256 races of 1,300 steps, every car driven by uniform random actions in the
    box or by saturated ones (each axis -1 or +1). Nothing becomes non-finite; no two racing
    cars swap their order along the track while their footprints overlap across it at both
    ends of the step (a pass-through); every contact that begins an incident is judged once,
    with a verdict of :data:`VERDICTS` and at most one car at fault.

    The order along the track is an order in metres only where the track's frame holds: a
    car more than half a corner's radius off the centre line towards the corner's centre
    (``1 - n kappa < 0.5``; random drivers reach 80 m off the track, past the centre) has an
    arc length that no longer says where it is, so a pass-through is looked for where both
    cars of the pair are inside that region at both ends of the step."""
    from racing_env import race
    from racing_env.steward import VERDICTS

    env = racing_env.parallel_env(track=track, num_agents=20, scenario="anywhere", max_steps=10**6, laps=100)
    params = env.params
    races, steps, width = 256, 1300, float(VehicleParams().width)

    def one_race(key):
        key, x0, _, _ = race.next_start(key, params)
        state, _, _ = race.start(x0, params)

        def step(carry, k):
            state, key = carry
            key, k_act = jax.random.split(key)
            raw = jax.random.uniform(k_act, (20, 2), minval=-1.0, maxval=1.0)
            act = jnp.sign(raw) if actions == "saturated" else raw
            new, _, reward, _, _, info = race.step(None, state, act, params)
            racing = state.status.active[:, None] & state.status.active[None, :]
            before = track_gap(state.x, params)
            after = track_gap(new.x, params)
            lateral = lambda x: jnp.abs(x[None, :, N_LAT] - x[:, None, N_LAT]) < 0.9 * width  # noqa: E731
            framed = in_frame(state.x) & in_frame(new.x)
            through = racing & (jnp.sign(before) * jnp.sign(after) < 0) & lateral(state.x) & lateral(new.x) & (
                jnp.abs(before) < 10.0) & framed[:, None] & framed[None, :]
            v = info.incidents
            judged = (~v.incident | (v.rule >= 0) & (v.rule < len(VERDICTS))).all() & (
                (v.fault & v.fault.T) == 0).all() & (~v.fault | v.incident).all()
            finite = jnp.isfinite(new.x).all() & jnp.isfinite(reward).all()
            return (new, key), (through.sum(), judged, finite, v.incident.sum() // 2)

        _, out = jax.lax.scan(step, (state, key), jnp.arange(steps))
        return out

    def in_frame(x):  # (N,): the track's frame is metric at the car (see the docstring)
        return 1.0 - x[:, N_LAT] * params.game.track.kappa_at(x[:, S]) >= 0.5

    def track_gap(x, params):
        return params.game.track.wrap_ds(x[None, :, S] - x[:, None, S])

    through, judged, finite, incidents = jax.jit(jax.vmap(one_race))(jax.random.split(jax.random.key(0), races))
    assert bool(finite.all())
    assert int(through.sum()) == 0
    assert bool(judged.all())
    assert int(incidents.sum()) > 0
