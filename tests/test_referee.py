"""The race's rules (racing_env.referee): finishing order, retirements, positions, rewards.

Expected values are worked out by hand from the rules' definitions in the docstrings of
RewardConfig and RacingParallelEnv; the env tests cover the same rules inside whole races.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import racing_env  # noqa: F401  (float64: tests/conftest.py)
from racing_env.referee import REWARD_TERMS, RaceRules, RaceStatus, judge, places, positions

DT = 0.1
FINISH = 100.0
WEIGHTS = {"progress": 0.1, "position": 0.5, "collision": -5.0, "off_track": -1.0, "finish": 10.0, "lead": 0.2,
           "time": -2.0, "fault": -10.0}


def _rules(num, retire_on_collision=False, retire_off_track=False):
    return RaceRules(
        retire_on_collision=jnp.asarray(retire_on_collision),
        retire_off_track=jnp.asarray(retire_off_track),
        weights=jnp.asarray([WEIGHTS[t] for t in REWARD_TERMS]),
        spread=jnp.asarray(float(max(num - 1, 1))),
    )


def _status(active, finished=None, out=None, place=None, finish_time=None, penalty=None):
    num = len(active)
    start = RaceStatus.start(num, jnp.float64)
    return start._replace(
        active=jnp.asarray(active),
        finished=start.finished if finished is None else jnp.asarray(finished),
        out=start.out if out is None else jnp.asarray(out),
        place=start.place if place is None else jnp.asarray(place, jnp.int32),
        finish_time=start.finish_time if finish_time is None else jnp.asarray(finish_time),
        penalty=start.penalty if penalty is None else jnp.asarray(penalty),
    )


def test_positions_rank_like_a_stable_sort():
    rng = np.random.default_rng(3)
    for _ in range(50):
        num = int(rng.integers(1, 7))
        s = rng.choice([0.0, 1.0, 2.0, 5.5], size=num)  # many ties
        finished = rng.random(num) < 0.4
        place = np.where(finished, rng.permutation(num) + 1, 0)
        key = np.where(finished, -1e12 + place, -s)
        expected = np.empty(num, int)
        expected[np.argsort(key, kind="stable")] = np.arange(1, num + 1)
        got = positions(jnp.asarray(s), jnp.asarray(finished), jnp.asarray(place, jnp.int32))
        np.testing.assert_array_equal(np.asarray(got), expected)


def test_cars_crossing_in_one_step_are_ranked_by_interpolated_time():
    # car 0 finished earlier (place 1); cars 1-3 cross in step 7 at fractions 0.5, 0.25, 0.5
    # of the step (car 3 ties with car 1 and ranks behind it by index); car 4 does not cross.
    s_prev = jnp.asarray([130.0, 98.0, 99.0, 96.0, 90.0])
    s = jnp.asarray([131.0, 102.0, 103.0, 104.0, 95.0])
    status = _status([False, True, True, True, True], finished=[True, False, False, False, False],
                     place=[1, 0, 0, 0, 0], finish_time=[0.35, np.nan, np.nan, np.nan, np.nan])
    none = jnp.zeros(5, bool)
    v = judge(s_prev, s, status, none, none, jnp.asarray(7), DT, jnp.asarray(FINISH), _rules(5))

    np.testing.assert_array_equal(np.asarray(v.crossed), [False, True, True, True, False])
    np.testing.assert_array_equal(np.asarray(v.status.place), [1, 3, 2, 4, 0])
    # crossing time (step - 1 + fraction) * dt; car 0 keeps its time
    np.testing.assert_allclose(np.asarray(v.status.finish_time)[:4], [0.35, 0.65, 0.625, 0.65], rtol=1e-15)
    assert np.isnan(np.asarray(v.status.finish_time)[4])
    np.testing.assert_array_equal(np.asarray(v.status.active), [False, False, False, False, True])
    np.testing.assert_array_equal(np.asarray(v.positions), [1, 3, 2, 4, 5])
    # finish reward 10 * (N - place) / (N - 1) for the crossing cars only
    terms = np.asarray(v.terms)
    np.testing.assert_allclose(terms[:, REWARD_TERMS.index("finish")], [0.0, 5.0, 7.5, 2.5, 0.0], rtol=1e-15)
    np.testing.assert_allclose(np.asarray(v.reward), terms.sum(axis=1), rtol=1e-15)


@pytest.mark.parametrize("retire", [False, True])
def test_incidents_retire_only_under_the_terminate_rule(retire):
    s_prev, s = jnp.asarray([10.0, 12.0, 98.0]), jnp.asarray([11.0, 13.0, 101.0])
    collided = jnp.asarray([True, True, True])  # car 2 collides while crossing the line
    outside = jnp.asarray([False, False, False])
    v = judge(s_prev, s, _status([True, True, True]), collided, outside, jnp.asarray(3), DT,
              jnp.asarray(FINISH), _rules(3, retire_on_collision=retire))

    np.testing.assert_array_equal(np.asarray(v.status.out), [retire, retire, False])
    np.testing.assert_array_equal(np.asarray(v.status.finished), [False, False, True])
    np.testing.assert_array_equal(np.asarray(v.status.active), [not retire, not retire, False])
    terms = np.asarray(v.terms)
    np.testing.assert_allclose(terms[:, REWARD_TERMS.index("collision")], [-5.0, -5.0, -5.0])
    np.testing.assert_allclose(terms[:, REWARD_TERMS.index("progress")], [0.1, 0.1, 0.3], rtol=1e-14)
    # position: 0.5 * (behind - ahead) / (N - 1); car 2 leads, then car 1, then car 0
    np.testing.assert_allclose(terms[:, REWARD_TERMS.index("position")], [-0.5, 0.0, 0.5])


def test_cars_not_racing_are_not_judged():
    # car 1 retired earlier and sits beyond the line: it neither finishes nor scores
    s_prev, s = jnp.asarray([50.0, 120.0]), jnp.asarray([51.0, 120.0])
    status = _status([True, False], out=[False, True])
    v = judge(s_prev, s, status, jnp.zeros(2, bool), jnp.zeros(2, bool), jnp.asarray(9), DT,
              jnp.asarray(FINISH), _rules(2))
    np.testing.assert_array_equal(np.asarray(v.crossed), [False, False])
    np.testing.assert_array_equal(np.asarray(v.status.finished), [False, False])
    np.testing.assert_array_equal(np.asarray(v.status.out), [False, True])
    np.testing.assert_array_equal(np.asarray(v.status.active), [True, False])
    assert np.asarray(v.terms)[1, REWARD_TERMS.index("finish")] == 0.0


def test_a_lone_car_gets_the_whole_finish_reward():
    # N = 1: (N - place) / (N - 1) has no second car to share with; the lone car wins it all
    v = judge(jnp.asarray([99.0]), jnp.asarray([101.0]), _status([True]), jnp.zeros(1, bool),
              jnp.zeros(1, bool), jnp.asarray(4), DT, jnp.asarray(FINISH), _rules(1))
    assert np.asarray(v.status.place).tolist() == [1]
    assert np.asarray(v.terms)[0, REWARD_TERMS.index("finish")] == WEIGHTS["finish"]
    # and nothing before it crosses
    v = judge(jnp.asarray([90.0]), jnp.asarray([92.0]), _status([True]), jnp.zeros(1, bool),
              jnp.zeros(1, bool), jnp.asarray(4), DT, jnp.asarray(FINISH), _rules(1))
    assert np.asarray(v.terms)[0, REWARD_TERMS.index("finish")] == 0.0


def test_time_is_charged_per_second_raced_up_to_the_crossing():
    """Weight -2 per second, step 0.1 s: car 0 races the whole step (-0.2), car 1 crosses
    the line a quarter of the way through it (-0.05), car 2 retires off the track in it and
    is charged the whole step (-0.2), car 3 finished before and is charged nothing."""
    s_prev, s = jnp.asarray([50.0, 99.0, 60.0, 120.0]), jnp.asarray([52.0, 103.0, 61.0, 120.0])
    status = _status([True, True, True, False], finished=[False, False, False, True], place=[0, 0, 0, 1],
                     finish_time=[np.nan, np.nan, np.nan, 0.25])
    outside = jnp.asarray([False, False, True, False])
    v = judge(s_prev, s, status, jnp.zeros(4, bool), outside, jnp.asarray(6), DT, jnp.asarray(FINISH),
              _rules(4, retire_off_track=True))
    np.testing.assert_array_equal(np.asarray(v.status.out), [False, False, True, False])
    np.testing.assert_allclose(np.asarray(v.status.finish_time)[1], 0.525, rtol=1e-15)
    time = np.asarray(v.terms)[:, REWARD_TERMS.index("time")]
    np.testing.assert_allclose(time, [-0.2, -0.05, -0.2, 0.0], rtol=1e-15)
    assert not np.signbit(time[3])


def test_incident_terms_without_an_incident_are_positive_zero():
    """The module docstring's promise: 0.0, not the -0.0 of a negative weight times 0."""
    collided, outside = jnp.asarray([True, False]), jnp.asarray([False, True])
    v = judge(jnp.asarray([10.0, 20.0]), jnp.asarray([11.0, 21.0]), _status([True, True]), collided,
              outside, jnp.asarray(2), DT, jnp.asarray(FINISH), _rules(2))
    terms = np.asarray(v.terms)
    collision, off_track = terms[:, REWARD_TERMS.index("collision")], terms[:, REWARD_TERMS.index("off_track")]
    assert collision.tolist() == [-5.0, 0.0] and off_track.tolist() == [0.0, -1.0]
    assert not np.signbit(collision[1]) and not np.signbit(off_track[0])


