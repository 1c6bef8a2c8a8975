"""`racing sweep`: the same results on every backend (a real local Ray cluster included),
resumption, interruption, where the swept settings go, and refused files."""

from __future__ import annotations

import json

import numpy as np

import pytest

from experiments import sweep
from experiments.cli import main
from experiments.standings import wilson_interval
from experiments.sweep import SweepConfig, load_sweep, run_sweep
from interrupting import ctrl_c_when, start_racing


# Scripted cars on short races: the backends, not the driving, are under test here.
TINY_TOML = """
lineup = ["lane-keeping", "constant-speed"]
race_distance = 150.0
grids = 2

[parameters]
max_steps = [60, 400]
track = ["trefoil", "straight"]
"""


def _without_timing(record):
    """A record without the wall-clock fields (action times), which differ run to run."""
    cars = [{k: v for k, v in car.items() if not k.startswith("act_time")} for car in record["agents"]]
    return {**record, "agents": cars}


@pytest.fixture()
def tiny(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_TOML)
    return load_sweep(path)


OTHER_BACKENDS = {"two processes": dict(backend="local", workers=2), "ray": dict(backend="ray", workers=2)}


# The default run checks the in-process sweep's records and summary; the other backends are
# the slow legs. A real local Ray instance and a pool of two worker processes run the same
# races with the same records and leaderboard in the default tournament tests
# (tests/test_tournament.py::test_races_on_workers_give_the_same_records_and_leaderboard: the
# same experiments.backends.run_jobs), and a real `racing sweep --workers 2` runs its races in
# two worker processes in test_ctrl_c_stops_the_worker_processes_and_the_sweep_resumes below.
@pytest.mark.parametrize("backend", [pytest.param(None, id="in-process only"),
                                     pytest.param("two processes", marks=pytest.mark.slow),
                                     pytest.param("ray", marks=pytest.mark.slow)])
def test_every_backend_gives_the_same_records_and_summary(tiny, tmp_path, backend):
    runs = {"in-process": dict(backend="local", workers=1)}
    if backend is not None:
        runs[backend] = OTHER_BACKENDS[backend]
    results = {}
    for name, options in runs.items():
        report = run_sweep(tiny, tmp_path / name, progress=False, **options)
        assert report["interrupted"] is False
        records = sweep.read_results(tmp_path / name)
        assert sorted(r["id"] for r in records) == sorted(job["id"] for job in sweep.schedule(tiny))
        results[name] = ({r["id"]: _without_timing(r) for r in records}, report["rows"])
    reference = results["in-process"]
    assert all(result == reference for result in results.values())
    rows = reference[1]
    assert len(rows) == 4 * 2  # points x agents
    assert all(row["races"] == 2 * 2 for row in rows)  # grids x rotations
    # the lane keeper (v_max) is faster than the 20 m/s cruiser in every race long enough to finish
    finished = [row for row in rows if row["max_steps"] == 400]
    assert all(row["wins"] == (4 if row["agent"] == 0 else 0) for row in finished)
    assert all(row["mean_margin_s"] > 0 if row["agent"] == 0 else row["mean_margin_s"] < 0 for row in finished)
    for name in ("summary.csv", "summary.json", "sweep.png"):
        assert all((tmp_path / run / name).stat().st_size > 0 for run in runs)


def test_a_sweep_resumes_without_rerunning_finished_races(tiny, tmp_path):
    run_sweep(tiny, tmp_path / "full", progress=False)
    full = (tmp_path / "full" / "summary.json").read_text()
    lines = (tmp_path / "full" / sweep.RESULTS).read_text().splitlines()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / sweep.RESULTS).write_text("\n".join(lines[:3]) + "\n" + lines[3][:40])  # a line cut mid-write
    run_sweep(tiny, cut, progress=False)
    resumed = (cut / sweep.RESULTS).read_text().splitlines()
    assert resumed[:3] == lines[:3]
    assert len(sweep.read_results(cut)) == len(sweep.schedule(tiny))
    assert json.loads((cut / "summary.json").read_text()) == json.loads(full)
    with pytest.raises(ValueError, match="different sweep"):
        run_sweep(SweepConfig(**{**tiny.__dict__, "grids": 1}), cut, progress=False)


