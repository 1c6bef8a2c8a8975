"""The `racing` command line: help, demo outputs, errors, and the paper reproduction (slow)."""

from __future__ import annotations

import json

import pytest

from experiments import paper
from experiments.cli import build_parser, main
from planners.ilq import SolverOptions


def test_help_lists_the_subcommands(capsys):
    """`racing --help` explains every subcommand."""
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for command in ("demo", "paper", "tournament", "convergence", "bench"):
        assert command in text


def test_demo_writes_gif_plot_and_result(tmp_path):
    """`racing demo` races two scripted cars to the finish and writes its three outputs."""
    assert main(["demo", "--scripted", "--out", str(tmp_path), "--track", "straight"]) == 0
    for name in ("race.gif", "trajectories.png", "result.json"):
        assert (tmp_path / name).stat().st_size > 0
    result = json.loads((tmp_path / "result.json").read_text())
    positions = sorted(row["position"] for row in result["summary"])
    assert positions == [1, 2]
    assert all(row["finished"] for row in result["summary"])


def test_scripted_demo_races_the_race_distance(tmp_path, capsys):
    """--race-distance sets the finish line of the scripted demo too (it was ignored: a 300 m lap)."""
    assert main(["demo", "--scripted", "--out", str(tmp_path), "--track", "straight", "--race-distance", "50"]) == 0
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["race_distance"] == 50.0
    assert all(row["finished"] and row["distance"] < 60.0 for row in result["summary"])
    assert "50 m" in capsys.readouterr().out
    assert main(["demo", "--scripted", "--out", str(tmp_path / "x"), "--seed", "-1"]) == 2
    assert "seed (--seed) must be an integer >= 0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_folder_for_a_file_or_a_file_for_a_folder_is_a_one_line_error(tmp_path, capsys):
    """OSErrors (here IsADirectoryError, FileExistsError) exit with status 2, not a traceback."""
    assert main(["sweep", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("racing sweep: error: ") and str(tmp_path) in err and len(err.splitlines()) == 1
    (tmp_path / "afile").write_text("")
    assert main(["tournament", "--agents", "lane-keeping", "constant-speed", "--out", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("racing tournament: error: ") and "afile" in err and len(err.splitlines()) == 1
    assert main(["tournament", "--agents", "lane-keeping", "constant-speed",
                 "--out", str(tmp_path / "afile" / "sub")]) == 2
    assert "afile" in capsys.readouterr().err


def test_tournament_cli_runs_and_resumes(tmp_path, capsys):
    """`racing tournament` with scripted agents writes its outputs; a rerun resumes."""
    args = ["tournament", "--agents", "lane-keeping", "constant-speed", "--track", "straight",
            "--race-distance", "120", "--grids", "1", "--no-gif", "--out", str(tmp_path)]
    assert main(args) == 0
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    assert len(lines) == 2
    assert main(args) == 0
    assert (tmp_path / "results.jsonl").read_text().splitlines() == lines
    assert "resuming: 2 of 2 races" in capsys.readouterr().out


def test_tournament_incident_rules_from_the_command_line(tmp_path, capsys):
    """--off-track terminate retires the car that leaves the track, and the leaderboard
    gets a retired column; the choices are the env's own incident modes."""
    from experiments.cli import INCIDENT_CHOICES, SCENARIO_CHOICES
    from racing_env.config import INCIDENT_MODES
    from racing_env.scenarios import SCENARIOS

    assert INCIDENT_CHOICES == INCIDENT_MODES and set(SCENARIO_CHOICES) == set(SCENARIOS)
    args = ["tournament", "--agents", "lane-keeping:target_n=8", "lane-keeping", "--track", "straight",
            "--race-distance", "120", "--grids", "1", "--no-gif", "--off-track", "terminate", "--contact", "ghost",
            "--out", str(tmp_path)]
    assert main(args) == 0
    assert "retired" in capsys.readouterr().out
    retired = [car["retired"] for line in (tmp_path / "results.jsonl").read_text().splitlines()
               for car in json.loads(line)["cars"] if car["agent"] == "lane-keeping:target_n=8"]
    assert retired == [True, True]
    with pytest.raises(SystemExit):
        main(["tournament", "--collision", "crash"])
    assert "invalid choice: 'crash'" in capsys.readouterr().err


def test_bad_track_is_a_clear_error(tmp_path, capsys):
    """An unknown track name exits with status 2 and names the built-in tracks."""
    assert main(["demo", "--scripted", "--out", str(tmp_path), "--track", "nowhere"]) == 2
    assert "trefoil" in capsys.readouterr().err


def test_bench_rejects_unknown_sections(capsys):
    """`racing bench --only nope` exits with status 2 and lists the sections."""
    assert main(["bench", "--only", "nope"]) == 2
    assert "env" in capsys.readouterr().err


@pytest.mark.slow
def test_paper_reproduction_writes_figures_and_json(tmp_path):
    """`racing paper` solves every method, writes both figures and a complete paper.json."""
    assert main(["paper", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "paper.json").read_text())
    for name in ("fig1_methods.png", "fig2_collision_weight.png", "fig3_convergence.png",
                 "fig4_landscape_default.png", "fig5_landscape_printed.png", "fig6_stackelberg.png"):
        assert (tmp_path / name).stat().st_size > 0
    for key in ("ilqr", "feedback", "open_loop", "open_loop_from_feedback"):
        method = report["methods"][key]
        assert {"converged", "iterations", "solve_time_s", "ego_n_min", "final_gap_s", "min_distance"} <= set(method)
        # one convergence measure and step size per iteration; a converged run ends within tolerance
        assert len(method["convergence"]) == len(method["step_sizes"]) == method["iterations"]
        assert method["convergence"][-1] <= SolverOptions().tolerance
    assert report["methods"]["open_loop"]["converged"]
    assert max(report["methods"]["open_loop"]["nash_residual"]) < 1e-4
    assert len(report["findings"]) >= 6
    # every game solution is certified; the default solver's are local Nash equilibria
    for key in ("feedback", "open_loop", "open_loop_printed", "feedback_printed"):
        assert report["methods"][key]["certificate"]["verdict"] in ("local Nash equilibrium", "saddle", "not stationary")
    assert report["methods"]["open_loop"]["certificate"]["verdict"] == "local Nash equilibrium"
    # the leader-follower solutions, each car leading, certified (docs/experiments/paper.md)
    assert {record["leader"] for record in report["stackelberg"].values()} == {0, 1}
    for record in report["stackelberg"].values():
        assert record["converged"] and record["certificate"]["verdict"] == "local Stackelberg solution"
    assert set(report["landscapes"]) == {"default", "paper"}
    for by_mode in report["landscapes"].values():
        for record in by_mode.values():
            assert sum(e["count"] for e in record["equilibria"]) <= record["starts"] == paper.LANDSCAPE_STARTS


@pytest.mark.slow  # the default run's budget: find_equilibria is tested by default (tests/test_certify.py)
def test_equilibria_writes_the_certified_landscape(tmp_path, capsys):
    """`racing equilibria` on the paper scene with three starts (zero inputs and two pulses)."""
    out = tmp_path / "eq"
    assert main(["equilibria", "--modes", "open_loop", "--starts", "3", "--out", str(out)]) == 0
    report = json.loads((out / "equilibria.json").read_text())
    record = report["landscapes"]["open_loop"]
    assert record["starts"] == 3 and record["kinds"] == ["zero", "pulse", "pulse"]
    assert sum(e["count"] for e in record["equilibria"]) == 3 * record["converged_share"]
    zero = next(e for e in record["equilibria"] if 0 in e["starts"])
    assert zero["certificate"]["verdict"] == "local Nash equilibrium"  # the default solver from zero inputs
    assert zero["metrics"]["order"] == [1, 0]  # the faster opponent ends ahead
    assert (out / "equilibria.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "local Nash equilibrium" in capsys.readouterr().out
    assert main(["equilibria", "--starts", "0", "--out", str(out)]) == 2  # refused with a message


def test_convergence_figure_is_written(tmp_path):
    records = [{"method": "a", "convergence": [1.0, 1e-3, 1e-7], "step_sizes": [0.5, 1.0, 1.0]},
               {"method": "b", "convergence": [2.0], "step_sizes": [1.0]}]
    paper.plot_convergence(records, 1e-6, tmp_path / "fig3.png")
    assert (tmp_path / "fig3.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_commands_other_than_train_never_import_the_rl_layer(tmp_path):
    """`racing tournament` (and the parser of every command) runs without importing torch,
    stable-baselines3 or experiments.rl: only `racing train` needs them."""
    import subprocess
    import sys

    script = (
        "import sys\n"
        "from experiments.cli import build_parser, main\n"
        "build_parser()\n"
        f"code = main(['tournament', '--agents', 'lane-keeping', 'constant-speed', '--track', 'straight', "
        f"'--race-distance', '60', '--grids', '1', '--no-gif', '--no-compile-cache', '--out', {str(tmp_path)!r}])\n"
        "loaded = [m for m in ('torch', 'stable_baselines3', 'experiments.rl', 'experiments.rl.train') "
        "if m in sys.modules]\n"
        "print('loaded:', loaded)\n"
        "sys.exit(code or bool(loaded))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "loaded: []" in done.stdout


def test_the_jerk_weight_help_names_the_racing_default(capsys):
    """`--jerk-weight`'s help states the default races use, which is the env's own."""
    from racing_env.costs import RACING_JERK_WEIGHT

    for command in ("tournament", "train"):
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert f"(default: {RACING_JERK_WEIGHT}, racing_env.costs.RACING_JERK_WEIGHT" in text


def test_tracks_lists_every_track_by_name_and_draws_one(tmp_path, capsys):
    assert main(["tracks", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    names = [row["name"] for row in rows]
    assert names[:3] == ["straight", "trefoil", "random"] and len(names) == 3 + 25 and "Suzuka" in names
    monza = rows[names.index("Monza")]
    assert monza["closed"] and monza["raceline"] and 7.0 < monza["min_width"] < monza["mean_width"]
    assert monza["corners"] > 5 and 5700 < monza["length"] < 5900
    assert main(["tracks", "--plot", "suzuka", "--out", str(tmp_path / "suzuka.png")]) == 0
    assert (tmp_path / "suzuka.png").stat().st_size > 10_000
    assert main(["tracks", "--plot", "Imola", "--out", str(tmp_path / "imola.png")]) == 2
    assert "unknown track 'Imola'" in capsys.readouterr().err
