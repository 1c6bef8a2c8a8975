"""The library surface (planners/__init__.py, planners.methods, racing_env.scenarios.paper_game):
the documented names and nothing else, no RL stack at import, one name per method across the
registry, the agent classes, the solver modes, the predictions and the CLI, and the paper's scene."""

from __future__ import annotations

import argparse
import subprocess
import sys

import numpy as np
import pytest

import planners
from planners import agents as agents_package, ilq, methods, prediction
from planners.agents.receding_horizon import RecedingHorizonAgent
from racing_env.scenarios import PAPER_WEIGHTS, paper_game

DOCUMENTED = {
    # agents
    "Agent", "BaseAgent", "FeedbackGameAgent", "OpenLoopGameAgent", "LeaderGameAgent", "FollowerGameAgent", "ILQRAgent", "LaneKeepingAgent", "RacelineAgent",
    "ConstantSpeedAgent", "RandomAgent", "SB3Agent", "JaxPolicyAgent", "make_agent", "AGENTS", "agent_options", "reset_agents",
    # batched opponents (one object drives one car in B races)
    "BatchedOpponent", "make_batched_opponent",
    # solvers
    "solve", "solve_batch", "nash_residual", "SolverOptions", "SolverResult", "GameProblem",
    "problem_from_race_game", "solve_ilqr", "solve_feedback", "solve_open_loop",
    # certificates and landscapes
    "certify", "Certificate", "find_equilibria",
}

SPEC_CLASSES = {
    "ilqgame-fb": "FeedbackGameAgent",
    "ilqgame-ol": "OpenLoopGameAgent",
    "ilqgame-leader": "LeaderGameAgent",
    "ilqgame-follower": "FollowerGameAgent",
    "ilqr": "ILQRAgent",
    "raceline": "RacelineAgent",
    "lane-keeping": "LaneKeepingAgent",
    "constant-speed": "ConstantSpeedAgent",
    "random": "RandomAgent",
}


def test_planners_exports_exactly_the_documented_names():
    assert set(planners.__all__) == DOCUMENTED
    assert len(planners.__all__) == len(DOCUMENTED)
    for name in DOCUMENTED:
        assert getattr(planners, name) is not None
    namespace: dict = {}
    exec("from planners import *", namespace)
    assert DOCUMENTED <= set(namespace)
    assert planners.__doc__ and "ilqgame-fb" in planners.__doc__


def test_the_exported_names_are_the_modules_own():
    from planners import agents, certificates, game_problem, ilq_batch, ilqr, landscape, lq_game, nash, race_problem

    assert planners.solve is ilq.solve and planners.SolverOptions is ilq.SolverOptions
    assert planners.SolverResult is ilq.SolverResult and planners.GameProblem is game_problem.GameProblem
    assert planners.solve_batch is ilq_batch.solve_batch and planners.nash_residual is nash.nash_residual
    assert planners.problem_from_race_game is race_problem.problem_from_race_game
    assert planners.solve_ilqr is ilqr.solve_ilqr
    assert planners.solve_feedback is lq_game.solve_feedback and planners.solve_open_loop is lq_game.solve_open_loop
    assert planners.certify is certificates.certify and planners.Certificate is certificates.Certificate
    assert planners.find_equilibria is landscape.find_equilibria
    assert planners.AGENTS is agents.AGENTS is agents.AGENT_SPECS
    assert planners.SB3Agent is agents.SB3Agent