def test_interrupted_sweep_keeps_its_races(tiny, tmp_path, monkeypatch, capsys):
    real = sweep.run_job
    calls = []

    def interrupted_at_the_third_race(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(sweep, "run_job", interrupted_at_the_third_race)
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_TOML)
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--no-compile-cache"]) == 130
    assert len(sweep.read_results(tmp_path / "out")) == 2
    assert "run the same command to resume" in capsys.readouterr().err
    monkeypatch.setattr(sweep, "run_job", real)
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--no-compile-cache"]) == 0
    assert len(sweep.read_results(tmp_path / "out")) == len(sweep.schedule(load_sweep(path)))


@pytest.mark.slow  # worker processes; an interrupted in-process sweep: test_interrupted_sweep_keeps_its_races
def test_ctrl_c_stops_the_worker_processes_and_the_sweep_resumes(tmp_path):
    """SIGINT to the process group of a real `racing sweep --workers 2` (as a terminal sends
    Ctrl-C): exit status 130, the finished races kept, no process left; rerun: complete."""
    path = tmp_path / "long.toml"
    path.write_text(TINY_TOML.replace("grids = 2", "grids = 12"))
    out = tmp_path / "out"
    args = ["sweep", str(path), "--workers", "2", "--out", str(out), "--no-compile-cache"]
    process = start_racing(args)
    err = ctrl_c_when(process, lambda: len(sweep.read_results(out)) >= 4, timeout=120)
    assert process.returncode == 130, err
    kept = sweep.read_results(out)
    total = len(sweep.schedule(load_sweep(path)))
    assert 4 <= len(kept) < total
    assert main(args) == 0
    assert len(sweep.read_results(out)) == total


def test_swept_weights_and_cars_follow_their_agent_into_every_slot():
    config = SweepConfig(lineup=("ilqgame-fb", "ilqr", "lane-keeping"),
                         parameters=(("agent1.c_collision", (50.0,)), ("weights.c_gap", (2.0,)),
                                     ("jerk_weight", (0.03,)), ("agent2.v_max", (27.0,)),
                                     ("vehicles.ax_max_0", (9.0,))))
    (point,) = config.points()
    for rotation in range(3):
        race = config.race_config(point, rotation)
        for slot, (weights, car) in enumerate(zip(race.weights, race.vehicles)):
            agent = (slot + rotation) % 3
            assert weights.c_collision == (50.0 if agent == 1 else 10.0)
            assert (weights.c_gap, weights.r_jx, weights.r_jy) == (2.0, 0.03, 0.03)
            assert (car.v_max, car.ax_max_0, car.rho_0) == (27.0 if agent == 2 else 25.0, 9.0, 12.0)
    assert config.lineup_specs(point) == list(config.lineup)  # car fields are not agent options
    plain = SweepConfig(lineup=("ilqr", "lane-keeping"), parameters=(("agent0.c_gap", (1.0,)),))
    assert plain.race_config(plain.points()[0], 0).vehicles is None  # no car field: the scenario's cars
    jobs = sweep.schedule(config)
    assert [(j["rotation"], j["grid"]) for j in jobs] == [(r, g) for g in range(2) for r in range(3)]


def test_agent_options_are_swept_through_the_agent_specs(tmp_path):
    path = tmp_path / "speeds.toml"
    path.write_text('lineup = ["lane-keeping:target_n=1", "constant-speed"]\nrace_distance = 100.0\ngrids = 1\n'
                    '[parameters]\n"agent0.target_speed" = [8.0, 16.0]\n"agent1.c_gap" = [0.0]\n')
    config = load_sweep(path)
    assert config.lineup_specs(config.points()[0]) == ["lane-keeping:target_n=1,target_speed=8.0", "constant-speed"]
    records = [sweep.run_job(config, job) for job in sweep.schedule(config)]
    for record in records:  # the option follows agent 0 into both slots; the weight stays a race weight
        target = record["point"]["agent0.target_speed"]
        assert record["agents"][0]["agent"] == f"lane-keeping:target_n=1,target_speed={target}"
        assert record["agents"][1]["agent"] == "constant-speed"
    planner = SweepConfig(lineup=("ilqgame-fb", "lane-keeping"),
                          parameters=(("agent0.trailing.c_collision", (1.0,)), ("agent0.max_iterations", (50,))))
    assert planner.lineup_specs(planner.points()[0])[0] == "ilqgame-fb:trailing.c_collision=1.0,max_iterations=50"
    slow, fast = (np.mean([r["agents"][0]["mean_speed"] for r in records if r["point_index"] == p]) for p in (0, 1))
    assert slow < 8.5 < 15.0 < fast  # a point's option really drives the car


