"""One race spec (experiments.race_spec.RaceSpec) in the tournament, sweep and training
configurations, and one default jerk weight for every race a user or a command builds."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import racing_env
from experiments import sweep, tournament
from experiments.jsonl import settings_json
from experiments.race_spec import RACE_FIELDS, RaceSpec
from racing_env.config import RaceConfig
from racing_env.costs import RACING_JERK_WEIGHT, CostWeights
from racing_env.env import RacingParallelEnv
from racing_env.steward import RULES


def _jerk_weights(race: RaceConfig) -> np.ndarray:
    """Every car's (r_jx, r_jy) in the game the env builds for ``race``."""
    game = RacingParallelEnv(race).game
    return np.stack([np.broadcast_to(np.asarray(game.weights.r_jx), (race.num_agents,)),
                     np.broadcast_to(np.asarray(game.weights.r_jy), (race.num_agents,))], axis=1)


def test_every_race_gets_the_racing_jerk_weight_by_default():
    """parallel_env's game, a tournament's race, a sweep's race and a training race plan with
    the same jerk weight when none is given: RACING_JERK_WEIGHT, not CostWeights' own 1."""
    pytest.importorskip("stable_baselines3")
    from experiments.rl.train import TrainConfig

    races = {
        "parallel_env": racing_env.parallel_env(track="straight").config,
        "tournament": tournament.race_config(tournament.TournamentConfig(agents=("lane-keeping", "constant-speed"))),
        "sweep": sweep.SweepConfig(lineup=("lane-keeping", "constant-speed"),
                                   parameters=(("laps", (1,)),)).race_config({}, rotation=0),
        "training": TrainConfig().race_config(),
        "evaluation": TrainConfig().race_config(training=False),
    }
    for name, race in races.items():
        np.testing.assert_array_equal(_jerk_weights(race), RACING_JERK_WEIGHT, err_msg=name)
    assert CostWeights().r_jx == 1.0  # single solves (the paper's scene) keep the solver's default
    assert RaceConfig().game_weights() == CostWeights(r_jx=RACING_JERK_WEIGHT, r_jy=RACING_JERK_WEIGHT)
    own = CostWeights(r_jx=0.5, r_jy=0.5)
    assert RaceConfig(weights=own).game_weights() is own
    np.testing.assert_array_equal(_jerk_weights(racing_env.parallel_env(track="straight", weights=own).config), 0.5)


def test_the_three_configurations_hold_the_race_spec_once():
    """The race's fields are RaceSpec's in all three configurations, as flat keyword
    arguments, and a configuration's race is its spec's RaceConfig."""
    pytest.importorskip("stable_baselines3")
    from experiments.rl.train import TrainConfig

    for config in (tournament.TournamentConfig, sweep.SweepConfig, TrainConfig):
        assert issubclass(config, RaceSpec)
        names = [field.name for field in dataclasses.fields(config)]
        assert names[:len(RACE_FIELDS)] == list(RACE_FIELDS)
    assert sweep.RACE_PARAMETERS == RACE_FIELDS
    config = tournament.TournamentConfig(agents=("lane-keeping", "constant-speed"), track="straight", laps=2,
                                         jerk_weight=0.05, on_collision="both")
    assert config.race_spec() == RaceSpec(track="straight", laps=2, jerk_weight=0.05, on_collision="both")
    race = tournament.race_config(config)
    assert (race.track, race.laps, race.on_collision, race.num_agents) == ("straight", 2, "both", 2)
    assert race.weights == CostWeights(r_jx=0.05, r_jy=0.05)
    assert TrainConfig().on_off_track == "terminate"  # training keeps its own default rule


@pytest.mark.parametrize("fields, message", [
    (dict(laps=0), "laps must be an integer >= 1"),
    (dict(max_steps=0), "max_steps must be an integer >= 1"),
    (dict(race_distance=-5.0), "race_distance must be a finite number > 0"),
    (dict(race_distance="far"), "race_distance must be a finite number > 0"),
    (dict(jerk_weight=0.0), "jerk_weight must be a number > 0"),
    (dict(jerk_weight="x"), "jerk_weight must be a number > 0"),
    (dict(on_off_track="crash"), "on_off_track must be one of"),
    (dict(track=5), "track must be a string"),
    (dict(rules=("rear-end", "weave")), "unknown rule"),
])
def test_bad_race_fields_are_refused_in_every_configuration(fields, message):
    pytest.importorskip("stable_baselines3")
    from experiments.rl.train import TrainConfig

    with pytest.raises(ValueError, match=message):
        RaceSpec(**fields)
    with pytest.raises(ValueError, match=message):
        tournament.TournamentConfig(agents=("lane-keeping", "constant-speed"), **fields)
    with pytest.raises(ValueError, match=message):
        TrainConfig(**fields)


def test_settings_files_keep_their_flat_keys():
    """tournament.json and sweep.json hold the same flat keys as before the race spec, so
    runs written then resume (a tournament's default step budget is none now, where it was
    an enforced 1 s: a run written under that default starts afresh); enforce_budget is
    left out while there is no budget. The contact and the steward's penalties are named
    (a run written before cars collided, whose races ran with ghost cars, starts afresh)."""
    config = tournament.TournamentConfig(agents=("lane-keeping", "constant-speed"))
    assert json.loads(settings_json(config, config.added_later(tournament.ADDED_LATER))) == {
        "agents": ["lane-keeping", "constant-speed"], "cars": 2, "grids": 2, "jerk_weight": RACING_JERK_WEIGHT,
        "laps": 1, "max_steps": 3000, "race_distance": None, "seed": 0, "step_budget_s": None, "track": "trefoil",
        "versus": None, "contact": "physics", "penalties": "time", "penalty_seconds": 5.0}
    config = sweep.SweepConfig(lineup=("lane-keeping",), parameters=(("laps", (1,)),))
    assert json.loads(settings_json(config, config.added_later(sweep.ADDED_LATER))) == {
        "lineup": ["lane-keeping"], "parameters": [["laps", [1]]], "grids": 2, "jerk_weight": RACING_JERK_WEIGHT,
        "laps": 1, "max_steps": 3000, "race_distance": None, "seed": 0, "step_budget_s": None, "track": "trefoil",
        "contact": "physics", "penalties": "time", "penalty_seconds": 5.0}


def test_the_steward_rules_reach_the_race_and_are_named_when_not_the_default():
    """``rules`` (a list, as a TOML or JSON file gives it) becomes the race's tuple; the
    default (all but the optional weaving) is left out of tournament.json so that runs
    written before the field existed resume, any other choice is named."""
    spec = RaceSpec(rules=["rear-end", "weaving"])
    assert spec.rules == ("rear-end", "weaving")
    assert spec.to_race_config(2).rules == ("rear-end", "weaving")
    config = tournament.TournamentConfig(agents=("lane-keeping", "constant-speed"), rules=RULES)
    assert json.loads(settings_json(config, config.added_later(tournament.ADDED_LATER)))["rules"] == list(RULES)
