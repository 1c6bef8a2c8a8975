"""`racing bench`'s description of the machine its figures come from."""

import json
import os

import jax
import numpy as np
import pytest

from experiments import bench
from planners.compile_cache import ENV_VAR, compile_cache_dir


def test_machine_info_names_the_cpu_and_the_load():
    info = bench.machine_info()
    json.dumps(info)  # goes into the JSON report as it is
    assert info["cpu"] and info["cpu"] != "unknown"
    assert info["cpu_count"] == os.cpu_count()
    assert len(info["load_average"]) == 3 and all(v >= 0 for v in info["load_average"])
    # the tests' own per-run cache (tests/conftest.py), as the process has it
    assert info["devices"] and info["compile_cache"] == compile_cache_dir() == os.environ[ENV_VAR]
    # The tests import planners before JAX starts, so the solvers' loops are single kernels.
    assert "xla_cpu_small_while_loop_byte_threshold" in info["xla_flags"]


def test_batched_machine_reference_is_a_positive_rate():
    row = bench._machine_reference_batched(repeats=1, lanes=64, steps=5)
    assert row["name"] == "machine_reference_batched"
    assert row["ns_per_lane_step"] > 0 and row["compile_s"] >= 0


def test_dgemm_reference_is_a_positive_rate_below_any_cores_peak():
    row = bench._machine_reference_dgemm(repeats=2, n=200)
    assert row["name"] == "machine_reference_dgemm"
    # no core of this decade does more than 64 float64 flops per cycle at 6 GHz
    assert 0 < row["gflop_per_s"] < 64 * 6.0 * os.cpu_count()


def test_batch_verdict_states_the_rate_its_target_needs():
    row = {"name": "b", "throughput_ratio": 2.1, "target_ratio": 10.0,
           "gflop_per_s_at_target": 91.7, "dgemm_share_at_target": 0.85}
    assert bench._verdict_text(row, bench._target_verdict(row)) == (
        ">= 10 throughput_ratio: MISSED (the target needs 91.7 GFLOP/s, 85% of dgemm)")


def test_report_is_saved_after_every_row_and_kept_on_ctrl_c(tmp_path, monkeypatch):
    """Rows reach the JSON file as they are measured; Ctrl-C keeps them and marks the run."""
    out = tmp_path / "bench.json"
    seen_on_disk = []

    def section():
        yield {"name": "first", "ms_per_iter": 1.5, "compile_s": 0.1, "target_ms": 1.0}
        seen_on_disk.append(json.loads(out.read_text())["results"]["fake"])
        yield {"name": "second", "ms_per_iter": 2.5}
        raise KeyboardInterrupt

    monkeypatch.setitem(bench.SECTIONS, "fake", section)
    report = bench.run_bench(["fake"], out)
    assert seen_on_disk == [[{"name": "first", "ms_per_iter": 1.5, "compile_s": 0.1, "target_ms": 1.0,
                              "target_met": False}]]
    assert report["interrupted"] is True
    assert [row["name"] for row in report["results"]["fake"]] == ["first", "second"]
    assert json.loads(out.read_text()) == report
    assert not list(tmp_path.glob("*.partial"))
    assert set(report["section_seconds"]) == {"fake"}


def test_cli_exits_130_when_interrupted(monkeypatch, capsys):
    from experiments.cli import main

    def section():
        yield {"name": "only", "steps_per_s": 10.0}
        raise KeyboardInterrupt

    monkeypatch.setitem(bench.SECTIONS, "fake", section)
    assert main(["bench", "--only", "fake"]) == 130
    printed = json.loads(capsys.readouterr().out)
    assert printed["interrupted"] is True and printed["results"]["fake"][0]["name"] == "only"


