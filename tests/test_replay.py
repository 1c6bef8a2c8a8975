"""Frames a person can read (follow camera, labels, heads-up lines, inset map), the planners'
plans and predictions in their diagnostics and in frames, and replays of recorded races:
kept beside results.jsonl by tournaments and sweeps, and drawn again by `racing replay`
exactly as they were drawn while the race ran."""

from __future__ import annotations

import numpy as np
import pytest

import racing_env
from experiments.race import run_race
from experiments.replay import load_replay, recorded_races, render_race, replay_of, save_replay
from planners.agents import make_agent
from racing_env.dynamics import N_LAT, S, V
from racing_env.render import (
    ASPHALT,
    FINISHED,
    FOLLOW_MARGIN,
    FOLLOW_MAX_SPAN,
    FOLLOW_MIN_SPAN,
    PANEL,
    RACING,
    Renderer,
    Scene,
    car_colour,
    follow_view,
)

COAST = np.zeros(2, dtype=np.float32)


def _track(name: str) -> str:
    return "Monza" if name == "monza" else name


def _pixel(frame: np.ndarray, px: np.ndarray) -> tuple[int, ...]:
    return tuple(int(c) for c in frame[int(round(px[1])), int(round(px[0]))])


def _mid_race_env(track: str, steps: int = 30, seed: int = 0):
    env = racing_env.parallel_env(track=track, num_agents=2, laps=1)
    env.reset(seed=seed)
    for _ in range(steps):
        env.step({a: COAST for a in env.agents})
    return env


# --- the camera -------------------------------------------------------------------------------
def test_follow_view_holds_the_racing_cars_and_zooms_with_their_spread():
    racing = np.array([True, True])
    centre, side = follow_view(np.array([[0.0, 0.0], [10.0, 0.0]]), racing, leader=1)
    assert side == FOLLOW_MIN_SPAN and np.allclose(centre, [5.0, 0.0])  # close together: the closest view
    centre, side = follow_view(np.array([[0.0, 0.0], [100.0, 20.0]]), racing, leader=1)
    assert side == pytest.approx(1.5 * 100.0 + FOLLOW_MARGIN) and np.allclose(centre, [50.0, 10.0])
    # too far apart for one window: the leader's, at the widest side
    centre, side = follow_view(np.array([[0.0, 0.0], [400.0, 0.0]]), racing, leader=1)
    assert side == FOLLOW_MAX_SPAN and np.allclose(centre, [400.0, 0.0])
    # a car no longer racing (finished, far ahead) is not followed
    centre, side = follow_view(np.array([[0.0, 0.0], [10.0, 0.0], [900.0, 0.0]]), np.array([True, True, False]), 1)
    assert side == FOLLOW_MIN_SPAN and np.allclose(centre, [5.0, 0.0])


@pytest.mark.parametrize("track_name", ["trefoil", "monza"])
def test_follow_camera_draws_the_cars_large_where_they_are(track_name):
    """Each car's colour is at its projected centre, and a car is many times larger than in
    the whole-track view (on Monza a car there is under a pixel long)."""
    env = _mid_race_env(_track(track_name))
    scene = env.scene(labels=["", ""])  # no tags over the cars
    follow = Renderer(env.track, env.game.vehicles, size=512, camera="follow")
    frame = follow.draw(scene)
    assert frame.shape == (512, 512, 3) and frame.dtype == np.uint8
    centre, span = follow.view(scene)
    x = scene.x
    cx, cy, _ = env.track.to_cartesian(x[:, S], x[:, N_LAT])
    for i, px in enumerate(follow._to_px(np.stack([cx, cy], axis=-1), centre, span)):
        assert _pixel(frame, px) == car_colour(i)
    whole = Renderer(env.track, env.game.vehicles, size=512, camera="track")
    assert whole.view(scene)[1] / span >= 5.0
    car_px = 4.7 * 512 / span
    assert car_px >= 4.7 * 512 / FOLLOW_MAX_SPAN  # at least 10 px long


def test_auto_camera_follows_a_duel_and_shows_a_big_field_on_a_small_circuit_whole():
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    renderer = Renderer(env.track, env.game.vehicles, camera="auto")
    assert renderer.camera_for(2) == "follow" and renderer.camera_for(6) == "track"