def test_incident_rules_are_swept(tmp_path):
    """A car steering for a line beyond the track's edge retires under on_off_track =
    "terminate" and finishes under "penalty"; the summary counts the retirements. Ghost
    cars: on its way across the car does not bump into the other one."""
    path = tmp_path / "rules.toml"
    path.write_text('lineup = ["lane-keeping:target_n=8", "lane-keeping"]\ntrack = "straight"\nrace_distance = 120.0\n'
                    'contact = "ghost"\ngrids = 1\n[parameters]\non_off_track = ["penalty", "terminate"]\n')
    config = load_sweep(path)
    records = [sweep.run_job(config, job) for job in sweep.schedule(config)]
    rows = {(row["on_off_track"], row["agent"]): row for row in sweep.summarize(config, records)}
    assert (rows["penalty", 0]["retired"], rows["penalty", 0]["finished"]) == (0, 2)
    assert (rows["terminate", 0]["retired"], rows["terminate", 0]["finished"]) == (2, 0)
    assert rows["penalty", 1]["retired"] == rows["terminate", 1]["retired"] == 0


def test_summary_of_hand_made_records():
    """The summary's arithmetic on two races of one point, by hand."""
    config = SweepConfig(lineup=("ilqgame-fb", "lane-keeping"), parameters=(("laps", (1,)),), grids=1)
    jobs = sweep.schedule(config)

    def car(start, place, finish, contact=0, off=0.0, converged=None, **retired):
        return {"start_place": start, "place": place, "finish_time": finish, "collision_steps": contact,
                "time_off_track": off, "error": None, "solver_converged_fraction": converged, **retired}

    records = [  # the second race first: the summary must not depend on the order records came in
        {**jobs[1], "overtakes": 0, "agents": [car(2, 2, 61.0, converged=0.5), car(1, 1, 60.0, off=0.4)]},
        {**jobs[0], "overtakes": 1, "agents": [car(1, 1, 59.0, contact=3, converged=0.9),
                                               car(2, 2, None, 3, retired=True)]},  # others: older records
    ]
    planner, keeper = sweep.summarize(config, records)
    assert planner == {"point": 0, "laps": 1, "agent": 0, "spec": "ilqgame-fb", "races": 2, "wins": 1,
                       "races_from_front": 1, "wins_from_front": 1, "finished": 2, "retired": 0, "mean_place": 1.5,
                       "mean_margin_s": -1.0,  # only the race both finished counts
                       "mean_finish_time_s": 60.0, "best_finish_time_s": 59.0,
                       "overtakes_per_race": 0.5, "contact_steps": 3, "time_off_track_s": 0.0, "errors": 0,
                       "converged_fraction": 0.7,
                       "overtakes": None, "overtaken": None,  # records without the cars' passes: older ones
                       # its car beat the keeper's in the first race, not in the second
                       "beaten": 1, "faced": 2, "beaten_share": 0.5,
                       "beaten_ci95_low": wilson_interval(1, 2)[0], "beaten_ci95_high": wilson_interval(1, 2)[1]}
    assert keeper["wins"] == 1 and keeper["mean_margin_s"] == 1.0 and keeper["time_off_track_s"] == 0.4
    assert keeper["finished"] == 1 and keeper["retired"] == 1  # it retired in the second race
    assert keeper["converged_fraction"] is None  # not a planner
    assert keeper["mean_finish_time_s"] == keeper["best_finish_time_s"] == 60.0


def test_summary_of_a_hand_made_time_trial():
    """Alone, a car is always first: only a finished lap counts as a win, and there is no margin."""
    config = SweepConfig(lineup=("ilqr",), parameters=(("laps", (1,)),), grids=2)
    jobs = sweep.schedule(config)
    assert len(jobs) == 2  # one rotation per grid

    def car(finish, off=0.0):
        return {"start_place": 1, "place": 1, "finish_time": finish, "collision_steps": 0, "time_off_track": off,
                "error": None, "solver_converged_fraction": None}

    records = [{**jobs[0], "overtakes": 0, "agents": [car(None, off=2.5)]},
               {**jobs[1], "overtakes": 0, "agents": [car(57.5)]}]
    (row,) = sweep.summarize(config, records)
    assert row["wins"] == row["wins_from_front"] == row["finished"] == 1 and row["races_from_front"] == 2
    assert row["mean_margin_s"] is None and row["mean_place"] == 1.0
    assert row["mean_finish_time_s"] == row["best_finish_time_s"] == 57.5 and row["time_off_track_s"] == 2.5


