"""Car classes (racing_env.car_classes) and table-based limits (racing_env.vehicle.LimitTable):
each preset's limits are its source's, the table and the formula are one curve where they
describe one car, stacked classes keep their own limits, the QSS laps order the classes by
speed, and bad input is refused naming what is allowed."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from racing_env import limits
from racing_env.car_classes import CAR_CLASSES, car_names, get_car
from racing_env.physics import enforce_limits
from racing_env.track import circuit_names, get_track
from racing_env.vehicle import LimitTable, VehicleParams, stack_vehicles

TABLE_CLASSES = [name for name, c in CAR_CLASSES.items() if c.source_speeds]
#: float64 rounding of ``v + slope (w - w_k)`` at the table's magnitudes (|values| < 100 m/s^2)
ROUNDING = 1e-12


@pytest.fixture(scope="module")
def cars() -> dict[str, VehicleParams]:
    return {name: get_car(name) for name in car_names()}


def test_the_paper_class_is_the_default_car(cars):
    assert cars["paper"] == VehicleParams()
    assert cars["paper"].table is None


@pytest.mark.parametrize("name", TABLE_CLASSES)
def test_a_table_class_has_its_sources_limits_at_the_sources_speeds(name, cars):
    """At every source speed below the top speed the drive limit (``drive_max``: the net
    ``ax_max`` plus the still-air drag, for a class with drag) and the gg radius are the
    source's; at the top speed (v_max) the net limit is zero, and beyond it negative."""
    source, car = CAR_CLASSES[name], cars[name]
    speeds = np.asarray(source.source_speeds)
    below = speeds < float(car.v_max)
    assert below.sum() >= 2
    np.testing.assert_allclose(np.asarray(car.drive_max(speeds[below])), np.asarray(source.source_ax_max)[below],
                               rtol=0, atol=ROUNDING)
    np.testing.assert_allclose(np.asarray(car.rho(speeds[below])), np.asarray(source.source_rho)[below],
                               rtol=0, atol=ROUNDING)
    assert abs(float(car.ax_max(float(car.v_max)))) <= ROUNDING
    assert float(car.ax_max(float(car.v_max) + 1.0)) < 0.0
    np.testing.assert_allclose(float(car.ax_max(0.0)), car.ax_max_0, rtol=0, atol=ROUNDING)
    np.testing.assert_allclose(float(car.rho(0.0)), car.rho_0, rtol=0, atol=ROUNDING)


def test_the_tum_class_is_tumftms_published_tables(cars):
    """The figures of TUMFTM/global_racetrajectory_optimization's ggv.csv, ax_max_machines.csv
    and racecar.ini, as the class states them: the machines' drive less the drag 0.75 kg/m
    over 1200 kg, whose top speed is where they are equal, between the table's 60 and 66 m/s
    (both linear in V^2 there: 2.7 - 0.5 (w - 3600) / 756 = 0.75 w / 1200 at w = V^2)."""
    tum = cars["tum"]
    assert float(tum.length) == 4.7 and float(tum.width) == 2.0 and float(tum.c_drag) == 0.75 / 1200.0
    assert float(tum.mass) == 1200.0 and float(tum.min_turn_radius) == pytest.approx(1.0 / 0.12)
    slope = 0.5 / (66.0**2 - 60.0**2)
    top = np.sqrt((2.7 + slope * 60.0**2) / (slope + 0.75 / 1200.0))
    assert float(tum.v_max) == pytest.approx(top, rel=1e-12) and 60.0 < top < 66.0
    assert float(tum.drive_max(0.0)) == 5.3 and float(tum.drive_max(66.0)) == pytest.approx(2.2, abs=ROUNDING)
    assert np.allclose(np.asarray(tum.rho(np.linspace(0.0, 70.0, 71))), 12.0, rtol=0, atol=ROUNDING)


def test_the_f1tenth_class_is_f1tenth_gyms_car(cars):
    """f1tenth_gym's defaults: a_max 9.51 up to v_switch 7.319 m/s, a_max v_switch / V above
    it, mu g of grip, v_max 20 m/s, 0.58 m x 0.31 m, wheelbase 0.3302 m and 0.4189 rad of lock."""
    car = cars["f1tenth"]
    assert float(car.ax_max(5.0)) == pytest.approx(9.51, abs=ROUNDING)
    assert float(car.ax_max(10.0)) == pytest.approx(9.51 * 7.319 / 10.0, abs=ROUNDING)
    assert float(car.rho(12.0)) == pytest.approx(1.0489 * 9.81, abs=ROUNDING)
    assert (float(car.v_max), float(car.length), float(car.width)) == (20.0, 0.58, 0.31)
    assert float(car.min_turn_radius) == pytest.approx(0.3302 / np.tan(0.4189), rel=1e-12)