def test_ctrl_c_on_a_real_run_keeps_the_measured_rows(tmp_path):
    """SIGINT to `racing bench --only env` after its first row: exit status 130, and the
    JSON file holds that row, marked interrupted."""
    import signal
    import subprocess

    from interrupting import racing_command

    out = tmp_path / "bench.json"
    proc = subprocess.Popen(
        racing_command(["bench", "--only", "env", "--json", str(out)]),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    for line in proc.stderr:  # rows are printed as they are measured
        if "env_step_2_cars:" in line:
            break
    proc.send_signal(signal.SIGINT)
    stdout, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130
    report = json.loads(out.read_text())
    assert report["interrupted"] is True
    assert [row["name"] for row in report["results"]["env"]][0] == "env_step_2_cars"
    assert json.loads(stdout)["interrupted"] is True


def test_lq_state_size_row_reports_every_state_size():
    # A loop kernel runs a stage of a 1-state game in well under a microsecond: the horizon
    # must be long enough for 20 solves to stand out from the timing noise of one.
    row = bench._lq_state_size_row(state_dims=(1, 3), horizon=50)
    assert row["name"] == "lq_feedback_us_per_stage_by_state_size_N2"
    assert set(row) == {"name", "n1", "n3"}
    assert row["n1"] > 0 and row["n3"] > 0


def test_figure_shows_the_headline_or_every_part():
    assert bench._figure({"name": "x", "ms_per_iter": 0.6971, "compile_s": 5.0, "target_ms": 0.25}) == "0.6971 ms_per_iter"
    assert bench._figure({"name": "parts", "linearize": 0.1042, "lq_feedback": 0.19961}) == "linearize 0.104, lq_feedback 0.2"


def test_figure_and_verdict_show_the_tenth_percentile_beside_the_median():
    row = {"name": "x", "ms_per_iter": 0.36, "ms_per_iter_p10": 0.21, "target_ms": 0.25, "target_met_p10": True}
    assert bench._figure(row) == "0.36 ms_per_iter (p10 0.21)"
    verdict = bench._target_verdict(row)
    assert verdict == ("<= 0.25 ms_per_iter", False)  # the median decides
    assert bench._verdict_text(row, verdict) == "<= 0.25 ms_per_iter: MISSED (p10: met)"
    assert bench._verdict_text({"name": "y"}, ("<= 50 ms_per_solve", True)) == "<= 50 ms_per_solve: met"


def test_interleaved_calls_time_every_function_in_turns():
    order = []
    calls = {name: (lambda name=name: order.append(name) or len(order)) for name in ("a", "b")}
    timed = bench._interleaved_calls(calls, rounds=3)
    assert order == ["a", "b"] * 4  # one compiling call each, then three rounds in turns
    assert timed.results == {"a": 1, "b": 2}  # the first calls' results
    assert {name: s.shape for name, s in timed.seconds.items()} == {"a": (3,), "b": (3,)}
    assert all((s >= 0).all() for s in timed.seconds.values()) and all(v >= 0 for v in timed.first_s.values())
    assert timed.median_s("a") == float(np.median(timed.seconds["a"]))
    assert timed.compile_s("a") == timed.first_s["a"] - timed.median_s("a")


def test_a_bench_run_records_the_verdict_on_the_tenth_percentile(monkeypatch):
    def section():
        yield {"name": "iter", "ms_per_iter": 0.36, "ms_per_iter_p10": 0.21, "target_ms": 0.25}
        yield {"name": "solve", "ms_per_solve": 5.0, "target_ms": 50.0}

    monkeypatch.setitem(bench.SECTIONS, "fake", section)
    iteration, solve = bench.run_bench(["fake"])["results"]["fake"]
    assert iteration["target_met"] is False and iteration["target_met_p10"] is True
    assert solve["target_met"] is True and "target_met_p10" not in solve


def test_target_verdict_knows_which_way_each_target_points():
    assert bench._target_verdict({"name": "x", "ms_per_iter": 0.52, "target_ms": 0.25}) == ("<= 0.25 ms_per_iter", False)
    assert bench._target_verdict({"name": "x", "ms_per_solve": 8.7, "target_ms": 50.0}) == ("<= 50 ms_per_solve", True)
    assert bench._target_verdict({"name": "x", "throughput_ratio": 1.6, "target_ratio": 10.0}) == (">= 10 throughput_ratio", False)
    assert bench._target_verdict({"name": "x", "steps_per_s": 5100.0, "target_steps_per_s": 5000}) == (">= 5000 steps_per_s", True)
    assert bench._target_verdict({"name": "x", "ms_p95": 21.6, "target_ms_p95": 50.0}) == ("<= 50 ms_p95", True)
    assert bench._target_verdict({"name": "x", "ms_per_iter": 1.9, "target_ms": None}) is None
    # suffix: the same target judged on another figure of the row, if the row has it
    assert bench._target_verdict({"name": "x", "ms_per_iter": 0.36, "ms_per_iter_p10": 0.21, "target_ms": 0.25},
                                 "_p10") == ("<= 0.25 ms_per_iter", True)
    assert bench._target_verdict({"name": "x", "ms_per_solve": 8.7, "target_ms": 50.0}, "_p10") is None


def test_env_section_measures_both_views():
    rows = list(bench.bench_env(steps=30, repeats=1, cars=(2,)))
    assert [row["name"] for row in rows] == ["env_step_2_cars", "gym_step_vs_lane_keeper"]
    assert all(row["steps_per_s"] > 0 and row["us_per_step"] > 0 for row in rows)
    assert rows[0]["target_steps_per_s"] == 5000 and "target_steps_per_s" not in rows[1]


@pytest.mark.slow
def test_iteration_rows_report_the_distribution_of_every_configuration():
    rows = list(bench._iteration_rows(fixed_iterations=2, rounds=3))
    assert [row["name"] for row in rows] == [f"{mode}_iteration_N{num}_T50"
                                            for num in (2, 3) for mode in ("feedback", "open_loop")]
    for row in rows:
        assert row["calls"] == 3 and row["compile_s"] > 0
        assert 0 < row["ms_per_iter_min"] <= row["ms_per_iter_p10"] <= row["ms_per_iter"]
        assert row["gflop_per_s"] == pytest.approx(row["mflop_per_iter"] / row["ms_per_iter"], rel=1e-12)
    assert [row["target_ms"] for row in rows] == [0.25, None, None, None]


# slow (the default run's budget)
@pytest.mark.slow
def test_convergence_rows_summarise_the_single_solves_of_the_same_scenes():
    """The convergence row's fraction, status counts, iteration figures and per-scene
    outcomes are those of the same random scenes solved one at a time, with the row's
    jerk weight, iteration cap and first step size."""
    from planners import ilq
    from racing_env import CostWeights, RaceGame, VehicleParams
    from racing_env.scenarios import random_scenes
    from racing_env.track import trefoil

    count = 6
    (row,) = bench.convergence_rows(count, seed=3, repeats=1, modes=("open_loop",), max_iterations=40,
                                    jerk_weight=0.5, per_scene=True, initial_step=0.5)
    vehicles = [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0)]
    game = RaceGame.create(trefoil(), vehicles, CostWeights(r_jx=0.5, r_jy=0.5))
    singles = [ilq.solve(game, x0, mode="open_loop", max_iterations=40, initial_step=0.5)
               for x0 in random_scenes(trefoil(), vehicles, count, seed=3)]
    converged = np.array([bool(r.converged) for r in singles])
    iterations = np.array([int(r.iterations) for r in singles])
    assert row["name"] == f"open_loop_convergence_random{count}_N2_trefoil" and row["scenes"] == count
    assert (row["mode"], row["track"], row["cars"]) == ("open_loop", "trefoil", 2)
    assert row["iterations"] == iterations.tolist()
    assert row["status"] == [ilq.status_message(r.status) for r in singles]
    assert row["converged_fraction"] == converged.mean()
    assert sum(row["statuses"].values()) == count
    assert row["statuses"].get("converged", 0) == converged.sum()
    if converged.any():
        assert row["iterations_median"] == np.median(iterations[converged])
        assert row["iterations_max"] == iterations[converged].max()
    assert row["ms_batch"] > 0 and row["compile_s"] > 0
    assert bench._figure(row) == f"{row['converged_fraction']:.4g} converged_fraction"
    with pytest.raises(ValueError, match="repeats"):
        next(bench.convergence_rows(count, repeats=0))
    with pytest.raises(ValueError, match="max_iterations"):
        next(bench.convergence_rows(count, max_iterations=0))