def test_lead_is_gained_on_the_furthest_rival_still_in_the_race():
    """Car 0 finished at t = 0.35 s at 20 m/s; car 3 retired earlier beyond the line. In step 7
    (t 0.6 -> 0.7 s) car 0 stands at 100 + 20 (t - 0.35) = 105 -> 107 m, car 1 drives
    90 -> 92 m and car 2 80 -> 81 m. Car 1's lead over car 0 stays -15 m, car 2's falls from
    -25 to -26 m; car 3 counts for nobody, and the cars not racing get no term."""
    s_prev, s = jnp.asarray([131.0, 90.0, 80.0, 150.0]), jnp.asarray([131.0, 92.0, 81.0, 150.0])
    status = _status([False, True, True, False], finished=[True, False, False, False],
                     out=[False, False, False, True], place=[1, 0, 0, 0],
                     finish_time=[0.35, np.nan, np.nan, np.nan])
    none = jnp.zeros(4, bool)
    v = judge(s_prev, s, status, none, none, jnp.asarray(7), DT, jnp.asarray(FINISH), _rules(4),
              speed=jnp.asarray([20.0, 20.0, 10.0, 0.0]))
    lead = np.asarray(v.terms)[:, REWARD_TERMS.index("lead")]
    np.testing.assert_allclose(lead, WEIGHTS["lead"] * np.array([0.0, 0.0, -1.0, 0.0]), atol=1e-12)
    # without speeds the finished car stands at the line: car 1 gains 2 m, car 2 1 m
    v = judge(s_prev, s, status, none, none, jnp.asarray(7), DT, jnp.asarray(FINISH), _rules(4))
    lead = np.asarray(v.terms)[:, REWARD_TERMS.index("lead")]
    np.testing.assert_allclose(lead, WEIGHTS["lead"] * np.array([0.0, 2.0, 1.0, 0.0]), atol=1e-12)