def test_frames_show_the_labels_and_the_inset_map():
    """Labels and the inset map change only their parts of the frame; finished cars are grey."""
    env = _mid_race_env("trefoil")
    renderer = Renderer(env.track, env.game.vehicles, size=256, camera="follow")
    named = renderer.draw(env.scene(labels=["alpha", "beta"]))
    unnamed = renderer.draw(env.scene(labels=["", ""]))
    assert np.any(named != unnamed)
    # the inset occupies the bottom-right corner, the heads-up box the top-left one
    side = round(0.3 * 256)
    corner = named[256 - side - 4: 256 - 4, 256 - side - 4: 256 - 4]
    colours = {tuple(int(c) for c in p) for p in corner.reshape(-1, 3)}
    assert {PANEL, car_colour(1)} <= colours  # the map's panel and a dot (car 1's, drawn over car 0's)
    assert {PANEL, car_colour(1)}.isdisjoint({tuple(int(c) for c in p) for p in unnamed[:20, 200:].reshape(-1, 3)})
    scene = env.scene(labels=["", ""])
    finished = Scene(x=scene.x, time=scene.time, status=np.array([FINISHED, RACING]), position=scene.position,
                     labels=scene.labels)
    greyed = renderer.draw(finished)
    centre, span = renderer.view(finished)
    cx, cy, _ = env.track.to_cartesian(scene.x[:, S], scene.x[:, N_LAT])
    px = renderer._to_px(np.stack([cx, cy], axis=-1), centre, span)
    assert _pixel(greyed, px[0]) == (200, 200, 200) and _pixel(greyed, px[1]) == car_colour(1)


def test_plans_are_drawn_in_the_planning_cars_colour_and_can_be_switched_off():
    """Car 0 predicts car 1 driving 3 m to the left of where it is: the dashes of that
    prediction, clear of both cars, are car 0's colour, and asphalt without plans."""
    env = _mid_race_env("trefoil", seed=3)  # car 1 starts behind, on the right
    assert env.state()[1, N_LAT] < -1.0
    x = env.state()
    ahead = np.arange(51)[:, None] * 0.1 * x[None, :, V]
    plan = np.stack([x[None, :, S] + ahead, np.broadcast_to(x[:, N_LAT], ahead.shape).copy()], axis=-1)
    plan[:, 1, 1] += 3.0
    scene = env.scene(labels=["", ""], plans=[plan.astype(np.float32), None])
    with_plans = Renderer(env.track, env.game.vehicles, size=512, camera="follow")
    without = Renderer(env.track, env.game.vehicles, size=512, camera="follow", plans=False)
    centre, span = with_plans.view(scene)
    k = 10  # a drawn dash of the prediction (every other segment), metres clear of both cars
    midpoint = plan[k: k + 2, 1].astype(float).mean(axis=0)
    px, py, _ = env.track.to_cartesian(midpoint[0], midpoint[1])
    at = with_plans._to_px(np.array([px, py]), centre, span)
    assert _pixel(with_plans.draw(scene), at) == car_colour(0)
    assert _pixel(without.draw(scene), at) == ASPHALT


def test_bad_renderer_settings_are_refused():
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    with pytest.raises(ValueError, match="camera must be one of"):
        Renderer(env.track, env.game.vehicles, camera="drone")
    with pytest.raises(ValueError, match="frame size"):
        Renderer(env.track, env.game.vehicles, size=8)