@pytest.mark.slow  # the default run's budget: the convergence rows' test covers the same solves by default
def test_open_loop_from_feedback_rows_start_from_each_scenes_feedback_solution():
    """``open_loop_from_feedback``: per scene, the open-loop solve initialised with that
    scene's feedback solution, whether or not a feedback row comes first."""
    from planners import ilq
    from racing_env import CostWeights, RaceGame, VehicleParams
    from racing_env.scenarios import random_scenes
    from racing_env.track import trefoil

    count, options = 4, dict(max_iterations=40, initial_step=0.5)
    fb, ol_fb = bench.convergence_rows(count, seed=3, repeats=1, modes=("feedback", "open_loop_from_feedback"),
                                       jerk_weight=0.5, per_scene=True, **options)
    (alone,) = bench.convergence_rows(count, seed=3, repeats=1, modes=("open_loop_from_feedback",),
                                      jerk_weight=0.5, per_scene=True, **options)
    vehicles = [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0)]
    game = RaceGame.create(trefoil(), vehicles, CostWeights(r_jx=0.5, r_jy=0.5))
    singles = []
    for x0 in random_scenes(trefoil(), vehicles, count, seed=3):
        feedback = ilq.solve(game, x0, mode="feedback", **options)
        singles.append(ilq.solve(game, x0, feedback.us, mode="open_loop", **options))
    assert ol_fb["mode"] == "open_loop_from_feedback"
    assert ol_fb["iterations"] == alone["iterations"] == [int(r.iterations) for r in singles]
    assert ol_fb["status"] == alone["status"] == [ilq.status_message(r.status) for r in singles]
    assert fb["iterations"] != ol_fb["iterations"]  # the rows are two different solves