def test_the_leader_gains_its_gap_to_the_second_and_a_lone_car_nothing():
    # three racing cars at 50, 40, 30 m drive 2, 3 and 1 m: the leader's lead over car 1
    # shrinks from 10 to 9 m; car 1 gains 1 m on the leader, car 2 loses 1 m
    v = judge(jnp.asarray([50.0, 40.0, 30.0]), jnp.asarray([52.0, 43.0, 31.0]), _status([True] * 3),
              jnp.zeros(3, bool), jnp.zeros(3, bool), jnp.asarray(2), DT, jnp.asarray(FINISH), _rules(3),
              speed=jnp.asarray([20.0, 30.0, 10.0]))
    lead = np.asarray(v.terms)[:, REWARD_TERMS.index("lead")]
    np.testing.assert_allclose(lead, WEIGHTS["lead"] * np.array([-1.0, 1.0, -1.0]), atol=1e-12)
    v = judge(jnp.asarray([50.0]), jnp.asarray([52.0]), _status([True]), jnp.zeros(1, bool),
              jnp.zeros(1, bool), jnp.asarray(2), DT, jnp.asarray(FINISH), _rules(1), speed=jnp.asarray([20.0]))
    assert np.asarray(v.terms)[0, REWARD_TERMS.index("lead")] == 0.0


