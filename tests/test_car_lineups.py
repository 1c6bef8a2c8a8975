"""Cars of different classes in one lineup (an agent spec's ``car=NAME``), models that record
their car's class, and fields of the 1:10 class on a 1:10 model of a circuit."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

from experiments.race_spec import RaceSpec
from planners.agents import make_agent
from planners.agents.registry import split_car
from racing_env.car_classes import car_names, class_of, get_car
from racing_env.costs import racing_weights
from racing_env.scenarios import START_MARGIN, grid_size, grid_starts
from racing_env.steward import DEFEND_GAP, DRIVE_THROUGH, STRAIGHT_KAPPA, make_steward
from racing_env.track import circuit
from racing_env.vehicle import stack_vehicles


@pytest.fixture(scope="module")
def monza_model():
    """Monza as a 1:10 model."""
    return circuit("Monza", 0.1)


def test_a_spec_names_its_car_and_the_agent_is_made_without_it():
    assert split_car("ilqgame-fb:car=av21,max_iterations=50") == ("ilqgame-fb:max_iterations=50", "av21")
    assert split_car("lane-keeping:car=F1TENTH") == ("lane-keeping", "f1tenth")
    assert split_car("ilqr:c_collision=1") == ("ilqr:c_collision=1", None)
    assert split_car("rl:car=tum:runs/a/model.zip") == ("rl:runs/a/model.zip", "tum")
    assert split_car("rl:sac:car=tum:runs/a/model.zip") == ("rl:sac:runs/a/model.zip", "tum")
    assert split_car("rl:runs/car=x/model.zip") == ("rl:runs/car=x/model.zip", None)  # a path's '=' is the path's
    assert make_agent("lane-keeping:car=f1tenth,target_speed=3").spec == "lane-keeping"
    for spec in ("ilqgame-fb:car=kart", "rl:car=kart:model.zip"):
        with pytest.raises(ValueError, match=r"unknown car class 'kart'.*'paper', 'tum', 'av21', 'f1tenth'"):
            make_agent(spec)


def test_a_lineup_races_each_car_in_its_class_with_its_own_jerk_weight():
    spec = RaceSpec(track="Monza", car="tum")
    lineup = ["ilqgame-fb:car=av21", "lane-keeping", "raceline:car=paper"]
    classes = spec.car_classes(lineup)
    assert classes == ["av21", "tum", "paper"]
    race = spec.to_race_config(3, cars=classes)
    for vehicle, weights, name in zip(race.vehicles, race.weights, classes):
        assert vehicle == get_car(name)
        assert weights == racing_weights(spec.jerk_weight, get_car(name))  # scaled for its own jerk limits
    # every planner's game has every car's own limits: its own and its rivals'
    stacked = stack_vehicles(race.vehicles)
    assert [class_of(stacked.car(i)) for i in range(3)] == classes
    assert spec.to_race_config(2, cars=["paper", "paper"]).vehicles is None  # the paper's: the scenario's cars
    with pytest.raises(ValueError, match="unknown car class 'kart'"):
        spec.to_race_config(2, cars=["paper", "kart"])


def test_a_tournament_refuses_an_agent_of_an_unknown_class_and_builds_each_race_from_its_lineup():
    from experiments.tournament import TournamentConfig, race_config

    with pytest.raises(ValueError, match=r"unknown car class 'kart'.*\['paper', 'tum', 'av21', 'f1tenth'\]"):
        TournamentConfig(agents=("lane-keeping:car=kart", "raceline"))
    config = TournamentConfig(agents=("lane-keeping:car=f1tenth", "raceline"), track="straight")
    for lineup in (["lane-keeping:car=f1tenth", "raceline"], ["raceline", "lane-keeping:car=f1tenth"]):
        race = race_config(config, lineup)
        assert [class_of(vehicle) for vehicle in race.vehicles] == config.car_classes(lineup)


def test_training_puts_the_learner_in_the_race_car_and_each_opponent_in_its_own():
    from experiments.rl.config import TrainConfig

    config = TrainConfig(opponents=("lane-keeping:car=tum", "constant-speed"), car="av21", envs=3, track="Monza")
    for copy in range(3):  # the learner drives car copy % 3
        race = config.race_config(copy=copy)
        expected = ["tum", "av21"]
        expected.insert(copy, "av21")
        assert [class_of(vehicle) for vehicle in race.vehicles] == expected
    assert config.car_classes_with_learner(2) == ["tum", "av21", "av21"]
    pool = TrainConfig(opponents=("lane-keeping:car=tum", "constant-speed:car=tum"), pool=True, pool_cars=3)
    assert pool.opponent_cars() == ["tum", "tum"]
    with pytest.raises(ValueError, match="a pool draws every opponent car's driver per episode"):
        TrainConfig(opponents=("lane-keeping:car=tum", "constant-speed"), pool=True)


def test_a_model_records_its_car_and_warns_in_a_car_of_another_class(tmp_path):
    """A JAX learner's model file keeps the class it trained in; driving that class it says
    nothing, another class (by the spec's car=) or a car of no class it warns."""
    from experiments.tournament import TournamentConfig, race_config
    from planners.agents.jax_policy import actor_critic, load_model, save_model
    from racing_env.env import RacingParallelEnv

    config = TournamentConfig(agents=("lane-keeping", "raceline"), track="straight", car="f1tenth")
    env = RacingParallelEnv(race_config(config, ["lane-keeping", "raceline"]))
    size = env.observation_space("car_0").shape[0]
    params = actor_critic((8,)).init(jax.random.PRNGKey(0), np.zeros(size, np.float32))["params"]
    path = save_model(tmp_path / "m.npz", (8,), params, np.zeros(size), np.ones(size), car_class="f1tenth")
    assert load_model(path).car_class == "f1tenth"
    agent = make_agent(f"rl:{path}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        agent.reset(0, 1, env)  # its own class: no warning
    other = RacingParallelEnv(race_config(config, ["lane-keeping", "raceline:car=tum"]))
    with pytest.warns(UserWarning, match=r"trained in a car of class 'f1tenth' and drives car 1, a car of class 'tum'"):
        agent.reset(0, 1, other)
    unsaid = save_model(tmp_path / "old.npz", (8,), params, np.zeros(size), np.ones(size))
    assert load_model(unsaid).car_class is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_agent(f"rl:{unsaid}").reset(0, 1, other)  # a model that does not say: nothing to compare


def test_a_grid_of_the_1_10_class_on_a_1_10_model_is_the_full_size_grid_widened_for_its_cars(monza_model):
    """The 1:10 car (0.58 m x 0.31 m) is wider than the paper's car at 1:10 (0.2 m): the grid's
    distances are scaled by 0.31 / 2.0 = 0.155, which holds the scaled clearance 0.05 m on the
    worst jitter; the paper's car on the full-size circuit keeps the full-size grid."""
    f1 = get_car("f1tenth")
    assert grid_size(0.1, [f1]) == pytest.approx(0.31 / 2.0, rel=1e-12)
    assert grid_size(1.0, [get_car("paper"), get_car("av21")]) == 1.0
    for cars in (2, 4):
        starts = grid_starts(monza_model, cars, vehicles=f1, jitter=False, shuffle=False)
        slots = np.asarray(starts.slots)
        np.testing.assert_allclose(np.diff(slots[:, 0]), -0.5 * 8.0 * 0.155, rtol=1e-12)  # half a row apart
        np.testing.assert_allclose(np.abs(slots[:, 2]), 2.0 * 0.155, rtol=1e-12)
        np.testing.assert_allclose(slots[:, 1], 15.0 * np.sqrt(0.1), rtol=1e-12)
    # the clearance the worst jitter leaves, across (0.62 - 2 * 0.0465 - 0.31 m) and along a column
    # (1.24 - 2 * 0.155 - 0.58 m), is above the scaled margin
    assert min(0.62 - 2 * 0.3 * 0.155 - 0.31, 1.24 - 2 * 1.0 * 0.155 - 0.58) > START_MARGIN * 0.1


def test_the_steward_of_a_model_judges_by_the_scaled_distances(monza_model):
    full, model = (make_steward(track, get_car("f1tenth"), 2) for track in (circuit("Monza"), monza_model))
    assert float(full.defend_gap) == DEFEND_GAP and float(full.straight_kappa) == STRAIGHT_KAPPA
    assert float(model.defend_gap) == pytest.approx(0.1 * DEFEND_GAP, rel=1e-12)
    assert float(model.straight_kappa) == pytest.approx(STRAIGHT_KAPPA / 0.1, rel=1e-12)
    assert float(model.across_speed) == pytest.approx(float(full.across_speed) * np.sqrt(0.1), rel=1e-12)
    drive = make_steward(monza_model, get_car("f1tenth"), 2, penalties="drive-through")
    assert float(drive.drive_through) == pytest.approx(0.1 * DRIVE_THROUGH, rel=1e-12)


@pytest.mark.slow
def test_a_field_of_the_1_10_class_races_clean_on_a_1_10_model(monza_model):
    """Three 1:10 cars behind the racing-line driver from a seeded grid on 1:10 Monza, 60 m
    (about 4 s): every car stays on the track, no car touches another (the grid holds the
    scaled clearance, the drivers keep the scaled gaps), so the steward finds no incident,
    and every car finishes in its class's record."""
    from experiments.tournament import race_lineup
    from racing_env.config import RaceConfig

    race = RaceConfig(num_agents=3, track=monza_model, vehicles=get_car("f1tenth"), race_distance=60.0,
                      max_steps=400)
    record, _ = race_lineup(race, ["raceline"] * 3, seed=0, replay=False, cars=["f1tenth"] * 3)
    assert record["incidents"] == []
    for car in record["cars"]:
        assert car["car_class"] == "f1tenth"
        assert car["collision_steps"] == 0 and car["time_off_track"] == 0.0 and car["faults"] == 0
        assert car["finish_time"] is not None


def test_car_names_are_what_the_specs_take():
    for name in car_names():
        assert split_car(f"raceline:car={name}")[1] == name


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Monza", "Suzuka"])
def test_the_racing_line_driver_laps_a_1_10_model_on_the_track(name):
    """Alone, a lap of a 1:10 model from the grid: the racing-line driver's law with its times
    scaled to the model, in a race whose step is scaled alike (0.032 s), keeps the car on the
    track (at the full size's 0.1 s step it left Suzuka's for 2.9 s a lap; with the law's times
    unscaled too, Monza's first chicane for 1.4 s)."""
    from experiments.tournament import race_lineup

    race = RaceSpec(track=name, track_scale=0.1, car="f1tenth", max_steps=3000).to_race_config(1)
    record, _ = race_lineup(race, ["raceline"], seed=0, replay=False, cars=["f1tenth"])
    car = record["cars"][0]
    assert car["finish_time"] is not None and car["time_off_track"] == 0.0


def test_a_race_on_a_model_steps_in_froude_scaled_time(monza_model):
    """A race's step is 0.1 s at full size and 0.1 s x sqrt(k) on a model at scale k, unless
    given; a step that is no positive number is refused."""
    from racing_env.config import DEFAULT_DT, RaceConfig, model_step

    assert RaceConfig(track="Monza").dt == DEFAULT_DT == 0.1
    assert RaceConfig(track=circuit("Monza")).dt == DEFAULT_DT
    assert RaceConfig(track=monza_model).dt == pytest.approx(0.1 * np.sqrt(0.1), rel=1e-15)
    assert model_step(circuit("Spa", 0.25)) == pytest.approx(0.05, rel=1e-15)
    assert RaceConfig(track=monza_model, dt=0.05).dt == 0.05  # given: kept
    assert RaceSpec(track="Monza", track_scale=0.1).to_race_config(2).dt == pytest.approx(0.1 * np.sqrt(0.1))
    for bad in (0.0, -0.1, float("nan"), "0.1", True):
        with pytest.raises(ValueError, match="dt must be None"):
            RaceConfig(dt=bad)


def test_a_race_spec_at_a_track_scale_races_the_model_and_refuses_a_bad_scale():
    from racing_env.track import get_track

    config = RaceSpec(track="Monza", track_scale=0.1, car="f1tenth").to_race_config(2)
    assert config.track.scale == 0.1 and config.track.length == pytest.approx(0.1 * get_track("Monza").length)
    assert RaceSpec(track="Monza").to_race_config(2).track == "Monza"  # full size: the name, as before
    for bad in (0.0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="scale must be a finite number > 0"):
            RaceSpec(track="Monza", track_scale=bad)