def test_a_time_trial_sweep_races_one_car_alone(tmp_path, capsys):
    """A lineup of one agent: every point is raced alone on each grid, once (one slot); a
    faster target speed gives the lane keeper a shorter finish time, as the summary, the
    table and the plot report."""
    path = tmp_path / "alone.toml"
    path.write_text('lineup = ["lane-keeping"]\ntrack = "straight"\nrace_distance = 150.0\ngrids = 2\n'
                    '[parameters]\n"agent0.target_speed" = [15.0, 24.0]\n')
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 0
    slow, fast = json.loads((tmp_path / "out" / "summary.json").read_text())
    records = sweep.read_results(tmp_path / "out")
    assert len(records) == 4 and all(len(r["agents"]) == 1 and r["gap"] is None for r in records)
    for row, speed in ((slow, 15.0), (fast, 24.0)):
        times = [r["agents"][0]["finish_time"] for r in records if r["point"]["agent0.target_speed"] == speed]
        assert row["races"] == row["wins"] == row["finished"] == 2 and row["mean_margin_s"] is None
        assert row["mean_finish_time_s"] == pytest.approx(np.mean(times), abs=1e-12)
        assert row["best_finish_time_s"] == min(times)
    assert fast["mean_finish_time_s"] < slow["mean_finish_time_s"]
    err = capsys.readouterr().err
    assert "lane-keeping (time trial)" in err and "finish time" in err and "margin" not in err
    assert (tmp_path / "out" / "sweep.png").stat().st_size > 0