def test_the_formula_and_its_table_are_one_curve():
    """The paper's formula is linear in V^2, so its two-point table gives the same limits at
    every speed (beyond v_max too) up to rounding, and the same QSS lap."""
    for car in (VehicleParams(), VehicleParams(v_max=20.0, rho_aero=0.0), VehicleParams(ax_max_0=6.0, rho_0=9.0)):
        table = car.as_table()
        v = np.linspace(0.0, 1.5 * float(car.v_max), 301)
        np.testing.assert_allclose(np.asarray(table.ax_max(v)), np.asarray(car.ax_max(v)), rtol=0, atol=ROUNDING)
        np.testing.assert_allclose(np.asarray(table.rho(v)), np.asarray(car.rho(v)), rtol=0, atol=ROUNDING)
    line = limits.get_line(get_track("Monza"), "raceline")
    assert limits.speed_profile(line, VehicleParams().as_table()).lap_time == pytest.approx(
        limits.speed_profile(line, VehicleParams()).lap_time, rel=1e-12)


def test_stacked_classes_keep_their_own_limits(cars):
    """Cars of different classes in one race: the stacked (N, K) table on the union of their
    speeds gives each car the limits it has alone, at any speed, and car(i) returns it."""
    field = [cars["paper"], cars["tum"], cars["av21"], cars["f1tenth"], VehicleParams(v_max=20.0)]
    stacked = stack_vehicles(field)
    assert np.shape(stacked.table.speeds)[0] == len(field) and np.shape(stacked.v_max) == (len(field),)
    v = np.linspace(0.0, 95.0, 191)
    speeds = np.repeat(v[:, None], len(field), axis=1)  # (S, N): every car at every speed
    ax, rho = np.asarray(stacked.ax_max(speeds)), np.asarray(stacked.rho(speeds))
    for i, car in enumerate(field):
        np.testing.assert_allclose(ax[:, i], np.asarray(car.ax_max(v)), rtol=0, atol=1e-9)
        np.testing.assert_allclose(rho[:, i], np.asarray(car.rho(v)), rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(stacked.car(i).rho(v)), np.asarray(car.rho(v)), rtol=0, atol=1e-9)
        assert float(stacked.car(i).v_max) == float(car.v_max)


def test_table_limits_are_jax_differentiable_and_batch(cars):
    """Under jit and vmap over stacked cars, and jax.grad between the knots equal to the
    segment's slope (linear in V^2: d ax / dV = 2 V slope)."""
    stacked = stack_vehicles([cars["tum"], cars["av21"]])
    v = jnp.array([45.0, 45.0])
    jitted = jax.jit(lambda veh, speed: veh.ax_max(speed))(stacked, v)
    mapped = jax.vmap(lambda veh, speed: veh.ax_max(speed))(stacked, v)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(mapped), rtol=0, atol=ROUNDING)
    grad = float(jax.grad(lambda s: cars["tum"].ax_max(s))(46.0))
    slope = (4.6 - 5.0) / (48.0**2 - 44.0**2)  # ax_max_machines.csv between 44 and 48 m/s
    slope -= 0.75 / 1200.0  # less the drag per V^2 (racecar.ini's 0.75 kg/m over 1200 kg)
    assert grad == pytest.approx(2.0 * 46.0 * slope, rel=1e-12)


def test_the_environment_enforces_the_class_limits(cars):
    """The env's projection caps ax at the drive limit (the table's net limit plus the
    still-air drag) and |a| at its gg radius."""
    stacked = stack_vehicles([cars["tum"], cars["av21"]])
    x = jnp.array([[0.0, 50.0, 0.0, 0.0, 20.0, 0.0], [0.0, 60.0, 0.0, 0.0, 0.0, 40.0]])
    out = np.asarray(enforce_limits(x, stacked))
    assert out[0, 4] == pytest.approx(float(cars["tum"].drive_max(50.0)), abs=ROUNDING)
    assert abs(out[1, 5]) == pytest.approx(float(cars["av21"].rho(60.0)), abs=1e-9)


def test_the_monza_limit_orders_the_classes_by_speed(cars):
    """On Monza the faster class's QSS lap is shorter (every circuit: the slow test below)."""
    _check_order(cars, "Monza")