@pytest.mark.slow  # a long end: the default run stays within its budget
def test_rl_rows_measure_the_vectorised_env_and_its_opponents():
    from experiments import bench_rl

    baseline = bench_rl.pettingzoo_row(steps=20, repeats=1)
    assert baseline["steps_per_s"] > 0
    rows = list(bench_rl.vector_rows(baseline["steps_per_s"], calls=3, repeats=1, batches=(1, 8)))
    assert [row["races"] for row in rows] == [1, 8]
    assert all(row["steps_per_s"] > 0 and row["vs_pettingzoo"] > 0 for row in rows)
    rows = list(bench_rl.opponent_rows(num_envs=2, calls=2, opponents=("lane-keeping", "ilqgame-fb")))
    assert [row["replan_every"] for row in rows] == [1, 1, 5]
    planner = rows[1]
    assert planner["target_steps_per_s"] == 4_000 and 0.0 <= planner["converged_share"] <= 1.0
    assert 1 <= planner["iterations_median"] <= planner["iterations_p95"]
    rows = list(bench_rl.opponent_rows(num_envs=2, calls=2, opponents=("ilqgame-fb:iterations=2",),
                                       learner_acts="random", replan_every=(1,)))
    [row] = rows
    assert row["name"].endswith("_random_learner") and row["target_steps_per_s"] == 3_000
    assert 1 <= row["iterations_median"] <= row["iterations_p95"] <= 2  # capped at its 2 iterations


def test_the_short_episode_row_counts_resets_and_judges_the_rate_against_endless_races():
    from experiments import bench_rl

    endless, short = bench_rl.short_episode_rows(num_envs=16, calls=40, repeats=1, track="trefoil")
    assert endless["episode_ends_per_step"] == 0.0 and endless["steps_per_s"] > 0
    assert short["race_distance"] == 150.0 and short["on_off_track"] == "terminate"
    assert short["episode_ends_per_step"] > 0  # random actions leave the track within a few dozen steps
    assert short["vs_endless"] == pytest.approx(short["steps_per_s"] / endless["steps_per_s"], rel=1e-12)
    text, _ = bench._target_verdict(short)
    assert "vs_endless" in text and ">= 0.5" in text


@pytest.mark.slow  # two vectorised envs compiled (about 8 s); `racing bench --only rl` runs the rows
def test_the_contact_rows_judge_physics_against_ghost_cars():
    from experiments import bench_rl

    ghost, physics = bench_rl.contact_rows(num_envs=4, calls=55, repeats=1)
    assert (ghost["contact"], physics["contact"]) == ("ghost", "physics")
    assert physics["vs_ghost"] == pytest.approx(physics["steps_per_s"] / ghost["steps_per_s"], rel=1e-12)
    text, _ = bench._target_verdict(physics)
    assert ">= 0.8 vs_ghost" in text and bench._target_verdict(ghost) is None


@pytest.mark.slow  # three compiled race loops (about 19 s); `racing bench --only rl` runs the rows
def test_gymnax_rows_time_the_scanned_races_with_x64_on_and_off_beside_the_vector_env():
    from experiments import bench_rl

    rows = list(bench_rl.gymnax_rows(num_envs=4, steps=5, repeats=1))
    assert [row["name"] for row in rows] == ["gymnax_trefoil_lane-keeping_B4_x64_on",
                                             "gymnax_trefoil_lane-keeping_B4_x64_off", "vector_env_trefoil_lane-keeping_B4"]
    assert [row.get("race_dtype") for row in rows] == ["float64", "float32", None]  # the race in the scoped precision
    assert all(row["steps_per_s"] > 0 and row["compile_s"] > 0 for row in rows)
    assert jax.config.jax_enable_x64  # the scope ended: the process's setting is back


