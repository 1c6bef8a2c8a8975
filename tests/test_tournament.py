"""Tournaments: schedule, faulty agents, resume after an interruption, determinism."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from experiments import tournament as tour
from experiments.cli import main
from planners import agents as agents_module
from planners.agents import LaneKeepingAgent
from racing_env.env import RacingParallelEnv

# races that run long: compiled with XLA's full optimisations (tests/conftest.py)
pytestmark = pytest.mark.optimized

SHORT = dict(track="straight", race_distance=120.0, grids=1, max_steps=400)
TIMING_KEYS = ("act_time_mean_s", "act_time_max_s", "over_budget_steps")


class RaisingAgent(LaneKeepingAgent):
    name = "raiser"

    def act(self, observation, joint_state):
        if self._steps >= 3:
            raise RuntimeError("planner exploded")
        return super().act(observation, joint_state)


class SlowAgent(LaneKeepingAgent):
    name = "sleeper"

    def act(self, observation, joint_state):
        if self._steps >= 2:
            time.sleep(0.05)
        return super().act(observation, joint_state)


class InterruptingAgent(LaneKeepingAgent):
    """Stands for Ctrl-C: interrupts the tournament once, in its second race."""

    name = "interrupter"
    races = 0
    armed = True

    def reset(self, seed, index, env_info):
        super().reset(seed, index, env_info)
        InterruptingAgent.races += 1

    def act(self, observation, joint_state):
        if InterruptingAgent.armed and InterruptingAgent.races == 2:
            InterruptingAgent.armed = False
            raise KeyboardInterrupt
        return super().act(observation, joint_state)


@pytest.fixture
def extra_specs(monkeypatch):
    for spec, cls in (("raiser", RaisingAgent), ("sleeper", SlowAgent), ("interrupter", InterruptingAgent)):
        monkeypatch.setitem(agents_module.AGENTS, spec, cls)


def _strip_timing(record):
    record = json.loads(json.dumps(record))
    for car in record["cars"]:
        for key in TIMING_KEYS:
            car.pop(key)
    return record


def _without_timing(board):
    rows = [{k: v for k, v in row.items() if k != "mean_act_time_s"} for row in board["rows"]]
    return rows, board["head_to_head"]


def test_schedule_swaps_positions_for_every_pair_and_grid():
    """Each pair races once per grid in both starting orders."""
    config = tour.TournamentConfig(agents=("a", "b", "c"), grids=2)
    races = tour.schedule(config)
    assert len(races) == 3 * 2 * 2
    lineups = {tuple(r["lineup"]) for r in races}
    assert ("a", "b") in lineups and ("b", "a") in lineups
    assert len({r["id"] for r in races}) == len(races)


def test_versus_schedules_only_races_against_that_agent():
    """A gauntlet: every other agent meets the named one, in both orders, and nobody else."""
    config = tour.TournamentConfig(agents=("a", "b", "c"), grids=2, versus="c")
    races = tour.schedule(config)
    assert len(races) == 2 * 2 * 2
    assert all("c" in r["lineup"] for r in races)
    with pytest.raises(ValueError, match="versus"):
        tour.TournamentConfig(agents=("a", "b"), versus="z")


def test_bad_configurations_are_refused():
    """Too few or duplicated agents, and a non-positive budget, raise ValueError."""
    with pytest.raises(ValueError, match="at least 2"):
        tour.TournamentConfig(agents=("a",))
    with pytest.raises(ValueError, match="distinct"):
        tour.TournamentConfig(agents=("a", "a"))
    with pytest.raises(ValueError, match="step_budget_s"):
        tour.TournamentConfig(agents=("a", "b"), step_budget_s=0)
    with pytest.raises(ValueError, match="enforce_budget needs a step budget"):
        tour.TournamentConfig(agents=("a", "b"), enforce_budget=True)
    with pytest.raises(ValueError, match=r"seed \(--seed\) must be an integer >= 0, got -1"):
        tour.TournamentConfig(agents=("a", "b"), seed=-1)


@pytest.mark.parametrize("agents", [("ilqr", "ILQR"), (" ilqr", "ilqr"), ("ilqr:a=1,b=2", "iLQR:b=2, a=1")])
def test_specs_naming_the_same_agent_are_not_distinct(agents):
    """Names are matched in any case, options in any order: these would race an agent against itself."""
    with pytest.raises(ValueError, match="distinct"):
        tour.TournamentConfig(agents=agents)


def test_versus_names_an_agent_as_the_agents_do():
    config = tour.TournamentConfig(agents=("ilqr:a=1,b=2", "lane-keeping"), versus="iLQR:b=2,a=1")
    assert config.versus == "ilqr:a=1,b=2"  # the spec as the lineup writes it
    with pytest.raises(ValueError, match="versus must be one of the agents"):
        tour.TournamentConfig(agents=("ilqr:a=1,b=2", "lane-keeping"), versus="ilqr:a=1")


def test_specs_of_different_agents_are_distinct():
    tour.TournamentConfig(agents=("ilqr", "ilqr:max_iterations=5", "rl:Model.zip", "rl:model.zip"))


def test_negative_seed_fails_before_the_output_folder_is_written(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["tournament", "--agents", "lane-keeping", "constant-speed", "--seed", "-1", "--out", str(out)]) == 2
    assert "seed (--seed) must be an integer >= 0" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow  # the default run's budget
def test_fresh_replaces_the_gif_and_a_resumed_run_keeps_it(tmp_path):
    """The GIF shows the first race of the results it sits with: --fresh draws it again (or,
    with --no-gif, deletes the old one), a resumed run keeps it."""
    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed"), track="straight",
                                   race_distance=100.0, grids=1, max_steps=300)
    gif, results = tmp_path / "race.gif", tmp_path / tour.RESULTS

    def run(**kwargs):
        tour.run_tournament(config, tmp_path, progress=False, **kwargs)

    run()
    assert gif.read_bytes().startswith(b"GIF")
    gif.write_bytes(b"stale")
    results.write_text(results.read_text().splitlines()[0] + "\n")  # the second race is run again
    run()
    assert gif.read_bytes() == b"stale"  # its first race was recorded: the GIF is that race's
    run(fresh=True)
    assert gif.read_bytes().startswith(b"GIF")
    gif.write_bytes(b"stale")
    results.unlink()  # results deleted by hand: the GIF is not of the races recorded next
    run()
    assert gif.read_bytes().startswith(b"GIF")
    gif.write_bytes(b"stale")
    run(fresh=True, gif=False)
    assert not gif.exists()


def test_raising_and_slow_agents_lose_and_the_tournament_completes(tmp_path, extra_specs):
    """A raising agent and one over its enforced time budget are placed last with the error recorded."""
    config = tour.TournamentConfig(agents=("lane-keeping", "raiser", "sleeper"), step_budget_s=0.02,
                                   enforce_budget=True, **SHORT)
    board = tour.run_tournament(config, tmp_path, gif=False, progress=False)
    records = tour.load_results(tmp_path)
    assert len(records) == len(tour.schedule(config))
    for record in records:
        faulted = [c for c in record["cars"] if c["error"] is not None]
        clean = [c for c in record["cars"] if c["error"] is None]
        assert faulted, "every race here has a faulty agent, and the race stops at its first fault"
        assert all(f["place"] > c["place"] for f in faulted for c in clean)
        if "lane-keeping" in record["order"]:
            (rival,) = [c for c in record["cars"] if c["agent"] != "lane-keeping"]
            expected = "planner exploded" if rival["agent"] == "raiser" else "over the budget"
            assert expected in rival["error"]
    rows = {row["agent"]: row for row in board["rows"]}
    assert rows["lane-keeping"]["wins"] == rows["lane-keeping"]["races"]
    assert (tmp_path / "summary.csv").exists() and (tmp_path / "head_to_head.png").exists()


def test_interrupted_tournament_resumes_without_rerunning_and_matches(tmp_path, extra_specs):
    """Interrupt mid-way, resume: finished races are kept as written, the table is unchanged."""
    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed", "interrupter"), **SHORT)
    InterruptingAgent.races, InterruptingAgent.armed = 0, True
    with pytest.raises(KeyboardInterrupt):
        tour.run_tournament(config, tmp_path / "cut", gif=False, progress=False)
    before = (tmp_path / "cut" / tour.RESULTS).read_text().splitlines()
    assert 0 < len(before) < len(tour.schedule(config))
    with open(tmp_path / "cut" / tour.RESULTS, "a") as sink:
        sink.write('{"id": "lane-keeping|constant-sp')  # a record cut mid-write by a kill
    resumed = tour.run_tournament(config, tmp_path / "cut", gif=False, progress=False)
    after = (tmp_path / "cut" / tour.RESULTS).read_text().splitlines()
    assert after[: len(before)] == before  # finished races were not re-run (timings would differ)
    assert len(after) == len(tour.schedule(config))  # the cut line is gone, every record whole
    assert len(tour.load_results(tmp_path / "cut")) == len(after)
    InterruptingAgent.armed = False
    full = tour.run_tournament(config, tmp_path / "full", gif=False, progress=False)
    assert _without_timing(resumed) == _without_timing(full)


def test_same_seed_gives_identical_results(tmp_path):
    """Two runs of the same tournament give identical races (timings aside)."""
    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed"), **SHORT)
    first = tour.run_tournament(config, tmp_path / "a", gif=True, progress=False)
    second = tour.run_tournament(config, tmp_path / "b", gif=False, progress=False)
    records_a = [_strip_timing(r) for r in tour.load_results(tmp_path / "a")]
    records_b = [_strip_timing(r) for r in tour.load_results(tmp_path / "b")]
    assert records_a == records_b
    assert _without_timing(first) == _without_timing(second)
    assert (tmp_path / "a" / "race.gif").stat().st_size > 0
    # start places are the grid order of the race's start state: the car furthest along is 1st
    for record in records_a:
        env = RacingParallelEnv(tour.race_config(config))
        env.reset(seed=record["seed"])
        s0 = env.state()[:, 0]
        places = [car["start_place"] for car in record["cars"]]
        assert sorted(places) == [1, 2] and s0[places.index(1)] > s0[places.index(2)]


@pytest.mark.slow
def test_a_busy_machine_decides_no_race_and_a_given_budget_is_only_reported(tmp_path, capsys):
    """`racing tournament` here, then on two worker processes while a process of this test
    keeps a core busy and with a step budget that no action meets (1 ns: every timed action
    is over it): the same races and leaderboard, every car's actions over the budget counted
    in its record and printed, no car faulted by it. A budget decides only when enforced
    (the sleeping agent above). Slow: its busy core slows every test running beside it; the
    default run checks the same records on worker processes
    (test_races_on_workers_give_the_same_records_and_leaderboard)."""
    args = ["tournament", "--agents", "lane-keeping", "constant-speed", "--track", "straight", "--race-distance",
            "120", "--grids", "1", "--max-steps", "400", "--no-gif", "--no-report"]
    assert main([*args, "--out", str(tmp_path / "here")]) == 0
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])  # a busy core, until killed
    try:
        assert main([*args, "--workers", "2", "--step-budget", "1e-9", "--out", str(tmp_path / "busy")]) == 0
    finally:
        hog.kill()
        hog.wait()
    printed = " ".join(capsys.readouterr().out.split())  # rich wraps long lines
    assert "step budget 1e-09 s, actions over it: lane-keeping" in printed and "reported only" in printed
    here, busy = (tour.load_results(tmp_path / name) for name in ("here", "busy"))
    assert all(car["over_budget_steps"] is None for record in here for car in record["cars"])
    assert all(car["over_budget_steps"] > 0 and car["error"] is None for record in busy for car in record["cars"])
    assert {r["id"]: _strip_timing(r) for r in busy} == {r["id"]: _strip_timing(r) for r in here}
    boards = [json.loads((tmp_path / name / "leaderboard.json").read_text()) for name in ("here", "busy")]
    assert _without_timing(boards[0]) == _without_timing(boards[1])


@pytest.mark.parametrize("backend, workers", [("local", 2), ("ray", 2)], ids=["two-processes", "ray"])
def test_races_on_workers_give_the_same_records_and_leaderboard(tmp_path, backend, workers):
    """The races of a tournament run on worker processes or a real local Ray instance:
    the same records (timings aside) and the same leaderboard as in this process."""
    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed"), **{**SHORT, "grids": 2})
    here = tour.run_tournament(config, tmp_path / "here", gif=False, progress=False)
    there = tour.run_tournament(config, tmp_path / "there", gif=True, progress=False, backend=backend,
                                workers=workers)
    by_id = {r["id"]: _strip_timing(r) for r in tour.load_results(tmp_path / "here")}
    assert {r["id"]: _strip_timing(r) for r in tour.load_results(tmp_path / "there")} == by_id
    assert len(by_id) == len(tour.schedule(config))
    assert _without_timing(here) == _without_timing(there)
    assert (tmp_path / "there" / "race.gif").stat().st_size > 0


def test_leaderboard_of_hand_made_records_counts_wins_finishes_and_margins():
    """The leaderboard's arithmetic on two races, by hand: a car that never finished still
    has a place (by distance) but no finish, and races it did not finish give no margin."""
    config = tour.TournamentConfig(agents=("ilqr", "lane-keeping"), grids=1)
    first, second = tour.schedule(config)

    def car(agent, place, finish, converged=None):
        return {"agent": agent, "place": place, "finish_time": finish, "error": None, "collision_steps": 0,
                "time_off_track": 0.0, "act_time_mean_s": 0.01, "solver_converged_fraction": converged}

    records = [
        {"id": first["id"], "order": ["ilqr", "lane-keeping"],
         "cars": [car("ilqr", 1, 60.0, 0.9), car("lane-keeping", 2, 61.5)]},
        {"id": second["id"], "order": ["lane-keeping", "ilqr"],  # iLQR stopped for good
         "cars": [car("lane-keeping", 1, 62.0), car("ilqr", 2, None, 0.1)]},
    ]
    rows = {row["agent"]: row for row in tour.leaderboard(config, records)["rows"]}
    assert (rows["ilqr"]["wins"], rows["ilqr"]["finished"], rows["ilqr"]["races"]) == (1, 1, 2)
    assert (rows["lane-keeping"]["wins"], rows["lane-keeping"]["finished"]) == (1, 2)
    assert rows["ilqr"]["mean_margin_s"] == 1.5 and rows["lane-keeping"]["mean_margin_s"] == -1.5
    assert rows["ilqr"]["converged_fraction"] == pytest.approx(0.5, abs=1e-15)


def test_a_time_trial_races_each_agent_alone_and_ranks_by_finish_time(tmp_path, capsys):
    """cars=1: one race per agent and grid, the agent alone; ranked by races finished, then
    mean finish time (a lane keeper at 10 m/s laps slower than one at its default speed);
    no ratings, no head-to-head, no margin. A gauntlet makes no sense alone."""
    slow, fast = "lane-keeping:target_speed=10", "lane-keeping"
    code = main(["tournament", "--cars", "1", "--agents", slow, fast, "--track", "straight", "--race-distance",
                 "120", "--grids", "2", "--max-steps", "400", "--no-gif", "--out", str(tmp_path)])
    assert code == 0
    records = tour.load_results(tmp_path)
    assert sorted(r["id"] for r in records) == sorted(f"{a}@grid{g}" for a in (slow, fast) for g in (0, 1))
    assert all(len(r["cars"]) == 1 and r["gap"] is None for r in records)
    board = json.loads((tmp_path / "leaderboard.json").read_text())
    assert [row["agent"] for row in board["rows"]] == [fast, slow]
    for row in board["rows"]:
        times = [r["cars"][0]["finish_time"] for r in records if r["order"] == [row["agent"]]]
        assert row["finished"] == row["wins"] == 2 and row["mean_margin_s"] is None
        assert row["mean_finish_time_s"] == pytest.approx(np.mean(times), rel=1e-15)
        assert row["best_finish_time_s"] == min(times)
    assert board["rows"][0]["rating"] == board["rows"][1]["rating"]  # the prior: no one to be rated against
    assert not (tmp_path / "head_to_head.png").exists()
    assert "time trial: 4 laps alone on straight" in capsys.readouterr().out
    with pytest.raises(ValueError, match="versus has no one to race"):
        tour.TournamentConfig(agents=(slow, fast), cars=1, versus=fast)
    assert len(tour.schedule(tour.TournamentConfig(agents=(fast,), cars=1, grids=3))) == 3


WANDERER, KEEPER = "lane-keeping:target_n=8", "lane-keeping"  # 8 m left: beyond the 6 m half-width


def test_leaving_the_track_retires_the_car_under_terminate_rules_and_only_then(tmp_path):
    """A car steering for a line beyond the track's edge retires there under
    ``on_off_track="terminate"``: unfinished, placed behind the finisher. By default the
    time off track is counted and it finishes. The incident rules reach the race. Ghost
    cars: on its way across the wanderer does not bump into the keeper."""
    boards, records = {}, {}
    for rule in ("penalty", "terminate"):
        config = tour.TournamentConfig(agents=(WANDERER, KEEPER), on_off_track=rule, contact="ghost", **SHORT)
        assert tour.race_config(config).on_off_track == rule
        boards[rule] = {row["agent"]: row for row in
                        tour.run_tournament(config, tmp_path / rule, gif=False, progress=False)["rows"]}
        records[rule] = tour.load_results(tmp_path / rule)
    for rule, retires in (("penalty", False), ("terminate", True)):
        assert len(records[rule]) == 2  # one grid, both slots
        for record in records[rule]:
            wanderer, keeper = (next(c for c in record["cars"] if c["agent"] == a) for a in (WANDERER, KEEPER))
            assert wanderer["time_off_track"] > 0 and keeper["time_off_track"] == 0
            assert wanderer["retired"] == retires and (wanderer["finish_time"] is None) == retires
            assert not keeper["retired"] and keeper["finish_time"] is not None
            if retires:
                assert keeper["place"] == 1 and wanderer["place"] == 2
        assert (boards[rule][WANDERER]["retired"], boards[rule][KEEPER]["retired"]) == (2 * retires, 0)
    # the settings file names the rules only where they differ from the default
    assert "on_off_track" not in json.loads((tmp_path / "penalty" / tour.CONFIG).read_text())
    assert json.loads((tmp_path / "terminate" / tour.CONFIG).read_text())["on_off_track"] == "terminate"
    with pytest.raises(ValueError, match="different tournament configuration"):
        tour.run_tournament(tour.TournamentConfig(agents=(WANDERER, KEEPER), contact="ghost", **SHORT),
                            tmp_path / "terminate",
                            gif=False, progress=False)


def test_the_paper_scene_as_a_start(tmp_path):
    """--scenario paper: every race starts from the paper's overtaking scene, the first slot's
    car (v_max 20 m/s) ahead, so each pair races once each way round; one start of 2 cars."""
    from racing_env.scenarios import paper_overtake

    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed"), scenario="paper", **SHORT)
    env = RacingParallelEnv(tour.race_config(config))
    env.reset(seed=123)
    expected = paper_overtake(env.game.track)
    np.testing.assert_array_equal(env.state(), expected.x0)
    np.testing.assert_array_equal(np.asarray(env.game.vehicles.v_max), [20.0, 25.0])
    tour.run_tournament(config, tmp_path, gif=False, progress=False)
    for record in tour.load_results(tmp_path):
        first = record["id"].split("|")[0]
        assert next(c for c in record["cars"] if c["agent"] == first)["start_place"] == 1
    for bad, message in ((dict(grids=2), "one start of 2 cars"), (dict(cars=3), "one start of 2 cars"),
                         (dict(scenario="pit_lane"), "unknown scenario")):
        with pytest.raises(ValueError, match=message):
            tour.TournamentConfig(agents=("a", "b", "c"), **{"scenario": "paper", "grids": 1, **bad})


def test_scenes_anywhere_as_starts(tmp_path):
    """--scenario anywhere: each grid seed is one scene somewhere on the track, raced once per
    starting slot, so every agent starts each scene once in front and once behind; two grid
    seeds give two scenes."""
    from racing_env.dynamics import S

    config = tour.TournamentConfig(agents=("lane-keeping", "constant-speed"), scenario="anywhere",
                                   **{**SHORT, "race_distance": 250.0, "grids": 2})
    env = RacingParallelEnv(tour.race_config(config))
    scenes = {}
    for race in tour.schedule(config):
        env.reset(seed=race["seed"])
        scenes.setdefault(race["grid"], env.state()[:, S])
    assert not np.array_equal(scenes[0], scenes[1])
    assert all(np.all(s <= 150.0) for s in scenes.values())  # 100 m short of the finish at least
    tour.run_tournament(config, tmp_path, gif=False, progress=False)
    records = tour.load_results(tmp_path)
    assert len(records) == 4
    for grid in (0, 1):
        for agent in config.agents:
            places = sorted(c["start_place"] for r in records if r["grid"] == grid for c in r["cars"]
                            if c["agent"] == agent)
            assert places == [1, 2]
    # a finish line too close for the scenes is refused before anything is written
    short = dataclasses.replace(config, race_distance=80.0)
    with pytest.raises(ValueError, match="scenario 'anywhere' places its scenes at least 100 m"):
        tour.run_tournament(short, tmp_path / "short", gif=False, progress=False)
    assert not (tmp_path / "short").exists()


def test_a_tournament_written_before_the_incident_rules_resumes(tmp_path):
    """A run whose settings file predates the incident-rule fields resumes under the default
    rules instead of being refused as another configuration."""
    config = tour.TournamentConfig(agents=(WANDERER, KEEPER), **SHORT)
    older = {k: v for k, v in json.loads(json.dumps(dataclasses.asdict(config))).items()
             if k not in config.added_later(tour.ADDED_LATER)}
    (tmp_path / tour.CONFIG).write_text(json.dumps(older, sort_keys=True))
    (tmp_path / tour.RESULTS).write_text("")
    tour.run_tournament(config, tmp_path, gif=False, progress=False)
    assert len(tour.load_results(tmp_path)) == len(tour.schedule(config))
    both = tour.TournamentConfig(agents=(WANDERER, KEEPER), on_collision="both", **SHORT)
    assert tour.race_config(both).on_collision == "both"
    with pytest.raises(ValueError, match="on_off_track must be one of"):
        tour.TournamentConfig(agents=(WANDERER, KEEPER), on_off_track="crash")


def test_overtakes_count_sign_changes():
    """Two cars swapping the lead twice make two overtakes."""
    s = np.array([[0.0, 1.0], [2.0, 1.5], [3.0, 3.5]])
    assert tour.count_overtakes(s) == 2
    assert tour.pass_events(s) == [(1, 0, 1), (2, 1, 0)]


def test_pass_events_skip_level_steps_and_cars_out_of_the_race():
    """A step level with the other car is no change; a frozen car is not passed."""
    s = np.array([[0.0, 1.0, 5.0], [1.0, 1.0, 5.0], [2.0, 1.5, 5.0], [6.0, 1.6, 5.0]])
    racing = np.ones((4, 3), dtype=bool)
    racing[2:, 2] = False  # car 2 stopped racing at step 2
    assert tour.pass_events(s, racing) == [(2, 0, 1)]
    assert tour.pass_events(s) == [(2, 0, 1), (3, 0, 2)]


# slow: a cut last line is dropped (test_jsonl), an interrupted tournament resumes without
# re-running and matches (test_interrupted_tournament_resumes_without_rerunning_and_matches), and a
# real process stopped mid-run resumes (test_sweep's Ctrl-C test) by default
@pytest.mark.slow
def test_killed_tournament_process_resumes_to_the_same_table(tmp_path):
    """SIGKILL a real `racing tournament` process mid-way, rerun: kept races, same table."""
    args = ["tournament", "--agents", "lane-keeping", "constant-speed", "--track", "trefoil",
            "--grids", "4", "--no-gif"]
    cut = tmp_path / "cut"
    results = cut / tour.RESULTS
    process = subprocess.Popen([sys.executable, "-m", "experiments.cli", *args, "--out", str(cut)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and process.poll() is None:
            if results.exists() and results.read_text().count("\n") >= 2:
                break
            time.sleep(0.02)
        assert process.poll() is None, "the tournament ended before it could be killed"
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    before = results.read_text()
    kept = [line for line in before.splitlines() if line.strip()]
    total = 2 * 4
    assert 2 <= len(kept) < total
    assert main([*args, "--out", str(cut)]) == 0
    after = results.read_text().splitlines()
    complete = [line for line in kept if line.endswith("}")]
    assert after[: len(complete)] == complete  # finished races were not re-run
    assert len(tour.load_results(cut)) == total
    assert main([*args, "--out", str(tmp_path / "full")]) == 0
    resumed = json.loads((cut / "leaderboard.json").read_text())
    full = json.loads((tmp_path / "full" / "leaderboard.json").read_text())
    assert _without_timing(resumed) == _without_timing(full)


@pytest.mark.slow  # a long end: the default run stays within its budget
def test_game_agents_beat_the_lane_keeper(tmp_path):
    """Every game planner beats the lane keeper over a lap of the trefoil, from both slots.

    One start grid, positions swapped: 2 races per planner. Measured margins (finish-time
    lead, README): iLQR +1.82/+0.85 s, open loop +1.86/+0.96 s, feedback +1.80/+1.07 s.
    """
    planners = ("ilqr", "ilqgame-ol", "ilqgame-fb")
    config = tour.TournamentConfig(agents=(*planners, "lane-keeping"), versus="lane-keeping",
                                   track="trefoil", grids=1)
    board = tour.run_tournament(config, tmp_path, gif=False, progress=False)
    rows = {row["agent"]: row for row in board["rows"]}
    assert rows["lane-keeping"]["races"] == 2 * len(planners)
    for spec in planners:
        assert rows[spec]["mean_margin_s"] > 0, rows
        assert rows[spec]["wins"] > rows[spec]["races"] / 2, rows
        assert rows[spec]["errors"] == 0
        fractions = [car["solver_converged_fraction"] for r in tour.load_results(tmp_path) for car in r["cars"]
                     if car["agent"] == spec]
        assert rows[spec]["converged_fraction"] == pytest.approx(np.mean(fractions), abs=1e-12)
    assert rows["lane-keeping"]["converged_fraction"] is None  # no solver


def test_records_give_each_finish_time_as_a_ratio_to_the_lap_time_limit(tmp_path):
    """A lap of the trefoil alone: the ratio is the finish time over the limit of the trefoil's
    centre line (no racing line is shipped for it); a race to a distance has none."""
    from racing_env import limits
    from racing_env.track import get_track

    config = tour.TournamentConfig(agents=("raceline", "lane-keeping"), cars=1, track="trefoil", laps=1, grids=1)
    board = tour.run_tournament(config, tmp_path, gif=False, progress=False)
    records = tour.load_results(tmp_path)
    limit = limits.lap_time_limit(get_track("trefoil"), line="centerline")
    for record in records:
        car, = record["cars"]
        assert car["limit_line"] == "centerline" and car["limit_time"] == pytest.approx(limit, rel=1e-12)
        assert car["limit_ratio"] == pytest.approx(car["finish_time"] / limit, rel=1e-12)
    rows = {row["agent"]: row for row in board["rows"]}
    for row in rows.values():  # both drive the centre line, at most v_max: near its limit, never below it
        assert 1.0 < row["mean_limit_ratio"] < 1.05
    record, _ = tour.race_lineup(tour.race_config(dataclasses.replace(config, laps=1, race_distance=100.0)),
                                 ["lane-keeping"], seed=0, replay=False)
    assert record["cars"][0]["limit_ratio"] is None and record["cars"][0]["limit_line"] is None


def test_a_field_gives_every_agent_a_fair_share_of_the_cars_in_a_shuffled_order():
    agents = ("a", "b", "c")
    lineups = [tour.field_lineup(agents, 10, grid, seed=0) for grid in range(3)]
    counts = [{spec: lineup.count(spec) for spec in agents} for lineup in lineups]
    assert counts == [{"a": 4, "b": 3, "c": 3}, {"a": 3, "b": 4, "c": 3}, {"a": 3, "b": 3, "c": 4}]
    assert lineups[0] != sorted(lineups[0]) and len({tuple(lineup) for lineup in lineups}) == 3
    assert tour.field_lineup(agents, 10, 1, seed=0) == lineups[1]  # deterministic
    config = tour.TournamentConfig(agents=agents, cars=10, grids=3)
    assert [race["id"] for race in config.schedule()] == ["field10@grid0", "field10@grid1", "field10@grid2"]
    assert [race["lineup"] for race in config.schedule()] == lineups
    with pytest.raises(ValueError, match=r"in \[1, 20\]"):
        tour.TournamentConfig(agents=agents, cars=21)
    with pytest.raises(ValueError, match="versus"):
        tour.TournamentConfig(agents=agents, cars=6, versus="a")


def test_passes_are_counted_per_car():
    """Car 0 passes car 2 and car 1 (then loses to car 1 again); car 1 passes car 2."""
    s = np.array([[0.0, 1.0, 2.0], [2.5, 1.0, 0.0], [3.0, 4.0, 1.0]])
    made, lost = tour.overtakes_by_car(s)
    assert made.tolist() == [2, 2, 0] and lost.tolist() == [1, 1, 2]
    assert tour.count_overtakes(s) == made.sum() == lost.sum() == 4
    # car 2 finished (frozen) at step 0: the others reaching its spot later do not pass it
    racing = np.array([[True, True, False]] * 3)
    made, lost = tour.overtakes_by_car(s, racing)
    assert made.tolist() == [1, 1, 0] and lost.tolist() == [1, 1, 0]


def test_a_fields_leaderboard_rates_agents_by_their_cars_places():
    """Two agents with two cars each, by hand: in race 1 ``a`` takes places 1 and 4 (mean 2.5)
    and ``b`` 2 and 3 (mean 2.5: a tie); in race 2 ``a`` takes 1 and 2. ``a``'s cars beat 2 + 4
    of the 4 + 4 pairs with ``b``'s cars."""
    from experiments.standings import rating_ranks, standings

    assert rating_ranks(["a", "b", "b", "a"]) == (["a", "b"], [2.5, 2.5])
    assert rating_ranks(["a", "a", "b", "b"]) == (["a", "b"], [1.5, 3.5])

    def car(agent, place):
        return {"agent": agent, "place": place, "finish_time": 60.0 + place, "error": None, "collision_steps": place,
                "time_off_track": 0.0, "act_time_mean_s": 0.01, "overtakes": 1, "overtaken": 0}

    records = [{"order": ["a", "b", "b", "a"], "cars": [car("a", 1), car("b", 2), car("b", 3), car("a", 4)]},
               {"order": ["a", "a", "b", "b"], "cars": [car("a", 1), car("a", 2), car("b", 3), car("b", 4)]}]
    rows = {row["agent"]: row for row in standings(["a", "b"], records, time_trial=False)["rows"]}
    assert rows["a"]["races"] == 4 and rows["a"]["mean_place"] == 2.0 and rows["b"]["mean_place"] == 3.0
    assert (rows["a"]["beaten"], rows["a"]["faced"]) == (6, 8) and (rows["b"]["beaten"], rows["b"]["faced"]) == (2, 8)
    assert rows["a"]["beaten_share_ci95"] == list(tour.wilson_interval(6, 8))
    assert rows["a"]["overtakes"] == 4 and rows["a"]["collision_steps"] == 1 + 4 + 1 + 2
    assert rows["a"]["rating"] > rows["b"]["rating"]  # a tie, then a win