@pytest.mark.parametrize("text, message", [
    ('lineup = ["lane-keeping", "constant-speed"]\ncolour = "red"\n[parameters]\nlaps = [1]', "unknown keys"),
    ('[parameters]\nlaps = [1]', "needs a lineup"),
    ('lineup = "ilqr"\n[parameters]\nlaps = [1]', "needs a lineup, a list of agent specs"),
    ('lineup = ["lane-keeping", "constant-speed"]', "at least one parameter"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\nspeed = [1]', "unknown sweep parameter 'speed'"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent2.c_gap" = [1]', "agent2.c_gap"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"weights.c_grip" = [1]', "weights.c_grip"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent1.target_n" = [1]', "agent1.target_n"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"vehicles.colour" = [1]', "vehicles.colour"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent0.v_max" = [-1.0]', "v_max must be > 0"),
    ('lineup = ["ilqr", "constant-speed"]\n[parameters]\n"agent0.max_iterations" = [0]', "max_iterations must be"),
    ('lineup = ["rl:x.zip", "ilqr"]\n[parameters]\n"agent0.max_iterations" = [5]', "agent0.max_iterations"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\nlaps = []', "non-empty list"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\nlaps = [0]', "laps must be"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent0.c_collision" = [-1.0]', "c_collision"),
    ('lineup = []\n[parameters]\nlaps = [1]', "at least 1 agent spec"),
    ('lineup = ["lane-keeping", "constant-speed"\n', "not valid TOML"),
    # only agent<i>. is applied to agent i: agent01. would be accepted and never set
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent01.c_gap" = [1.0]', "agent1.c_gap"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent00.target_n" = [1.0]', "agent0.target_n"),
    ('lineup = ["lane-keeping", "constant-speed"]\nseed = "abc"\n[parameters]\nlaps = [1]', "seed must be an integer >= 0"),
    ('lineup = ["lane-keeping", "constant-speed"]\nseed = -3\n[parameters]\nlaps = [1]', "seed must be an integer >= 0"),
    ('lineup = ["lane-keeping", "constant-speed"]\nstep_budget_s = -1.0\n[parameters]\nlaps = [1]', "step_budget_s must"),
    ('lineup = ["lane-keeping", "constant-speed"]\nstep_budget_s = 0.0\n[parameters]\nlaps = [1]', "step_budget_s must"),
    ('lineup = ["lane-keeping", "constant-speed"]\nstep_budget_s = "1"\n[parameters]\nlaps = [1]', "step_budget_s must"),
    ('lineup = ["lane-keeping", "constant-speed"]\nenforce_budget = true\n[parameters]\nlaps = [1]',
     "enforce_budget needs a step budget"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\ntrack = ["straight", 5]', "track values"),
    ('lineup = ["lane-keeping", "constant-speed"]\ntrack = 5\n[parameters]\nlaps = [1]', "track values"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\njerk_weight = ["x"]', "jerk_weight must be a number"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\non_off_track = ["crash"]', "on_off_track must be one of"),
    ('lineup = ["lane-keeping", "constant-speed"]\non_collision = "stop"\n[parameters]\nlaps = [1]', "on_collision must be one of"),
    # a top-level setting that every point overrides is still checked (review finding)
    ('lineup = ["lane-keeping", "constant-speed"]\non_collision = "stop"\n[parameters]\n'
     'on_collision = ["penalty", "terminate"]', "on_collision must be one of"),
    ('lineup = ["lane-keeping", "constant-speed"]\nlaps = 0\n[parameters]\nlaps = [1]', "laps must be"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\nrace_distance = ["x"]', "race_distance must be a number"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"weights.c_gap" = ["x"]', "weights.c_gap must be"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent1.v_max" = [true]', "agent1.v_max must be"),
    ('lineup = ["lane-keeping", "constant-speed"]\njerk_weight = "x"\n[parameters]\nlaps = [1]', "jerk_weight must be"),
    ('lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n"agent0.c_gap" = [1.0]\nagent0.c_gap = [2.0]',
     "'agent0.c_gap' is given twice"),
])
def test_bad_sweep_files_are_refused(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_sweep(path)


def test_dotted_keys_need_no_quotes(tmp_path):
    """An unquoted dotted key is a nested table in TOML; it names the same parameter as the quoted key."""
    head = 'lineup = ["lane-keeping", "constant-speed"]\n[parameters]\n'
    quoted, dotted = tmp_path / "quoted.toml", tmp_path / "dotted.toml"
    quoted.write_text(head + '"agent0.target_speed" = [20.0, 25.0]\n"weights.c_gap" = [1.0]\nlaps = [1]')
    dotted.write_text(head + 'agent0.target_speed = [20.0, 25.0]\nweights = {c_gap = [1.0]}\nlaps = [1]')
    assert load_sweep(dotted) == load_sweep(quoted)
    assert load_sweep(dotted).lineup_specs({"agent0.target_speed": 25.0})[0] == "lane-keeping:target_speed=25.0"


def test_the_example_sweeps_ship_with_the_package_and_load_by_name_or_path(tmp_path, capsys):
    """`racing sweep NAME` finds an example sweep in the package (experiments/sweeps), every
    one of which is a valid sweep; a path still names any file, and a name that is neither
    is refused naming the examples."""
    names = sweep.example_sweeps()
    assert {"aggression", "overtaking", "time_trial"} <= set(names)
    for name in names:
        path = sweep.sweep_path(name)
        assert path.parent == sweep.EXAMPLES and sweep.sweep_path(f"{name}.toml") == path
        load_sweep(path)  # every value checked, as `racing sweep` does before its first race
    mine = tmp_path / "aggression.toml"  # a file of the user's wins over the example of its name
    mine.write_text(TINY_TOML)
    assert sweep.sweep_path(mine) == mine
    with pytest.raises(ValueError, match=r"no sweep file 'agression': .* one of \['aggression'"):
        sweep.sweep_path("agression")
    with pytest.raises(ValueError, match="no sweep file"):
        sweep.sweep_path(tmp_path / "aggression.toml.missing")
    assert main(["sweep", "agression"]) == 2
    assert "the name of an example sweep" in capsys.readouterr().err


def test_bad_command_lines_fail_before_any_race(tmp_path, capsys):
    path = tmp_path / "sweep.toml"
    path.write_text(TINY_TOML.replace('"constant-speed"', '"wizard"'))
    assert main(["sweep", str(path), "--out", str(tmp_path / "a")]) == 2
    assert "unknown agent spec 'wizard'" in capsys.readouterr().err
    path.write_text(TINY_TOML)
    assert main(["sweep", str(path), "--workers", "0", "--out", str(tmp_path / "b")]) == 2
    assert "workers must be" in capsys.readouterr().err
    assert main(["sweep", str(tmp_path / "missing.toml")]) == 2
    path.write_text(TINY_TOML.replace('"straight"', f'"{tmp_path / "nowhere.csv"}"'))
    assert main(["sweep", str(path), "--out", str(tmp_path / "c")]) == 2
    assert "nowhere.csv" in capsys.readouterr().err
    # a point whose finish line lies beyond the open straight's end (300 m), after one that is fine
    path.write_text(TINY_TOML.replace('track = ["trefoil", "straight"]', 'race_distance = [150.0, 5000.0]')
                    .replace("race_distance = 150.0\n", 'track = "straight"\n'))
    assert main(["sweep", str(path), "--out", str(tmp_path / "d")]) == 2
    assert "the finish line at s = 5000 m lies beyond the end of the open track" in capsys.readouterr().err
    assert not any((tmp_path / name / sweep.RESULTS).exists() for name in "abcd")


def test_a_lineup_with_counts_sweeps_a_field(tmp_path, capsys):
    """``"SPEC*K"`` in a sweep's lineup: each point races one field per grid, its five cars
    shuffled over the slots the same way at every point (on one grid here: the fields'
    order over the grids is the tournaments' shuffle, tested there); ``agent1.`` sets both of agent 1's
    cars; the summary pools an agent's cars, and its rivals beaten and passes are those of
    the records."""
    path = tmp_path / "field.toml"
    path.write_text('lineup = ["lane-keeping", "lane-keeping*2", "constant-speed*2"]\ntrack = "straight"\n'
                    'race_distance = 120.0\nmax_steps = 400\ngrids = 1\n'
                    '[parameters]\n"agent1.target_speed" = [12.0, 20.0]\n')
    config = load_sweep(path)
    assert config.field and config.cars == 5 and config.counts == (1, 2, 2)
    jobs = sweep.schedule(config)
    assert [job["id"] for job in jobs] == ["p0/grid0/field", "p1/grid0/field"]
    assert jobs[0]["slots"] == jobs[1]["slots"] == config.field_slots(0) and sorted(jobs[0]["slots"]) == [0, 1, 1, 2, 2]
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 0
    records = sweep.read_results(tmp_path / "out")
    rows = json.loads((tmp_path / "out" / "summary.json").read_text())
    for record in records:
        speed = record["point"]["agent1.target_speed"]
        assert [car["entry"] for car in record["agents"]] == record["slots"]
        assert [car["slot"] for car in record["agents"]] == list(range(5))
        assert [car["agent"] for car in record["agents"] if car["entry"] == 1] == [
            f"lane-keeping:target_speed={speed}"] * 2
    for row in rows:
        mine = [(car, r) for r in records if r["point_index"] == row["point"]
                for car in sweep.agent_cars(r, row["agent"])]
        assert row["races"] == len(mine) == config.counts[row["agent"]]
        assert row["mean_place"] == pytest.approx(np.mean([car["place"] for car, _ in mine]), rel=1e-15)
        rivals = [(car, other) for car, r in mine for other in r["agents"] if other["entry"] != row["agent"]]
        assert (row["beaten"], row["faced"]) == (sum(o["place"] > c["place"] for c, o in rivals), len(rivals))
        assert row["overtakes"] == sum(car["overtakes"] for car, _ in mine)
    # the two faster lane keepers beat more of their rivals than at 12 m/s
    fast, slow = ([row for row in rows if row["agent"] == 1 and row["agent1.target_speed"] == v][0] for v in (20.0, 12.0))
    assert fast["beaten_share"] > slow["beaten_share"]
    err = capsys.readouterr().err  # the table's headers wrap in its narrow columns
    assert "beaten" in err and "made/" in err
    report = (tmp_path / "out" / "report.html").read_text()
    assert "one field of 5 cars shuffled over the slots" in report and "rivals beaten" in report
    with pytest.raises(ValueError, match="at most 20"):
        SweepConfig(lineup=("lane-keeping*20", "constant-speed"), parameters=(("laps", (1,)),))
    with pytest.raises(ValueError, match=r"lineup entry 'lane-keeping\*0'"):
        SweepConfig(lineup=("lane-keeping*0", "constant-speed"), parameters=(("laps", (1,)),))


def test_a_fields_car_parameters_follow_every_car_of_their_agent():
    """``agent1.v_max`` in a field sets the car of every slot agent 1 holds, and only those."""
    config = SweepConfig(lineup=("lane-keeping", "constant-speed*2"), parameters=(("agent1.v_max", (30.0,)),),
                         track="straight", race_distance=120.0)
    (point,) = config.points()
    for slots in ([1, 0, 1], [0, 1, 1], config.field_slots(0)):
        race = config.race_config(point, slots=slots)
        assert [car.v_max == 30.0 for car in race.vehicles] == [agent == 1 for agent in slots]