@pytest.mark.slow
def test_certificates_section_times_solve_and_certificates_of_each_mode():
    rows = list(bench.bench_certificates(rounds=1, cars=(2,)))
    assert [row["name"] for row in rows] == ["certificate_open_loop_N2_T50", "certificate_feedback_N2_T50"]
    for row in rows:
        assert row["ms_solve"] > 0 and row["ms_cheap"] > 0 and row["ms_full"] > 0
        assert row["full_over_solve"] == pytest.approx(row["ms_full"] / row["ms_solve"], rel=1e-12)
        assert row["verdict"] == "local Nash equilibrium"  # the default solver's solutions of the paper scene


def test_render_section_times_each_camera_and_the_recording_of_a_race():
    rows = list(bench.bench_render(rounds=1, tracks=("trefoil",)))
    assert [row["name"] for row in rows] == ["frame_trefoil", "race_recording_trefoil"]
    frame, race = rows
    assert frame["ms_track_camera"] > 0 and frame["ms_follow"] > 0 and frame["ms_per_frame"] > 0
    assert bench._target_verdict(frame) is not None  # judged against the few-milliseconds target
    assert race["race_steps"] > 100 and race["bare_steps_per_s"] > 0 and race["steps_per_s"] > 0
    assert race["throughput_ratio"] == pytest.approx(race["steps_per_s"] / race["bare_steps_per_s"], rel=1e-12)
    assert race["ms_replay_write"] > 0


def test_the_vector_field_rows_time_each_field_with_contact_and_with_ghost_cars():
    from experiments.bench_field import vector_field_rows

    physics, ghost = vector_field_rows(cars=(3,), num_envs=4, calls=5, repeats=1)
    assert (physics["name"], ghost["name"]) == ("vector_env_3_cars_B4", "vector_env_3_cars_B4_ghost")
    assert physics["vs_ghost"] == pytest.approx(physics["steps_per_s"] / ghost["steps_per_s"], rel=1e-12)
    assert physics["vs_first_field"] == 1.0 and ghost["steps_per_s"] > 0


def test_jax_learner_row_times_updates_after_the_compiling_one():
    from experiments import bench_rl

    small = (("n_steps", 16), ("batch_size", 64), ("n_epochs", 1))
    row = bench_rl.jax_training_row("lane-keeping", 8, updates=2, target=50_000, hyperparameters=small)
    assert row["races"] == "compiled" and row["steps"] == 2 * 16 * 8
    assert row["steps_per_s"] > 0 and row["first_update_s"] > 0
    assert bench._target_verdict(row) is not None


@pytest.mark.slow  # the host races' training compiles apart (about 15 s)
def test_the_jax_learner_row_races_on_the_host_when_asked():
    from experiments import bench_rl

    small = (("n_steps", 16), ("batch_size", 64), ("n_epochs", 1))
    host = bench_rl.jax_training_row("lane-keeping", 8, updates=2, hyperparameters=small, host=True)
    assert host["races"] == "host" and host["name"] == "jax_ppo_lane-keeping_B8_host" and host["steps"] == 2 * 16 * 8
    assert host["steps_per_s"] > 0 and host["first_update_s"] > 0


@pytest.mark.slow  # a child process compiles the parts and the whole iteration (about 2 min)
def test_roofline_rows_cover_every_part_against_both_references():
    from experiments.bench_roofline import PARTS, roofline_rows

    rows = {row["name"]: row for row in roofline_rows(races=2)}
    assert rows["roofline_reference_gemm_one_core"]["gflop_per_s"] > 0
    assert rows["roofline_reference_small_matmul"]["gflop_per_s"] > 0
    names = [f"roofline_{part}_B2" for part in (*PARTS, "lq_recursion_batched", "whole_iteration_float32")]
    for name in names:
        row = rows[name]
        assert row["us_per_race"] > 0 and row["mflop_per_race"] > 0, row
        assert np.isclose(row["gemm_share"] * rows["roofline_reference_gemm_one_core"]["gflop_per_s"],
                          row["gflop_per_s"])
    whole = rows["roofline_whole_iteration_B2"]["mflop_per_race"]
    # the iteration holds each part once (one step-size trial), plus its own bookkeeping
    assert sum(rows[f"roofline_{part}_B2"]["mflop_per_race"] for part in PARTS[:-1]) <= whole
    # float32 runs the same arithmetic; the batched LQ recursion the same recursion (as dots)
    assert rows["roofline_whole_iteration_float32_B2"]["mflop_per_race"] == whole
    assert rows["roofline_lq_recursion_batched_B2"]["mflop_per_race"] >= rows["roofline_lq_recursion_B2"]["mflop_per_race"]