# --- what planners expect ---------------------------------------------------------------------
@pytest.mark.parametrize("spec", ["ilqgame-fb:replan_every=2", "ilqr:replan_every=2"])
def test_planners_expose_their_plan_and_their_predictions_of_the_others(spec):
    """``diagnostics()["plan"]`` is the joint trajectory the last action followed: it starts
    at the state the agent re-planned from, has a row per car (the others: what the agent
    expects of them), and between re-plans is the same plan from the step reached."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, laps=1)
    agent, rival = make_agent(spec), make_agent("lane-keeping")
    agent.reset(0, 0, env)
    rival.reset(0, 1, env)
    observations, _ = env.reset(seed=0)
    x0 = env.state()
    agent.act(observations["car_0"], x0)
    plan = agent.diagnostics()["plan"]
    horizon = env.game.horizon
    assert plan.shape == (horizon + 1, 2, 6)
    np.testing.assert_array_equal(plan[0], x0)  # made from this state, for both cars
    assert np.all(plan[1:, 0, S] > x0[0, S]) and np.all(plan[1:, 1, S] > x0[1, S])
    observations, *_ = env.step({"car_0": agent.diagnostics()["action"],
                                 "car_1": rival.act(observations["car_1"], x0)})
    agent.act(observations["car_0"], env.state())  # between re-plans: the same plan, a step on
    assert not agent.diagnostics()["replanned"]
    np.testing.assert_array_equal(agent.diagnostics()["plan"], plan[1:])
    assert "plan" not in agent.history[-1]  # the history keeps no plans
    assert rival.diagnostics().get("plan") is None


# --- replays ----------------------------------------------------------------------------------
@pytest.mark.parametrize("track_name", ["trefoil", "monza"])
def test_a_replay_draws_the_frames_drawn_while_the_race_ran(track_name, tmp_path):
    """On the trefoil feedback iLQGame races (with plans); on Monza, where its solver would
    compile again for the track, iLQR does."""
    env = racing_env.parallel_env(track=_track(track_name), num_agents=2, race_distance=60.0,
                                  max_steps=200)
    agents = [make_agent("ilqgame-fb" if track_name == "trefoil" else "ilqr"), make_agent("lane-keeping")]
    for i, agent in enumerate(agents):
        agent.reset(0, i, env)
    labels = [agents[0].spec, "lane-keeping"]
    record = run_race(env, agents, seed=0, render_every=2, plans=True, labels=labels)
    assert record.steps > 10 and len(record.frames) == record.steps // 2 + 1 + (record.steps % 2 > 0)
    path = save_replay(replay_of(record, env, race=3, id="example"), tmp_path / "race.npz")
    replay = load_replay(path)
    np.testing.assert_array_equal(replay.xs, record.xs)
    np.testing.assert_array_equal(replay.status, record.status)
    assert replay.labels == tuple(labels) and (replay.race, replay.id) == (3, "example")
    # the planner's plans at every step it raced (and acted); the lane keeper never plans
    acted = np.flatnonzero(replay.status[: record.steps, 0] == RACING)
    assert acted.size > 10 and not np.isnan(replay.plans[acted, 0, 0]).any()
    assert np.isnan(np.delete(replay.plans[:, 0], acted, axis=0)).all() and np.isnan(replay.plans[:, 1]).all()
    renderer = Renderer(env.track, replay.cars, size=env.config.render_size, camera=env.config.camera,
                        laps=replay.laps, finish_s=replay.finish_s)
    again = replay.frames(every=2, renderer=renderer)
    assert len(again) == len(record.frames)
    for live, drawn in zip(record.frames, again):
        np.testing.assert_array_equal(live, drawn)
    # the replay's own renderer (its track found again from the name or the file) draws them too
    np.testing.assert_array_equal(replay.frames(every=2, size=env.config.render_size)[-1], record.frames[-1])
    unplanned = replay.frames(every=2, size=env.config.render_size, plans=False)
    assert any(np.any(a != b) for a, b in zip(again, unplanned))


def test_a_replay_of_a_race_on_a_track_object_keeps_the_track(tmp_path):
    track = racing_env.track.trefoil()
    env = racing_env.parallel_env(track=track, num_agents=2, race_distance=40.0)
    drivers = [make_agent("lane-keeping"), make_agent("constant-speed")]
    for i, driver in enumerate(drivers):
        driver.reset(0, i, env)
    record = run_race(env, drivers, seed=1, render_every=5)
    replay = load_replay(save_replay(replay_of(record, env), tmp_path / "race.npz"))
    np.testing.assert_array_equal(replay.track.x, track.x)
    assert replay.plans is None
    renderer = Renderer(replay.track, replay.cars, size=env.config.render_size, laps=replay.laps,
                        finish_s=replay.finish_s)
    for live, drawn in zip(record.frames, replay.frames(every=5, renderer=renderer), strict=True):
        np.testing.assert_array_equal(live, drawn)


def test_a_replay_keeps_the_incidents_and_its_frames_show_the_verdicts(tmp_path):
    """Two coasting cars, the one behind 5 m/s faster: a rear-end. The record and its replay
    hold the incident; the frames drawn while the race ran and from the replay show its
    verdict (they differ from the same frames without it) for a few seconds after it began."""
    import dataclasses

    from experiments.race import NOTE_SECONDS

    env = racing_env.parallel_env(track=racing_env.track.straight(length=200.0), num_agents=2, race_distance=150.0)
    x0 = np.zeros((2, 6))
    x0[:, 0], x0[:, 1] = (10.0, 20.0), (20.0, 15.0)
    coast = lambda observation, state: np.zeros(2)  # noqa: E731
    record = run_race(env, [coast, coast], seed=0, render_every=1, labels=["behind", "ahead"],
                      reset_options={"x0": x0})
    [incident] = record.incidents
    assert (incident["verdict"], incident["cars"], incident["at_fault"]) == ("rear-end", [0, 1], 0)
    replay = load_replay(save_replay(replay_of(record, env), tmp_path / "race.npz"))
    assert replay.incidents == record.incidents
    k = incident["step"]
    assert "behind / ahead: rear-end, behind answers" in replay.scene(k).notes[0]
    assert not replay.scene(k - 1).notes and not replay.scene(k + round(NOTE_SECONDS / env.config.dt)).notes
    renderer = replay.renderer(size=env.config.render_size)
    np.testing.assert_array_equal(renderer.draw(replay.scene(k)), record.frames[k])
    quiet = renderer.draw(dataclasses.replace(replay.scene(k), notes=None))
    assert np.any(quiet != record.frames[k])


def _tournament(out, **changes):
    from experiments.tournament import TournamentConfig, run_tournament

    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), track="straight", race_distance=100.0,
                              grids=1, max_steps=300, **changes)
    run_tournament(config, out, progress=False, report=False)
    return config


def test_tournaments_keep_every_races_replay_and_racing_replay_draws_it(tmp_path, capsys):
    from PIL import Image

    from experiments.cli import main
    from experiments.tournament import load_results

    out = tmp_path / "tour"
    _tournament(out)
    records = load_results(out)
    assert [r["race"] for r in records] == [0, 1]
    for record in records:
        replay = load_replay(out / record["replay"])
        assert replay.steps == record["steps"] and replay.labels == tuple(
            sorted(record["order"], key=lambda spec: [c["agent"] for c in record["cars"]].index(spec)))
    assert [r["race"] for r in recorded_races(out)] == [0, 1]
    stamps = {p: p.stat().st_mtime_ns for p in (out / "replays").iterdir()}
    _tournament(out)  # resumed: nothing raced again, no replay rewritten
    assert {p: p.stat().st_mtime_ns for p in (out / "replays").iterdir()} == stamps

    assert main(["replay", str(out)]) == 0
    listing = capsys.readouterr().out
    assert "lane-keeping|constant-speed@grid0" in listing and "constant-speed|lane-keeping@grid0" in listing
    gif = tmp_path / "race1.gif"
    assert main(["replay", str(out), "--race", "1", "--out", str(gif), "--every", "4", "--size", "160"]) == 0
    steps = records[1]["steps"]
    with Image.open(gif) as image:
        assert image.size == (160, 160) and image.n_frames == len(range(0, steps + 1, 4)) + (steps % 4 > 0)
    assert main(["replay", str(out), "--race", "7"]) == 2
    assert "no replay of race 7" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "missing"), "--race", "0"]) == 2


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # the reader starts ffmpeg (fork + exec)
def test_racing_replay_writes_an_mp4(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    out = tmp_path / "tour"
    _tournament(out)
    path = render_race(out, 0, tmp_path / "race.mp4", every=5, size=128)
    steps = load_replay(out / "replays" / "race-00000.npz").steps
    with imageio.get_reader(path) as reader:
        frames = [frame for frame in reader]
    assert len(frames) == len(range(0, steps + 1, 5)) + (steps % 5 > 0)
    assert frames[0].shape == (128, 128, 3)


def test_a_fresh_run_discards_the_replays(tmp_path):
    out = tmp_path / "tour"
    _tournament(out)
    (out / "replays" / "race-00009.npz").write_bytes(b"not a replay of this run")
    from experiments.tournament import TournamentConfig, run_tournament

    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), track="straight", race_distance=100.0,
                              grids=1, max_steps=300)
    run_tournament(config, out, progress=False, report=False, fresh=True)
    assert sorted(p.name for p in (out / "replays").iterdir()) == ["race-00000.npz", "race-00001.npz"]


def test_sweeps_keep_the_planners_plans_on_request(tmp_path):
    from experiments.sweep import SweepConfig, read_results, run_sweep

    config = SweepConfig(lineup=("ilqr", "lane-keeping"), track="straight", race_distance=60.0, grids=1,
                         max_steps=200, parameters=(("jerk_weight", (0.01,)),))
    run_sweep(config, tmp_path / "sweep", progress=False, plans=True, report=False)
    records = read_results(tmp_path / "sweep")
    assert [r["race"] for r in records] == [0, 1]
    for record in records:
        replay = load_replay(tmp_path / "sweep" / record["replay"])
        ilqr_car = record["agents"][0]["slot"]  # the rotation puts iLQR in either slot
        acted = replay.plans[: replay.steps][replay.status[: replay.steps, ilqr_car] == RACING]
        assert len(acted) > 10 and not np.isnan(acted[:, ilqr_car, 0]).any() and np.isnan(replay.plans[:, 1 - ilqr_car]).all()
