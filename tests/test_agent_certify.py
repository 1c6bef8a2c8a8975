"""Certified re-plans (the game agents' ``certify`` option): the spec, the per-step
verdicts, the share in race records and the tournament's ``certified`` column."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

import racing_env
from experiments import tournament as tour
from planners import agents as agents_module
from planners.agents import agent_options, make_agent, make_batched_opponent, receding_horizon
from planners.certificates import LOCAL_NASH, VERDICTS
from planners.methods import FEEDBACK, OPEN_LOOP

SHORT = dict(track="straight", race_distance=40.0, grids=1, max_steps=60, step_budget_s=30.0)
CERTIFYING = ("ilqgame-ol:certify=1", "ilqgame-fb:certify=true")
CERTIFICATE_KEYS = ("certified", "verdict", "certify_time")


def _recounted_share(history: list[dict]) -> float | None:
    """The share of certified re-plans at a local Nash equilibrium, counted from the steps."""
    verdicts = [step["verdict"] for step in history if "verdict" in step]
    return sum(v == LOCAL_NASH for v in verdicts) / len(verdicts) if verdicts else None


def _steps(agent, env, count: int, seed: int = 0) -> None:
    """``count`` steps of ``agent`` as car 0 against a constant-speed car 1."""
    rival = make_agent("constant-speed", target_speed=12.0)
    agent.reset(seed, 0, env)
    rival.reset(seed, 1, env)
    observations, _ = env.reset(seed=seed)
    for _ in range(count):
        state = env.state()
        observations, *_ = env.step({"car_0": agent(observations["car_0"], state),
                                     "car_1": rival(observations["car_1"], state)})


def test_the_spec_lists_and_parses_certify():
    for name in ("ilqgame-fb", "ilqgame-ol"):
        rows = {row[0]: row for row in agent_options(name)}
        assert rows["certify"][1:3] == ("bool", "False") and "local Nash" in rows["certify"][3]
    assert "certify" not in {row[0] for row in agent_options("ilqr")}
    assert make_agent("ilqgame-fb:certify=1").certify is True
    assert make_agent("ilqgame-ol:certify=true").certify is True
    assert make_agent("ilqgame-fb:certify=off").certify is False
    assert make_agent("ilqgame-fb").certify is False
    with pytest.raises(ValueError, match="option 'certify'"):
        make_agent("ilqgame-fb:certify=maybe")
    with pytest.raises(ValueError, match="no option 'certify'"):
        make_agent("ilqr:certify=1")


@pytest.mark.slow  # a long end: the default run stays within its budget
def test_certified_race_records_carry_the_share_of_the_verdicts(monkeypatch):
    """Both game agents certify every re-plan in a race; the record's certified_share is the
    share recounted from their per-step verdicts."""
    made, modes = [], {}
    make = agents_module.make_agent
    certificate = receding_horizon.certificate_record

    def recording_make(spec, **kwargs):
        made.append(make(spec, **kwargs))
        return made[-1]

    def recording_certificate(game, x0, result, mode):
        assert np.shape(x0) == (2, 6)
        modes.setdefault(mode, 0)
        modes[mode] += 1
        return certificate(game, x0, result, mode)

    monkeypatch.setattr(agents_module, "make_agent", recording_make)
    monkeypatch.setattr(receding_horizon, "certificate_record", recording_certificate)
    # 15 steps: every step re-plans, so each agent certifies 15 re-plans (> 10 below)
    config = tour.TournamentConfig(agents=CERTIFYING, **{**SHORT, "max_steps": 15})
    record, _ = tour.race_lineup(tour.race_config(config), list(CERTIFYING), seed=0)
    assert [agent.mode for agent in made] == [OPEN_LOOP, FEEDBACK]
    for agent, car, spec in zip(made, record["cars"], CERTIFYING):
        assert car["agent"] == spec
        certified = [step for step in agent.history if "verdict" in step]
        adopted = [step for step in agent.history if step["replanned"] and not step["fallback"]]
        assert len(certified) == len(adopted) > 10  # every adopted re-plan, and only those
        for step in certified:
            assert step["verdict"] in VERDICTS and step["certified"] == (step["verdict"] == LOCAL_NASH)
            assert step["certify_time"] > 0.0 and math.isfinite(step["certify_time"])  # seconds, a duration
        assert any(step["certified"] for step in certified)
        assert car["certified_share"] == pytest.approx(_recounted_share(agent.history), abs=1e-12)
        assert modes[agent.mode] == len(certified)


# slow (the default run's budget): the tournament test above checks the certified share by default
@pytest.mark.slow
def test_steps_without_an_adopted_re_plan_carry_no_certificate():
    env = racing_env.parallel_env(track="straight", num_agents=2, race_distance=60.0, max_steps=80)
    agent = make_agent("ilqgame-fb:certify=1,replan_every=3")
    _steps(agent, env, 7)
    assert [step["replanned"] for step in agent.history] == [True, False, False, True, False, False, True]
    for step in agent.history:
        assert all((key in step) == step["replanned"] for key in CERTIFICATE_KEYS)
    assert agent.summary()["certified_share"] == pytest.approx(_recounted_share(agent.history), abs=1e-12)

    failing = make_agent("ilqgame-ol:certify=1,require_converged=1,max_iterations=1")  # falls back
    _steps(failing, env, 3)
    assert all(step["fallback"] for step in failing.history)
    assert not any(key in step for step in failing.history for key in CERTIFICATE_KEYS)
    assert "certified_share" not in failing.summary()


def test_agents_without_the_option_report_no_certificate():
    env = racing_env.parallel_env(track="straight", num_agents=2, race_distance=60.0, max_steps=80)
    for spec in ("ilqgame-fb", "ilqgame-ol", "ilqr"):
        agent = make_agent(spec)
        _steps(agent, env, 2)
        assert agent.history[0]["replanned"] and agent.history[0]["converged"] is not None
        assert not any(key in step for step in agent.history for key in CERTIFICATE_KEYS)
        assert "certified_share" not in agent.summary()


def test_a_tournament_shows_the_certified_share_beside_converged(tmp_path, capsys):
    config = tour.TournamentConfig(agents=("ilqgame-fb:certify=1", "lane-keeping"), **SHORT)
    board = tour.run_tournament(config, tmp_path, gif=False, progress=False)
    rows = {row["agent"]: row for row in board["rows"]}
    shares = [car["certified_share"] for r in tour.load_results(tmp_path) for car in r["cars"]
              if car["agent"] == "ilqgame-fb:certify=1"]
    assert len(shares) == 2 and all(0.0 < share <= 1.0 for share in shares)
    assert rows["ilqgame-fb:certify=1"]["certified_share"] == pytest.approx(np.mean(shares), abs=1e-12)
    assert rows["lane-keeping"]["certified_share"] is None
    with open(tmp_path / "summary.csv", newline="") as handle:
        header = next(csv.reader(handle))
    assert header[header.index("converged_fraction") + 1] == "certified_share"
    saved = json.loads((tmp_path / "leaderboard.json").read_text())["rows"]
    assert {row["agent"]: row["certified_share"] for row in saved} == {n: r["certified_share"] for n, r in rows.items()}
    table = capsys.readouterr().out
    assert "converged" in table and "certified" in table


def test_a_leaderboard_of_records_without_the_share_still_builds():
    """Records written before certified_share existed (a resumed tournament) lack the field."""
    config = tour.TournamentConfig(agents=("ilqgame-fb", "lane-keeping"), grids=1)
    first, second = tour.schedule(config)

    def car(agent, place, **share):
        return {"agent": agent, "place": place, "finish_time": 60.0 + place, "error": None, "collision_steps": 0,
                "time_off_track": 0.0, "act_time_mean_s": 0.01, "solver_converged_fraction": None, **share}

    old = [{"id": first["id"], "order": ["ilqgame-fb", "lane-keeping"],
            "cars": [car("ilqgame-fb", 1), car("lane-keeping", 2)]}]
    rows = {row["agent"]: row for row in tour.leaderboard(config, old)["rows"]}
    assert rows["ilqgame-fb"]["certified_share"] is None and rows["lane-keeping"]["certified_share"] is None
    new = [{"id": second["id"], "order": ["lane-keeping", "ilqgame-fb"],
            "cars": [car("lane-keeping", 1, certified_share=None), car("ilqgame-fb", 2, certified_share=0.75)]}]
    rows = {row["agent"]: row for row in tour.leaderboard(config, old + new)["rows"]}
    assert rows["ilqgame-fb"]["certified_share"] == 0.75  # the race without a share does not count


def test_batched_opponents_refuse_certify():
    game = racing_env.parallel_env(track="straight", num_agents=2).game
    with pytest.raises(ValueError, match="option certify"):
        make_batched_opponent("ilqgame-fb:certify=1", game, 1, 4)
    with pytest.raises(ValueError, match="option certify"):
        make_batched_opponent(["lane-keeping", "ilqgame-ol:certify=1"], game, 1, 4)