# The default run races a field end to end in test_a_ten_car_lineup_races_end_to_end (the
# same schedule, records and leaderboard from an explicit lineup); --cars' fields are
# scheduled by field_lineup, whose default test above checks them.
@pytest.mark.slow
def test_a_tournament_of_fields_races_every_agent_in_one_race_per_grid(tmp_path):
    """Six scripted cars from three agents on two grids: every record has six cars of the
    lineup scheduled, each car's passes add up to the race's, and the leaderboard's place
    figures are those of the records."""
    agents = ["lane-keeping", "lane-keeping:target_speed=20", "lane-keeping:target_speed=12"]
    code = main(["tournament", "--agents", *agents, "--cars", "6", "--track", "straight", "--race-distance", "120",
                 "--grids", "2", "--max-steps", "400", "--no-gif", "--out", str(tmp_path)])
    assert code == 0
    records = tour.load_results(tmp_path)
    config = tour.TournamentConfig(agents=tuple(agents), cars=6, grids=2, track="straight", race_distance=120.0,
                                   max_steps=400)
    assert [r["id"] for r in records] == [race["id"] for race in config.schedule()]
    for record, race in zip(records, config.schedule()):
        assert [car["agent"] for car in record["cars"]] == race["lineup"]
        assert sorted(car["place"] for car in record["cars"]) == list(range(1, 7))
        assert sum(car["overtakes"] for car in record["cars"]) == record["overtakes"]
        assert sum(car["overtaken"] for car in record["cars"]) == record["overtakes"]
    board = json.loads((tmp_path / "leaderboard.json").read_text())
    for row in board["rows"]:
        places = [car["place"] for r in records for car in r["cars"] if car["agent"] == row["agent"]]
        assert row["races"] == len(places) == 4 and row["mean_place"] == pytest.approx(np.mean(places), rel=1e-15)
    report = (tmp_path / "report.html").read_text()
    assert "rivals beaten" in report and "a field of all agents per grid" in report