def test_a_car_finishing_in_the_step_takes_its_lead_at_the_line():
    """Both cars cross in step 1 (dt 0.1 s): car 0 from 149 to 151 m (20 m/s) at 0.05 s, when
    car 1 (148.4 -> 151.4 m, 30 m/s) is at 149.9 m: car 0 wins by 0.1 m, from a lead of 0.6 m.
    Car 1 crosses at 0.0533 s, when car 0, carried on at 20 m/s, is 20 / 300 m past the line.
    Taken at the step's end instead, the faster loser would lead the winner."""
    v = judge(jnp.asarray([149.0, 148.4]), jnp.asarray([151.0, 151.4]), _status([True, True]),
              jnp.zeros(2, bool), jnp.zeros(2, bool), jnp.asarray(1), DT, jnp.asarray(150.0), _rules(2),
              speed=jnp.asarray([20.0, 30.0]))
    assert np.asarray(v.status.place).tolist() == [1, 2]
    lead = np.asarray(v.terms)[:, REWARD_TERMS.index("lead")]
    np.testing.assert_allclose(lead, WEIGHTS["lead"] * np.array([0.1 - 0.6, -20.0 / 300.0 + 0.6]), atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_places_and_positions_are_exact_in_either_precision(dtype):
    """Finish times of a few minutes with penalties of seconds, arc lengths of a long race
    (cumulative over laps): places by finish time plus penalty and positions (finished cars
    first) are those of a stable sort, in float32 as in float64."""
    rng = np.random.default_rng(5)
    for _ in range(100):
        num = int(rng.integers(2, 7))
        finished = rng.random(num) < 0.6
        race_time = (rng.uniform(50.0, 150.0, num) + rng.choice([0.0, 5.0], num)).astype(dtype)
        place = np.asarray(places(jnp.asarray(finished), jnp.asarray(race_time)))
        expected = np.zeros(num, int)
        order = [i for i in np.argsort(race_time, kind="stable") if finished[i]]
        expected[order] = np.arange(1, len(order) + 1)
        np.testing.assert_array_equal(place, expected)
        s = rng.uniform(1e5, 1e5 + 3.0, num).astype(dtype)
        got = np.asarray(positions(jnp.asarray(s), jnp.asarray(finished), jnp.asarray(place, jnp.int32)))
        key = sorted(range(num), key=lambda i: (not finished[i], place[i] if finished[i] else -float(s[i]), i))
        want = np.empty(num, int)
        want[key] = np.arange(1, num + 1)
        np.testing.assert_array_equal(got, want)


def test_a_float32_race_reports_every_finishing_order():
    """With JAX's default precision (x64 off, in a fresh process): three cars coasting on a
    straight at speeds in every order finish in that order, and the finished cars' positions
    say so (keyed at -1e12 + place they all tied in float32, the first index ahead)."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import itertools
        import numpy as np
        import jax
        jax.config.update("jax_enable_x64", False)
        import racing_env
        for speeds in itertools.permutations([15.0, 20.0, 25.0]):
            env = racing_env.parallel_env(track=racing_env.track.straight(length=200.0), num_agents=3,
                                          race_distance=100.0)
            x0 = np.zeros((3, 6))
            x0[:, 0], x0[:, 1], x0[:, 2] = 10.0, speeds, (-4.0, 0.0, 4.0)
            env.reset(seed=0, options={"x0": x0})
            while env.agents:
                env.step({a: np.zeros(2) for a in env.agents})
            expected = 1 + np.argsort(np.argsort(-np.asarray(speeds)))
            assert env.positions.tolist() == expected.tolist(), (speeds, env.positions)
        print("ok")
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]
