"""`racing convergence`: the sweep's outputs, its errors, and what an interruption keeps."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import convergence
from experiments.cli import main
from planners import ilq, nash
from racing_env import CostWeights, RaceGame, VehicleParams
from racing_env.dynamics import S, V
from racing_env.track import get_track

# Not tests/test_bench.py's cap: that test checks that its first call compiles.
ARGS = ["convergence", "--scenes", "6", "--seed", "3", "--modes", "open_loop", "--max-iterations", "30",
        "--jerk-weight", "0.5", "--spread", "8", "--speed", "12", "14", "--step-control", "none",
        "--initial-step", "0.5", "--solver-option", "max_backtracks=3", "--no-compile-cache"]


@pytest.mark.slow  # the default run's budget: the bench's convergence rows run the same solves by default
def test_convergence_cli_writes_json_and_profile_plot(tmp_path, capsys):
    assert main(ARGS + ["--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "convergence.json").read_text())
    assert report["config"]["jerk_weight"] == 0.5 and report["config"]["max_iterations"] == 30
    assert report["config"]["step_control"] == "none" and report["config"]["initial_step"] == 0.5
    assert report["config"]["other_options"] == [["max_backtracks", 3]]
    assert "interrupted" not in report
    (row,) = report["rows"]
    assert (row["track"], row["cars"], row["mode"], row["scenes"]) == ("trefoil", 2, "open_loop", 6)
    assert len(row["iterations"]) == len(row["status"]) == len(row["x0"]) == 6
    x0 = np.array(row["x0"])  # (scenes, cars, 6): the scenes follow --spread and --speed
    assert np.all(np.ptp(x0[..., S], axis=1) <= 8.0) and np.all((x0[..., V] >= 12.0) & (x0[..., V] <= 14.0))
    assert all(1 <= it <= 30 for it in row["iterations"])
    converged = [st == "converged" for st in row["status"]]
    assert row["converged_fraction"] == sum(converged) / 6
    assert sum(row["statuses"].values()) == 6
    # the residual of every solve, as nash_residual gives it for that scene's own solve
    assert len(row["residual"]) == 6 and row["residual_max"] == max(row["residual"])
    race_game = RaceGame.create(get_track("trefoil"), [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0)],
                                CostWeights(r_jx=0.5, r_jy=0.5))  # convergence_rows' two cars
    x0 = np.array(row["x0"][0])
    single = ilq.solve(race_game, x0, mode="open_loop", max_iterations=30, step_control="none",
                       initial_step=0.5, max_backtracks=3)
    assert int(single.iterations) == row["iterations"][0]
    np.testing.assert_allclose(row["residual"][0], float(np.max(nash.nash_residual(race_game, x0, single.us))),
                               rtol=1e-9)
    (same,) = convergence.convergence_rows(6, seed=3, repeats=1, modes=("open_loop",), max_iterations=30,
                                           jerk_weight=0.5, per_scene=True, spread=8.0, speed=(12.0, 14.0),
                                           step_control="none", initial_step=0.5, max_backtracks=3)
    assert (same["x0"], same["iterations"], same["status"]) == (row["x0"], row["iterations"], row["status"])
    assert (tmp_path / "convergence.png").stat().st_size > 0
    assert not list(tmp_path.glob("*.partial"))
    assert f"{sum(converged)}/6" in capsys.readouterr().err  # the table


@pytest.mark.parametrize("bad, message", [
    (["--scenes", "0"], "scenes"),
    (["--cars", "0"], "cars"),
    (["--jerk-weight", "-1"], "jerk_weight"),
    (["--max-iterations", "0"], "max_iterations"),
    (["--tolerance", "-1"], "tolerance"),
    (["--initial-step", "0"], "initial_step"),
    (["--solver-option", "trust_radius"], "NAME=VALUE"),
    (["--solver-option", "warp=9"], "NAME=VALUE"),
    (["--solver-option", "mode=feedback"], "further solver options"),
    (["--solver-option", "oscillation_damping=maybe"], "true or false"),
    (["--solver-option", "trust_radius=0"], "trust_radius"),
    (["--spread", "-1"], "spread"),
    (["--speed", "19", "10"], "speed"),
    (["--track", "nowhere"], "trefoil"),
    (["--step-control", "residual"], "open-loop solves"),  # the default modes include feedback
    (["--solver-option", "control_regularization=0.3", "--solver-option", "adaptive_regularization=true"],
     "open-loop games and one-player problems"),  # feedback games of two cars refuse it
    (["--solver-option", "control_regularization=0.3", "--solver-option", "feedforward_regularization=true"],
     "is for feedback games"),  # the default modes include open loop
])
def test_convergence_cli_rejects_bad_input_before_any_work(tmp_path, capsys, bad, message):
    assert main(["convergence", "--out", str(tmp_path / "out")] + bad) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "convergence.json").exists()


def test_interrupted_sweep_keeps_the_rows_measured(tmp_path, monkeypatch, capsys):
    """Ctrl-C after the first (real) row: exit status 130, and the JSON and the plot hold
    that row, the report marked interrupted."""
    real_rows = convergence.convergence_rows

    def first_row_then_interrupt(*args, **kwargs):
        yield next(real_rows(*args, **kwargs))
        raise KeyboardInterrupt

    monkeypatch.setattr(convergence, "convergence_rows", first_row_then_interrupt)
    assert main(ARGS + ["--modes", "open_loop", "feedback", "--out", str(tmp_path)]) == 130
    report = json.loads((tmp_path / "convergence.json").read_text())
    assert report["interrupted"] is True
    assert [row["mode"] for row in report["rows"]] == ["open_loop"]
    assert (tmp_path / "convergence.png").stat().st_size > 0
    assert "interrupted" in capsys.readouterr().err