def test_a_lineup_names_the_field_with_counts_and_bad_lineups_are_refused():
    """``"SPEC*K"`` is K cars; the agents are the lineup's distinct specs (written as the
    lineup first writes them, or as ``agents`` does); every grid races the whole field,
    shuffled over the slots as ``field_lineup``'s fields are; a round robin's schedule is the
    one it always was."""
    assert tour.expand_lineup(["a*2", "b", "c:x=1,y=2*3"]) == ["a", "a", "b", "c:x=1,y=2", "c:x=1,y=2", "c:x=1,y=2"]
    config = tour.TournamentConfig(lineup=("lane-keeping*4", "LANE-KEEPING:target_speed=20*3", "constant-speed",
                                           "constant-speed*2"), grids=3, **{k: v for k, v in SHORT.items() if k != "grids"})
    assert config.agents == ("lane-keeping", "LANE-KEEPING:target_speed=20", "constant-speed") and config.cars == 10
    assert config.field and [race["id"] for race in config.schedule()] == ["field10@grid0", "field10@grid1", "field10@grid2"]
    for race in config.schedule():
        assert sorted(race["lineup"]) == sorted(config.lineup) and race["seed"] == race["grid"]
        assert race["lineup"] == tour.shuffle_field(config.lineup, race["grid"], seed=0)
    assert len({tuple(race["lineup"]) for race in config.schedule()}) == 3
    # agents may name the lineup's specs in another spelling: the lineup takes theirs
    named = tour.TournamentConfig(agents=("b", "a"), lineup=("A*2", "b"), cars=3)
    assert named.lineup == ("a", "a", "b") and named.agents == ("b", "a")
    # without a lineup and with cars <= agents: the round robin, ids and lineups as ever
    robin = tour.TournamentConfig(agents=("a", "b", "c"))
    assert robin.cars == 2 and not robin.field
    assert [race["id"] for race in robin.schedule()[:3]] == ["a|b@grid0", "b|a@grid0", "a|b@grid1"]
    bad = {"a lineup of 21 cars; a race has at most 20": dict(lineup=("a*11", "b*10")),
           r"lineup entry 'a\*0'": dict(lineup=("a*0", "b")),
           "the lineup has 4 cars, but cars": dict(lineup=("a*2", "b*2"), cars=5),
           "agents must be the lineup's distinct specs": dict(lineup=("a", "b"), agents=("a", "c")),
           "versus": dict(lineup=("a", "b"), versus="a"),
           "fixed start": dict(lineup=("a", "b"), scenario="paper", grids=1),
           "at least 2 agent specs": dict(lineup=("a*3",))}
    for message, fields in bad.items():
        with pytest.raises(ValueError, match=message):
            tour.TournamentConfig(**fields)
    # only a whole number after the last "*" counts cars: a policy's path may hold a "*"
    assert tour.split_count("rl:runs/a*b/model.zip") == ("rl:runs/a*b/model.zip", 1)
    assert tour.split_count("ilqgame-fb:rivals=3*4") == ("ilqgame-fb:rivals=3", 4)
    assert not tour.has_count("rl:runs/a*b/model.zip") and tour.has_count("lane-keeping*1")