@pytest.mark.slow
@pytest.mark.parametrize("circuit", circuit_names())
def test_a_slower_class_laps_every_circuit_slower(circuit, cars):
    _check_order(cars, circuit)


def _check_order(cars, circuit: str) -> None:
    by_speed = sorted(cars, key=lambda name: float(cars[name].v_max))
    laps = [limits.lap_time_limit(circuit, cars[name]) for name in by_speed]
    assert all(slow > fast for slow, fast in zip(laps, laps[1:])), dict(zip(by_speed, laps))


@pytest.mark.parametrize("bad, message", [
    (dict(speeds=[0.0, 30.0, 20.0], ax_max=[5.0, 3.0, 0.0], rho=[12.0] * 3), "strictly increasing"),
    (dict(speeds=[1.0, 20.0, 30.0], ax_max=[5.0, 3.0, 0.0], rho=[12.0] * 3), "start at 0"),
    (dict(speeds=[0.0, 20.0, 30.0], ax_max=[5.0, 3.0, 0.0], rho=[12.0, 0.0, 12.0]), "rho"),
    (dict(speeds=[0.0, 20.0, 30.0], ax_max=[5.0, -1.0, 0.0], rho=[12.0] * 3), "drive limit"),
    (dict(speeds=[0.0, 20.0, 30.0], ax_max=[5.0, 3.0, 1.0], rho=[12.0] * 3), "exactly 0"),
    (dict(speeds=[0.0], ax_max=[5.0], rho=[12.0]), "K >= 2"),
])
def test_a_bad_table_is_refused(bad, message):
    with pytest.raises(ValueError, match=message):
        LimitTable(*(np.asarray(bad[k], dtype=float) for k in ("speeds", "ax_max", "rho")))


def test_bad_classes_and_clashing_fields_are_refused(cars):
    with pytest.raises(ValueError, match="the classes are .*'paper'.*'tum'.*'av21'.*'f1tenth'"):
        get_car("ferrari")
    with pytest.raises(ValueError, match="come from the table"):
        VehicleParams.from_table(cars["tum"].table, v_max=80.0)
    with pytest.raises(ValueError, match="disagrees with its limit table"):
        cars["tum"].replace(rho_0=14.0)


def test_a_race_spec_takes_a_class_and_refuses_an_unknown_one():
    from experiments.race_spec import RaceSpec

    config = RaceSpec(track="Monza", car="av21").to_race_config(2)
    assert config.vehicles == get_car("av21")
    assert RaceSpec(track="Monza").to_race_config(2).vehicles is None  # the paper's: the scenario's cars
    with pytest.raises(ValueError, match="unknown car class 'ferrari'"):
        RaceSpec(car="ferrari")


def test_a_sweep_sets_one_agents_class():
    from experiments.sweep import SweepConfig

    sweep = SweepConfig(lineup=("lane-keeping", "lane-keeping"), track="Monza",
                        parameters=(("agent1.car", ("tum",)),))
    race = sweep.race_config(sweep.points()[0], rotation=0)
    assert race.vehicles[0] == get_car("paper") and race.vehicles[1] == get_car("tum")
    with pytest.raises(ValueError, match="must be a car class"):
        SweepConfig(lineup=("lane-keeping", "lane-keeping"), parameters=(("agent1.car", ("ferrari",)),))


def test_racing_cars_lists_every_class_with_its_monza_limit(capsys):
    from experiments.cli import main

    assert main(["cars", "--json"]) == 0
    import json

    rows = json.loads(capsys.readouterr().out)
    assert [row["name"] for row in rows] == car_names()
    monza = {row["name"]: row["limits"]["Monza"] for row in rows}
    assert monza["paper"] == pytest.approx(limits.lap_time_limit("Monza"), rel=1e-12)


def test_the_race_jerk_weight_is_scaled_for_a_class_jerk_limits(cars):
    """The racing jerk weight is tuned at the paper car's 30 m/s^3: a car with other jerk
    limits plans with r (30 / j_max)^2, the same cost for the same share of its limits."""
    from racing_env.config import RaceConfig
    from racing_env.costs import RACING_JERK_WEIGHT, racing_weights

    assert racing_weights(vehicle=cars["paper"]) == racing_weights()
    av21 = racing_weights(vehicle=cars["av21"])
    assert float(cars["av21"].jx_max) ** 2 * av21.r_jx == pytest.approx(30.0**2 * RACING_JERK_WEIGHT, rel=1e-12)
    assert av21.r_jx < RACING_JERK_WEIGHT / 5.0  # 81 m/s^3: (30 / 81)^2 = 0.14
    field = RaceConfig(num_agents=2, vehicles=[cars["paper"], cars["av21"]]).game_weights()
    assert [w.r_jy for w in field] == [RACING_JERK_WEIGHT, av21.r_jy]