def test_import_planners_loads_no_rl_stack():
    """``import planners`` (and making a planner) neither imports stable-baselines3 nor torch:
    the SB3 adapter is loaded when it is first used."""
    code = (
        "import sys, planners\n"
        "planners.make_agent('ilqgame-fb'); planners.make_agent('lane-keeping')\n"
        "print(sorted(m for m in ('stable_baselines3', 'torch', 'planners.agents.sb3') if m in sys.modules))\n"
        "planners.SB3Agent\n"
        "print('planners.agents.sb3' in sys.modules, 'stable_baselines3' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "[]"
    assert out[1] == "True False"  # the adapter's module is light: stable-baselines3 loads with a model


def test_planners_agents_keeps_every_name_it_had():
    earlier = {"Agent", "AGENT_SPECS", "AGENT_SUMMARIES", "BaseAgent", "ConstantSpeedAgent", "FeedbackGameAgent",
               "ILQRAgent", "LaneKeepingAgent", "OpenLoopGameAgent", "RecedingHorizonAgent", "SB3Agent",
               "agent_options", "check_specs", "game_of", "make_agent", "reset_agents", "vecnormalize_path",
               "SB3_ALGOS", "RECOVERED_SPEED", "STOPPED_SPEED", "REPLAN_TOLERANCE"}
    assert earlier <= set(agents_package.__all__)
    for name in agents_package.__all__:
        assert getattr(agents_package, name) is not None
    with pytest.raises(AttributeError):
        agents_package.no_such_name  # noqa: B018


def test_each_registry_name_is_its_class_spec():
    assert tuple(planners.AGENTS) == methods.AGENT_METHODS
    assert {name: cls.__name__ for name, cls in planners.AGENTS.items()} == SPEC_CLASSES
    for name, cls in planners.AGENTS.items():
        assert cls.spec == name == cls.name
        assert getattr(planners, SPEC_CLASSES[name]) is cls
        agent = planners.make_agent(name)
        assert type(agent) is cls and agent.spec == name
    assert planners.SB3Agent.spec == methods.RL
    assert RecedingHorizonAgent.spec is None and planners.BaseAgent.spec is None  # not in the registry
    assert set(agents_package.AGENT_SUMMARIES) == set(planners.AGENTS)


def _stub_solver(monkeypatch) -> list[str]:
    """Replace ``ilq.solve`` by a stub that records the mode it is called in and raises."""
    called = []

    def solve(game, x0, **kwargs):
        called.append(kwargs["mode"])
        raise RuntimeError("not solved here")

    monkeypatch.setattr(ilq, "solve", solve)
    return called


def test_game_agents_call_the_solver_in_their_mode(monkeypatch):
    """Each game agent's ``mode`` is the one its name stands for, and the one it solves in."""
    assert methods.GAME_MODES == {"ilqgame-fb": "feedback", "ilqgame-ol": "open_loop"}
    for mode in methods.SOLVER_MODES:
        ilq.SolverOptions(mode=mode)  # a solver mode the solver takes
    with pytest.raises(ValueError):
        ilq.SolverOptions(mode="ilqgame-fb")
    called = _stub_solver(monkeypatch)
    game, x0 = paper_game()
    for name, mode in {**methods.GAME_MODES, **dict.fromkeys(methods.STACKELBERG_GAMES, methods.STACKELBERG)}.items():
        agent = planners.make_agent(name)
        assert agent.mode == type(agent).mode == mode
        agent.reset(0, 0, game)
        action = agent.act(None, x0)  # the stub raises: the agent brakes, and says why
        assert called[-1] == mode and np.all(np.isfinite(action))
        assert "not solved here" in agent.diagnostics()["error"]
    assert planners.FeedbackGameAgent.feedback and not planners.OpenLoopGameAgent.feedback
    assert planners.LeaderGameAgent.feedback and planners.FollowerGameAgent.feedback


def test_predictions_take_the_same_names(monkeypatch):
    assert prediction.PREDICTIONS is methods.PREDICTIONS
    for name in ("CONSTANT_VELOCITY", "LANE_KEEPING", "ILQR", "FEEDBACK_GAME", "OPEN_LOOP_GAME"):
        assert getattr(prediction, name) == getattr(methods, name)
    assert set(methods.PREDICTIONS) - {methods.CONSTANT_VELOCITY} <= set(planners.AGENTS)
    for name in methods.PREDICTIONS:
        prediction.check_prediction(name)
        assert planners.make_agent(f"ilqr:prediction={name}").prediction == name
    with pytest.raises(ValueError, match="unknown prediction"):
        prediction.check_prediction("feedback")  # a solver mode, not a method's name
    called = _stub_solver(monkeypatch)
    game, x0 = paper_game()
    for name, mode in methods.GAME_MODES.items():
        predictor = prediction.make_predictor(name, game, 0)
        with pytest.raises(RuntimeError):
            predictor(game, x0)
        assert called[-1] == mode


def test_cli_names_are_the_registrys():
    """The command line writes the names out (it does not import JAX to build its parser):
    they must be the registry's, the solver's and the SB3 adapter's."""
    from experiments import cli
    from planners.agents.sb3 import SB3_ALGOS

    assert set(cli.DEMO_AGENTS) <= set(planners.AGENTS)
    parsers = {}

    def walk(parser, path=()):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, path + (name,))
            else:
                parsers[path + (action.dest,)] = action

    walk(cli.build_parser())
    assert parsers[("tournament", "agents")].default is None  # DEMO_AGENTS, unless --lineup names the field
    assert " ".join(cli.DEMO_AGENTS) in parsers[("tournament", "agents")].help
    # the Nash modes (the convergence study has no Stackelberg rows)
    assert set(methods.NASH_MODES) <= set(parsers[("convergence", "modes")].choices)
    assert tuple(parsers[("train", "algo")].choices) == SB3_ALGOS


def test_paper_game_is_the_papers_scene():
    """The scene ``racing paper`` solves (its x0 as experiments.paper has always written it)."""
    import experiments.paper

    assert experiments.paper.paper_game is paper_game and experiments.paper.PAPER_WEIGHTS is PAPER_WEIGHTS
    game, x0 = paper_game()
    np.testing.assert_array_equal(x0, [[15.0, 20.0, 0.0, 0.0, 0.0, 0.0], [5.0, 23.0, 2.0, 0.0, 0.0, 0.0]])
    assert (game.dt, game.horizon, game.num_players) == (0.1, 50, 2)
    assert game.track.length == 400.0 and not game.track.closed
    np.testing.assert_array_equal(game.track.width_left_at(np.array([0.0, 200.0])), [6.0, 6.0])
    np.testing.assert_array_equal(game.track.width_right_at(np.array([0.0, 200.0])), [6.0, 6.0])
    np.testing.assert_array_equal(np.asarray(game.vehicles.v_max), [20.0, 25.0])
    assert float(PAPER_WEIGHTS.r_jx) == float(PAPER_WEIGHTS.r_jy) == 10.0
    for field in vars(PAPER_WEIGHTS):
        np.testing.assert_array_equal(np.asarray(getattr(game.weights, field)),
                                      np.full(2, float(getattr(PAPER_WEIGHTS, field))))
    game2, x0_2 = paper_game(opponent_collision=50.0)
    np.testing.assert_array_equal(x0_2, x0)
    np.testing.assert_array_equal(np.asarray(game2.weights.c_collision), [float(PAPER_WEIGHTS.c_collision), 50.0])