def test_a_ten_car_lineup_races_end_to_end(tmp_path, capsys):
    """``racing tournament --lineup`` with ten scripted cars of three agents on two grids:
    the records hold the scheduled lineups, the leaderboard's place figures are the records'
    (each agent's cars pooled, rivals its cars beat counted pair by pair), and the console,
    the CSV and the report show them."""
    lineup = "lane-keeping*4,lane-keeping:target_speed=20*3,constant-speed*3"
    assert main(["tournament", "--lineup", lineup, "--track", "straight", "--race-distance", "120", "--grids", "2",
                 "--max-steps", "400", "--no-gif", "--out", str(tmp_path)]) == 0
    config = tour.TournamentConfig(lineup=tuple(lineup.split(",")), grids=2, track="straight", race_distance=120.0,
                                   max_steps=400)
    records = tour.load_results(tmp_path)
    assert [r["id"] for r in records] == ["field10@grid0", "field10@grid1"]
    board = json.loads((tmp_path / "leaderboard.json").read_text())
    for record, race in zip(records, config.schedule()):
        assert [car["agent"] for car in record["cars"]] == race["lineup"]
        assert sorted(car["place"] for car in record["cars"]) == list(range(1, 11))
        assert sum(car["overtakes"] for car in record["cars"]) == record["overtakes"]
    for row in board["rows"]:
        cars = [(car, r) for r in records for car in r["cars"] if car["agent"] == row["agent"]]
        assert row["races"] == len(cars) == 2 * config.lineup.count(row["agent"])
        assert row["mean_place"] == pytest.approx(np.mean([car["place"] for car, _ in cars]), rel=1e-15)
        beaten = sum(other["place"] > car["place"] for car, r in cars for other in r["cars"]
                     if other["agent"] != row["agent"])
        assert (row["beaten"], row["faced"]) == (beaten, sum(10 - config.lineup.count(row["agent"]) for _ in cars))
        assert row["overtakes"] == sum(car["overtakes"] for car, _ in cars)
    out = capsys.readouterr().out  # the table's headers wrap in its narrow columns
    assert "beaten" in out and "made/" in out
    header = (tmp_path / "summary.csv").read_text().splitlines()[0].split(",")
    assert {"mean_place", "beaten_share", "beaten_ci95_low", "beaten_ci95_high"} <= set(header)
    report = (tmp_path / "report.html").read_text()
    assert "the lineup&#x27;s field per grid" in report and "lane-keeping x4" in report and "pairs of cars" in report


def test_duels_and_round_robins_are_rated_as_one_player_per_car_in_finishing_order():
    """With one car per agent the place-based rating is openskill's Plackett-Luce update of
    the finishing order itself, to the bit: the ratings of duels and round robins do not move."""
    from openskill.models import PlackettLuce

    from experiments.standings import standings

    def car(agent, place):
        return {"agent": agent, "place": place, "finish_time": 60.0 + place, "error": None, "collision_steps": 0,
                "time_off_track": 0.0, "act_time_mean_s": 0.01}

    orders = [["a", "b"], ["b", "a"], ["a", "c"], ["c", "b", "a"]]
    records = [{"order": order, "cars": [car(n, p) for p, n in enumerate(order, 1)]} for order in orders]
    model = PlackettLuce()
    ratings = {n: model.rating(name=n) for n in "abc"}
    for order in orders:
        for n, [new] in zip(order, model.rate([[ratings[n]] for n in order], ranks=list(range(1, len(order) + 1)))):
            ratings[n] = new
    rows = {row["agent"]: row for row in standings(["a", "b", "c"], records, time_trial=False)["rows"]}
    assert all((rows[n]["rating_mu"], rows[n]["rating_sigma"]) == (ratings[n].mu, ratings[n].sigma) for n in "abc")