def test_on_a_model_the_jerk_weight_counts_progress_in_full_size_metres(cars):
    """On a model at scale k the jerk weight is k times the full size's (the terminal reward
    ``-s_K`` is in model metres, k of the full size's each), in the env's default weights and a
    race spec's alike; a scale that is no finite positive number is refused."""
    from experiments.race_spec import RaceSpec
    from racing_env.config import RaceConfig
    from racing_env.costs import racing_weights
    from racing_env.track import circuit

    full = racing_weights(vehicle=cars["f1tenth"])
    model = racing_weights(vehicle=cars["f1tenth"], scale=0.1)
    assert (model.r_jx, model.r_jy) == (full.r_jx * 0.1, full.r_jy * 0.1)
    assert racing_weights(scale=1.0) == racing_weights()
    config = RaceConfig(track=circuit("Monza", 0.1), vehicles=cars["f1tenth"])
    assert config.game_weights() == model
    assert RaceSpec(track="Monza", track_scale=0.1, car="f1tenth").weights() == model
    for bad in (0.0, -0.1, float("inf")):
        with pytest.raises(ValueError, match="scale must be a finite number > 0"):
            racing_weights(scale=bad)


def test_a_class_car_is_equal_to_itself_and_keys_a_cache(cars):
    """Two builds of a class are equal and hash alike (the JAX learner caches its compiled race
    by the race's config, whose cars are these), and another class differs."""
    from experiments.race_spec import RaceSpec

    assert get_car("tum") == cars["tum"] and hash(get_car("tum")) == hash(cars["tum"])
    assert cars["tum"] != cars["av21"]
    config = RaceSpec(track="Monza", car="tum").to_race_config(2)
    assert {config: 1}[RaceSpec(track="Monza", car="tum").to_race_config(2)] == 1


@pytest.mark.parametrize("name", car_names())
def test_the_lap_time_limit_reads_the_curve_the_env_and_the_planners_read(name, cars):
    """The QSS profile's scalar curve (racing_env.limits) equals VehicleParams.ax_max and rho
    (the env's projection, the planners' costs) at speeds between and beyond the knots."""
    car = cars[name]
    curve = limits._Curve.of(car)
    v = np.random.default_rng(0).uniform(0.0, 1.2 * float(car.v_max), 200)
    np.testing.assert_allclose([curve.at(curve.ax, s * s) for s in v], np.asarray(car.ax_max(v)), rtol=0, atol=1e-9)
    np.testing.assert_allclose([curve.at(curve.rho, s * s) for s in v], np.asarray(car.rho(v)), rtol=0, atol=1e-9)
    kappa = np.array([1e-4, 1e-3, 0.01, 0.05])
    w = curve.lateral_limit(kappa)
    np.testing.assert_allclose(kappa * w, np.asarray(car.rho(np.sqrt(w))), rtol=1e-9)  # |kappa| V^2 = rho(V)


def test_a_circuits_model_is_the_circuit_scaled():
    """A model at scale k (racing_env.track.scaled) is the circuit with every length times k:
    a car k^(1/2) times as fast at the same accelerations laps it in k^(1/2) times the time
    (the formula car without downforce, whose limits scale so), on the shipped line scaled."""
    from racing_env.track import circuit

    k = 0.1
    full, model = circuit("Monza"), circuit("Monza", k)
    assert model.scale == k and model.length == pytest.approx(k * full.length, rel=1e-12)
    car = VehicleParams(rho_aero=0.0)
    small = car.replace(v_max=float(car.v_max) * np.sqrt(k))
    assert limits.lap_time_limit(model, small) == pytest.approx(np.sqrt(k) * limits.lap_time_limit(full, car), rel=1e-9)
    line, full_line = limits.get_line(model, "raceline"), limits.get_line(full, "raceline")
    np.testing.assert_allclose(line.n, k * full_line.n, rtol=1e-12)


@pytest.mark.parametrize("scale", [0.0, -0.1, float("nan"), float("inf"), "0.1"])
def test_a_scale_that_is_not_a_positive_number_is_refused(scale):
    from racing_env.track import circuit, get_track

    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        circuit("Monza", scale)
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        get_track("trefoil", scale=scale)
