"""The `racing` command line: demo, agents, tracks, paper, equilibria, tournament, replay, convergence, train, exploit, sweep,
study, bench.

Each command's code is imported only when it runs: the RL layer (:mod:`experiments.rl`, torch
and stable-baselines3) only by ``racing train``. Guide: README.md and docs/.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from typing import Any
from pathlib import Path

# Agent names (planners.methods, the registry planners.AGENTS), solver modes and SB3 algorithms
# are written out here and in the choices below (importing planners loads JAX);
# tests/test_library_surface.py checks them against their definitions.
DEMO_AGENTS = ("ilqr", "ilqgame-ol", "ilqgame-fb", "raceline")  # racing demo's, and racing tournament's by default
# racing_env.config.INCIDENT_MODES, racing_env.scenarios.SCENARIOS and
# experiments.rl.train.TRAINING_STARTS (not imported here: JAX)
INCIDENT_CHOICES = ("penalty", "terminate", "both", "ignore")
SCENARIO_CHOICES = ("grid", "paper", "side_by_side", "anywhere")
START_CHOICES = ("grid", "anywhere", "mixed")
# racing train --envs by --learner (experiments.rl.train.LEARNERS)
DEFAULT_ENVS = {"sb3": 2, "jax": 256}
# experiments.exploit.DEFAULT_TARGETS (not imported here: JAX)
EXPLOIT_TARGETS = ("lane-keeping", "ilqr", "ilqgame-ol", "ilqgame-fb")


def _cmd_demo(args: argparse.Namespace) -> int:
    if args.scripted:
        from experiments.demo import run_demo

        run_demo(Path(args.out), track=args.track, laps=args.laps, race_distance=args.race_distance, seed=args.seed)
        return 0
    from experiments.tournament import TournamentConfig, run_tournament

    config = TournamentConfig(agents=DEMO_AGENTS, track=args.track, laps=args.laps,
                              race_distance=args.race_distance, grids=1, seed=args.seed)
    run_tournament(config, Path(args.out), fresh=True)
    return 0


def _cmd_paper(args: argparse.Namespace) -> int:
    from experiments.paper import run_paper

    run_paper(Path(args.out))
    return 0


def _cmd_equilibria(args: argparse.Namespace) -> int:
    from experiments.equilibria import EquilibriaConfig, run_equilibria

    config = EquilibriaConfig(scene=args.scene, track=args.track, cars=args.cars, jerk_weight=args.jerk_weight,
                              modes=tuple(args.modes), solver=args.solver, starts=args.starts, seed=args.seed,
                              cluster_tolerance=args.cluster_tolerance)
    run_equilibria(config, Path(args.out))
    return 0


def _add_contact_arguments(parser: argparse.ArgumentParser) -> None:
    """``--contact``, ``--penalties``, ``--penalty-seconds``, ``--rules`` (the race's contact
    and steward) and ``--observation-units`` (:class:`experiments.race_spec.RaceSpec`)."""
    from racing_env.contact import CONTACT_MODES
    from racing_env.observation import OBSERVATION_UNITS
    from racing_env.steward import DEFAULT_RULES, PENALTY_MODES, RULES

    parser.add_argument("--contact", default="physics", choices=CONTACT_MODES,
                        help="physics: cars that meet collide (the default); ghost: they drive through each other")
    parser.add_argument("--penalties", default="time", choices=PENALTY_MODES,
                        help="what the steward does to the car that caused a contact incident (docs/rules.md): time "
                        "(the default: --penalty-seconds added to its race time), drive-through, disqualify (at its "
                        "third) or none (verdicts recorded only)")
    parser.add_argument("--penalty-seconds", type=float, default=5.0,
                        help="seconds per incident with --penalties time (default: 5)")
    parser.add_argument("--rules", nargs="+", default=list(DEFAULT_RULES), choices=RULES, metavar="RULE",
                        help=f"the steward's rules, of {', '.join(RULES)} (default: all but the optional weaving)")
    parser.add_argument("--observation-units", default=OBSERVATION_UNITS[0], choices=OBSERVATION_UNITS,
                        help="what the cars' observations are in: scaled (the default, of order one) or physical "
                        "(SI units; what models trained before the choice existed read)")


def _contact_fields(args: argparse.Namespace) -> dict[str, Any]:
    return {"contact": args.contact, "penalties": args.penalties, "penalty_seconds": args.penalty_seconds,
            "rules": tuple(args.rules), "observation_units": args.observation_units}


def _cmd_tournament(args: argparse.Namespace) -> int:
    from experiments.tournament import TournamentConfig, run_tournament
    from planners.agents import split_spec_list

    lineup = None if args.lineup is None else tuple(split_spec_list(args.lineup))
    agents = args.agents if args.agents is not None else [] if lineup is not None else list(DEMO_AGENTS)
    config = TournamentConfig(
        agents=tuple(split_spec_list(agents)), lineup=lineup,
        track=args.track, laps=args.laps, race_distance=args.race_distance, grids=args.grids,
        cars=args.cars, seed=args.seed, versus=args.versus, max_steps=args.max_steps, step_budget_s=args.step_budget,
        enforce_budget=args.enforce_budget,
        on_collision=args.collision, on_off_track=args.off_track, scenario=args.scenario, **_contact_fields(args),
        **({} if args.jerk_weight is None else {"jerk_weight": args.jerk_weight}), car=args.car,
        **_track_scale(args),
    )
    _check_ray(args.backend)
    run_tournament(config, Path(args.out), gif=not args.no_gif, fresh=args.fresh, backend=args.backend,
                   workers=args.workers, address=args.address, plans=args.plans, report=args.report)
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from experiments.replay import print_races, render_race

    run = Path(args.run)
    if not run.is_dir():
        raise ValueError(f"{run} is not a run folder (a tournament's or a sweep's --out)")
    if args.race is None:
        print_races(run)
        return 0
    steps = None
    if args.steps is not None:
        try:
            steps = [int(k) for k in args.steps.split(",") if k.strip()]
        except ValueError:
            raise ValueError(f"--steps takes step indices separated by commas, e.g. 0,20,40; got {args.steps!r}") from None
    suffix = ".png" if steps is not None else ".gif"
    path = Path(args.out) if args.out else run / f"replay-{args.race}{suffix}"
    render_race(run, args.race, path, every=args.every, size=args.size, camera=args.camera, plans=args.plans,
                steps=steps)
    print(f"wrote {path}")
    return 0


def _cmd_tracks(args: argparse.Namespace) -> int:
    from experiments.tracks import plot_track, print_tracks, track_rows

    if args.plot:
        path = plot_track(args.plot, Path(args.out) if args.out else Path("runs/tracks") / f"{args.plot}.png")
        print(f"wrote {path}")
        return 0
    print_tracks(track_rows(lap_limits=args.limits), as_json=args.json)
    return 0


def _cmd_agents(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from planners.agents import AGENT_SUMMARIES, AGENTS, agent_options

    names = [args.name] if args.name else list(AGENTS)
    console = Console(width=max(Console().width, 120))
    for name in names:
        rows = agent_options(name)  # refuses an unknown name, listing the known ones
        table = Table(title=f"{name}: {AGENT_SUMMARIES[name]}", title_justify="left")
        for column in ("option", "type", "default", "meaning"):
            table.add_column(column)
        for row in rows:
            if not args.name and "." in row[0]:
                continue  # prefixed weights (leading., trailing., belief.): explained below, unless asked by name
            table.add_row(*(escape(cell) for cell in row))  # units like "[m]" are text, not markup
        console.print(table)
        if any(row[0].startswith("leading.") for row in rows):
            console.print("  leading.<weight>, trailing.<weight>: that cost weight in re-plans made while the car "
                          "leads, or trails (e.g. trailing.c_collision=1)\n"
                          "  belief.<weight>: the weight this agent believes every other car has (e.g. "
                          "belief.c_collision=100: it expects them to avoid contact at almost any cost)")
    console.print("rl:PATH.zip, rl:ALGO:PATH.zip: a saved stable-baselines3 policy (no options)")
    return 0


def _use_cpu_cores(command: str) -> None:
    """One JAX device per core, so solver batches are split over the cores."""
    from planners.devices import use_cpu_cores

    try:
        use_cpu_cores()  # before any JAX computation
    except RuntimeError as err:  # called in a process where JAX already runs (e.g. a notebook)
        print(f"racing {command}: {err}; the batches use the devices JAX has", file=sys.stderr)


def _cmd_bench(args: argparse.Namespace) -> int:
    _use_cpu_cores("bench")
    from experiments.bench import run_bench

    only = [s for part in (args.only or []) for s in part.split(",") if s]
    report = run_bench(only or None, Path(args.json) if args.json else None)
    print(json.dumps(report, indent=2))
    return 130 if report.get("interrupted") else 0


def _cmd_convergence(args: argparse.Namespace) -> int:
    from experiments.convergence import ConvergenceConfig, parse_solver_option, run_convergence

    other = tuple(parse_solver_option(text) for text in args.solver_option or ())
    config = ConvergenceConfig(tracks=tuple(args.track), cars=tuple(args.cars), scenes=args.scenes, seed=args.seed,
                               spread=args.spread, speed=tuple(args.speed), modes=tuple(args.modes),
                               max_iterations=args.max_iterations, tolerance=args.tolerance,
                               step_control=args.step_control, initial_step=args.initial_step,
                               other_options=other, jerk_weight=args.jerk_weight)
    _use_cpu_cores("convergence")
    report = run_convergence(config, Path(args.out))
    return 130 if report.get("interrupted") else 0


def _cmd_train(args: argparse.Namespace) -> int:
    needed = ("stable_baselines3", "flax", "optax") if args.learner == "jax" else ("stable_baselines3",)
    for module in needed:
        try:
            __import__(module)
        except ImportError:
            raise ValueError(f"racing train --learner {args.learner} needs {module}: "
                             "pip install 'racing-games[rl]'") from None
    if args.vector and not args.subprocesses:  # the vectorised races and the planners' re-plans split over the cores
        _use_cpu_cores("train")
    from experiments.rl.train import TrainConfig, parse_hyperparameter, parse_reward_weight, run_training
    from planners.agents import split_spec_list

    if args.time_trial and args.opponents is not None:
        raise ValueError("--time-trial races the learner alone: give no --opponents")
    opponents = () if args.time_trial else tuple(split_spec_list(args.opponents or ["lane-keeping"]))
    config = TrainConfig(
        opponents=opponents, pool=args.pool, pool_cars=args.pool_cars, algo=args.algo,
        timesteps=args.timesteps, track=args.track, laps=args.laps, race_distance=args.race_distance,
        max_steps=args.max_steps, start=args.start, seed=args.seed, vector=args.vector, learner=args.learner,
        envs=args.envs if args.envs is not None else DEFAULT_ENVS[args.learner],
        subprocesses=args.subprocesses,
        normalize=args.normalize,
        on_off_track=args.off_track, on_collision=args.collision, eval_off_track=args.eval_off_track,
        **_contact_fields(args),
        checkpoint_every=args.checkpoint_every,
        eval_every=args.eval_every, eval_grids=args.eval_grids,
        reward=tuple(parse_reward_weight(text) for text in args.reward or ()), init_model=args.init_model,
        imitate=args.imitate, imitate_episodes=args.imitate_episodes, imitate_noise=args.imitate_noise,
        imitate_spread=args.imitate_spread,
        hyperparameters=tuple(parse_hyperparameter(text) for text in args.hyperparameter or ()),
        **({} if args.jerk_weight is None else {"jerk_weight": args.jerk_weight}), car=args.car,
        **_track_scale(args),
    )
    report = run_training(config, Path(args.out), fresh=args.fresh)
    return 130 if report["status"] == "interrupted" else 0


def _cmd_exploit(args: argparse.Namespace) -> int:
    _check_ray(args.backend)
    if args.backend == "local" and args.workers == 1:  # the trainings run here: their races split over the cores
        _use_cpu_cores("exploit")
    from experiments.exploit import ExploitConfig, run_exploit
    from experiments.rl.train import parse_hyperparameter
    from planners.agents import split_spec_list

    config = ExploitConfig(
        targets=tuple(split_spec_list(args.targets)), seeds=args.seeds, timesteps=args.timesteps,
        learner=args.learner, envs=args.envs, grids=args.grids, eval_every=args.eval_every,
        hyperparameters=tuple(parse_hyperparameter(text) for text in args.hyperparameter or ()),
        track=args.track, laps=args.laps, race_distance=args.race_distance, max_steps=args.max_steps, car=args.car,
        **_track_scale(args),
    )
    report = run_exploit(config, Path(args.out), backend=args.backend, workers=args.workers, address=args.address,
                         fresh=args.fresh)
    return 130 if report["interrupted"] else 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from experiments.sweep import load_sweep, run_sweep, sweep_path

    path = sweep_path(args.file)
    config = load_sweep(path)
    if args.car is not None:
        config = dataclasses.replace(config, car=args.car)
    if args.track_scale is not None:
        config = dataclasses.replace(config, track_scale=args.track_scale)
    _check_ray(args.backend)
    out = Path(args.out) if args.out else Path("runs/sweep") / path.stem
    report = run_sweep(config, out, backend=args.backend, workers=args.workers, address=args.address,
                       fresh=args.fresh, plans=args.plans, report=args.report)
    return 130 if report["interrupted"] else 0


def _cmd_study(args: argparse.Namespace) -> int:
    from experiments.study import load_study, run_study

    path = Path(args.file)
    study = load_study(path)
    _check_ray(args.backend)
    out = Path(args.out) if args.out else Path("runs/study") / study.name
    report = run_study(study, out, backend=args.backend, workers=args.workers, address=args.address, fresh=args.fresh)
    return 130 if report["interrupted"] else 0


def _cmd_study_report(args: argparse.Namespace) -> int:
    import json as json_module

    from experiments.outlook import write_page
    from experiments.study import CONFIG

    run = Path(args.run)
    if not (run / CONFIG).is_file():
        raise ValueError(f"{run} is not a study's run folder (racing study run --out): it has no {CONFIG}")
    study_file = args.study or f"docs/studies/{json_module.loads((run / CONFIG).read_text())['name']}.toml"
    path = write_page(run, Path(args.page), study_file, Path(args.figures) if args.figures else None)
    print(f"wrote {path}" + (f" and its figures in {args.figures}" if args.figures else ""), file=sys.stderr)
    return 0


def _cmd_study_check(args: argparse.Namespace) -> int:
    from experiments.outlook import check_page

    differences = check_page(Path(args.page), Path(args.run))
    for line in differences:
        print(line, file=sys.stderr)
    print(f"{args.page}: " + (f"{len(differences)} line(s) differ from {args.run}" if differences
                              else f"every number matches {args.run}"), file=sys.stderr)
    return 1 if differences else 0


def _cmd_cars(args: argparse.Namespace) -> int:
    from experiments.cars import car_rows, print_cars, write_limits_page
    from racing_env.track import circuit_names

    if args.markdown:
        print(f"wrote {write_limits_page(Path(args.markdown))}")
        return 0
    print_cars(car_rows(circuit_names() if args.all_circuits else None), as_json=args.json)
    return 0


def _track_scale(args: argparse.Namespace) -> dict[str, float]:
    """``track_scale`` of ``--track-scale``, where given."""
    return {} if args.track_scale is None else {"track_scale": args.track_scale}


def _car_option(default: str | None = "paper") -> argparse.ArgumentParser:
    """``--car NAME``: every car's class (racing_env.car_classes)."""
    from racing_env.car_classes import car_names

    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--car", default=default, choices=car_names(), metavar="NAME",
                        help=f"every car's class, one of {', '.join(car_names())}, but an agent's whose spec says "
                        "car=NAME (racing cars lists them; default: "
                        + ("the sweep file's, else paper)" if default is None else f"{default}, the paper's car)"))
    parent.add_argument("--track-scale", type=float, default=None, metavar="K",
                        help="race on a model of the track at scale K, e.g. 0.1 for the 1:10 f1tenth class (its racing "
                        "line, grid and the steward's distances scaled alike; default: "
                        + ("the sweep file's, else 1: full size)" if default is None else "1: full size)"))
    return parent


def _compile_cache_option() -> argparse.ArgumentParser:
    """``--no-compile-cache``, shared by the commands that compile solvers."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument(
        "--no-compile-cache", dest="compile_cache", action="store_false",
        help="do not keep compiled solvers on disk for the next run (default: keep them in "
        "~/.cache/racing-games/jax, or in the folder RACING_COMPILE_CACHE names; RACING_COMPILE_CACHE=off "
        "also turns the cache off)",
    )
    return parent


def _backend_options() -> argparse.ArgumentParser:
    """``--backend``, ``--workers``, ``--address``: where the races of a sweep or a
    tournament run (experiments.backends)."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--backend", choices=["local", "ray"], default="local",
                        help="where races run: local (this process, or --workers processes) or ray (default: local)")
    parent.add_argument("--workers", type=int, default=1,
                        help="worker processes (local) or CPUs of a local Ray instance (default: 1: this process)")
    parent.add_argument("--address", default=None,
                        help="Ray cluster to join, e.g. auto or ray://head:10001 (default: start a local one)")
    return parent


def _recording_options() -> argparse.ArgumentParser:
    """``--plans`` and ``--no-report``, shared by the commands whose races keep replays."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--plans", action="store_true",
                        help="keep each planner's plan and predictions of the others at every step in the replays "
                        "(OUT/replays; about 10x larger files), so racing replay can draw them")
    parent.add_argument("--no-report", dest="report", action="store_false",
                        help="do not write OUT/report.html (the results page with replays of selected races)")
    return parent


def _check_ray(backend: str) -> None:
    if backend == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ValueError("the ray backend needs Ray: pip install 'racing-games[ray]'") from None


def build_parser() -> argparse.ArgumentParser:
    cache = _compile_cache_option()
    car = _car_option()
    backends = _backend_options()
    recording = _recording_options()
    parser = argparse.ArgumentParser(
        prog="racing",
        description="racing-games: race game-theoretic planners (iLQR, open-loop and feedback iLQGame) and "
        "RL agents on point-mass cars.",
        epilog="Each command explains itself: racing COMMAND --help. Guides: README.md; docs/env.md (the race), "
        "docs/agents.md (agent specs), docs/sweeps.md (tournaments, sweeps, Ray), docs/rl.md (training), "
        "docs/solvers.md (paper, convergence), docs/performance.md (bench).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser(
        "demo", parents=[cache],
        help="a short tournament of iLQR, open-loop and feedback iLQGame and the racing-line driver",
        description="A round robin (both starting orders, one start grid) of iLQR, open-loop iLQGame, feedback "
        "iLQGame and the racing-line driver (raceline; on the trefoil it drives the centre line at its limit) over one lap (--laps, --race-distance) of a built-in circuit "
        "(a few minutes, most of it compiling the planners). Prints the leaderboard; writes OUT/results.jsonl, "
        "summary.csv, head_to_head.png, race.gif, report.html and the races' replays. --scripted instead races two scripted cars (seconds). "
        "A fresh run each time; for a resumable one use racing tournament.",
    )
    demo.add_argument("--out", default="runs/demo", help="output folder (default: runs/demo)")
    demo.add_argument("--race-distance", type=float, default=None, help="finish line [m]; overrides --laps (default: a lap)")
    demo.add_argument("--scripted", action="store_true",
                      help="race two scripted cars (--laps or --race-distance; GIF + trajectory plot)")
    demo.add_argument("--track", default="trefoil", help="track name (racing tracks lists them) or TUMFTM CSV path (default: trefoil)")
    demo.add_argument("--laps", type=int, default=1, help="race length in laps (default: 1)")
    demo.add_argument("--seed", type=int, default=0, help="start-grid seed (default: 0)")
    demo.set_defaults(func=_cmd_demo)

    agents = sub.add_parser(
        "agents", help="list the agent specs and the options each accepts (name:option=value,...)",
        description="Agents are named by specs wherever the commands take them (tournament --agents, train "
        "--opponents, a sweep's lineup). A spec is a name with optional options after a colon, comma-separated: "
        "ilqgame-fb:max_iterations=100,replan_every=2. Planners also take their own cost weights (c_collision=1: "
        "private to the agent's plans; the other cars plan with the race's weights for it), weights by race "
        "position (leading.c_collision=10,trailing.c_collision=1) and beliefs about the other cars' weights "
        "(belief.c_collision=100). Any spec takes car=NAME, the class of its car in a lineup (rl:car=NAME:PATH). "
        "This command lists every option with its type and default. Guide: docs/agents.md.",
    )
    agents.add_argument("name", nargs="?", help="one agent (default: all)")
    agents.set_defaults(func=_cmd_agents)

    tracks = sub.add_parser(
        "tracks", help="list the tracks the commands take by name (--plot NAME draws one with its racing line)",
        description="The built-in tracks (straight, trefoil, random) and the real circuits shipped with the package "
        "(the TUMFTM racetrack-database, LGPL-3.0): length, mean and minimum width, corners (stretches of radius "
        "below 100 m), the tightest radius of the centre line, closed or not, whether a racing line is shipped; "
        "--limits adds the lap-time limit of the default car on the racing line and on the centre line (a few "
        "seconds). Any command's --track takes these names in any case (Monza, spa), or a CSV path. Guide: "
        "docs/env.md.",
    )
    tracks.add_argument("--plot", metavar="NAME", default=None,
                        help="draw track NAME with its racing line coloured by the limit's speed (PNG)")
    tracks.add_argument("--out", default=None, help="the PNG of --plot (default: runs/tracks/NAME.png)")
    tracks.add_argument("--limits", action="store_true", help="add the lap-time limits of the default car")
    tracks.add_argument("--json", action="store_true", help="print the table as JSON")
    tracks.set_defaults(func=_cmd_tracks)

    cars = sub.add_parser(
        "cars", help="list the car classes (--car NAME) with their top speed and lap-time limit of Monza",
        description="The car classes every race command takes with --car: the paper's car (the default), TUM's "
        "research car, the Dallara AV-21 of the Indy Autonomous Challenge and the 1:10-scale F1TENTH car, with "
        "their top speed and the lap-time limit (quasi-steady-state flying lap on the racing line) of Monza. "
        "Sources and figures: docs/model.md, 'Car classes'.",
    )
    cars.add_argument("--all-circuits", action="store_true", help="the limits of every shipped circuit (a minute)")
    cars.add_argument("--markdown", metavar="PATH", default=None,
                      help="write the table of every circuit's limit per class as a Markdown page (docs/lap-limits.md)")
    cars.add_argument("--json", action="store_true", help="print the table as JSON")
    cars.set_defaults(func=_cmd_cars)

    paper = sub.add_parser(
        "paper", parents=[cache],
        help="reproduce the paper's figures and claims, certify every solution, map the scene's equilibria "
        "(PNG figures + paper.json)",
        description="Solve the scene of the paper's Figure 1 (two cars on a straight, inputs initialised at zero) "
        "with iLQR, open-loop and feedback iLQGame and the variants of Figure 2 and of the paper's claims, and the "
        "game modes again with the paper's algorithm as printed (exact Hessians, fixed step 0.1), and as a "
        "leader-follower game with each car leading (feedback Stackelberg); certify every "
        "game solution (local Nash equilibrium, saddle or not stationary; local Stackelberg solution) and map the "
        "scene's distinct solutions from 64 starts per mode and solver; write fig1_methods.png, "
        "fig2_collision_weight.png, fig3_convergence.png, fig4_landscape_default.png, fig5_landscape_printed.png, "
        "fig6_stackelberg.png and paper.json (per method: "
        "converged, "
        "iterations, solve time, each car's lateral extent, final gap, minimum distance, first-order Nash "
        "residual, the convergence measure and step size of every iteration). Most of its time is compilation, "
        "which the compilation cache saves on the next run. Guide: docs/experiments/paper.md.")
    paper.add_argument("--out", default="runs/paper", help="output folder (default: runs/paper)")
    paper.set_defaults(func=_cmd_paper)

    equilibria = sub.add_parser(
        "equilibria", parents=[cache],
        help="the equilibrium landscape of a scene: multi-start solves, clustered and certified as local Nash "
        "equilibrium or saddle (table, JSON, PNG)",
        description="Solve one scene from --starts initial input sequences per solver mode (zero inputs, lane-change "
        "pulses of every combination of cars, then seeded random inputs), as one batch; group the converged "
        "solutions that agree within --cluster-tolerance, and certify each distinct solution as a local Nash "
        "equilibrium, a saddle (some player gains by deviating alone) or not stationary, with the numbers behind "
        "it (own-input Hessian eigenvalues, best-response gains). Writes OUT/equilibria.json (after each mode) and "
        "OUT/equilibria.png (every distinct solution in the s-n plane with its share of the starts and its "
        "verdict). Guide: docs/solvers.md (Equilibrium landscapes).")
    equilibria.add_argument("--scene", choices=["paper", "grid", "side_by_side"], default="paper",
                            help="paper: the paper's overtaking scene (default); grid, side_by_side: --cars cars "
                            "on --track")
    equilibria.add_argument("--track", default="trefoil", help="track name or TUMFTM CSV path for grid and "
                            "side_by_side (default: trefoil)")
    equilibria.add_argument("--cars", type=int, default=2, help="cars in grid and side_by_side scenes (default: 2)")
    equilibria.add_argument("--jerk-weight", type=float, default=None,
                            help="every car's jerk weight r for grid and side_by_side (default: CostWeights' 1)")
    equilibria.add_argument("--modes", nargs="+", choices=["open_loop", "feedback"], default=["open_loop", "feedback"],
                            help="solver modes (default: open_loop feedback)")
    equilibria.add_argument("--solver", choices=["default", "paper"], default="default",
                            help="default: the solver's defaults; paper: the paper's algorithm as printed (exact "
                            "Hessians, fixed step 0.1, up to 1000 iterations)")
    equilibria.add_argument("--starts", type=int, default=64, help="initial guesses per mode (default: 64)")
    equilibria.add_argument("--seed", type=int, default=0, help="seed of the random guesses (default: 0)")
    equilibria.add_argument("--cluster-tolerance", type=float, default=0.05,
                            help="solutions whose trajectories agree within this much in every state entry are one "
                            "(state units: m, m/s, rad; default: 0.05)")
    equilibria.add_argument("--out", default="runs/equilibria", help="output folder (default: runs/equilibria)")
    equilibria.set_defaults(func=_cmd_equilibria)

    tour = sub.add_parser(
        "tournament", parents=[car, cache, backends, recording],
        help="round robin of agents over seeded start grids (resumable; leaderboard, report.html, replays)",
        description="Every combination of --cars agents races on --grids start grids, once per rotation of "
        "the starting slots (with more --cars than agents, or a --lineup: one field per grid). Results are appended to OUT/results.jsonl as races end, every race's replay to "
        "OUT/replays; rerunning the same command resumes. Races run here, on --workers local processes, or on "
        "Ray (--backend ray); the leaderboard is the same. Prints the leaderboard; writes OUT/summary.csv, "
        "leaderboard.json, head_to_head.png, race.gif (the first race, with the planners' plans) and "
        "report.html (open it in a browser). Agent specs: racing agents; guide: docs/sweeps.md.",
    )
    tour.add_argument("--agents", nargs="+", default=None,
                      help="agent specs (space- or comma-separated; default: " + " ".join(DEMO_AGENTS) + ")")
    tour.add_argument("--lineup", nargs="+", default=None, metavar="SPEC[*K]",
                      help="race this field on every grid instead of a round robin: the specs of its cars, SPEC*K "
                      "for K cars of a spec, e.g. \"ilqgame-fb*4,ilqr*3,lane-keeping*3\" (at most 20 cars); the "
                      "cars are shuffled over the slots per grid; --agents may be left out, --cars too")
    tour.add_argument("--track", default="trefoil", help="track name (racing tracks lists them) or TUMFTM CSV path (default: trefoil)")
    tour.add_argument("--laps", type=int, default=1, help="laps on closed tracks (default: 1)")
    tour.add_argument("--race-distance", type=float, default=None, help="finish line [m]; overrides --laps")
    tour.add_argument("--grids", type=int, default=2, help="seeded start grids per pairing (default: 2)")
    tour.add_argument("--versus", default=None, metavar="SPEC",
                      help="race every other agent against this one only (a gauntlet), not a full round robin; "
                           "one of --agents (name in any case, options in any order)")
    tour.add_argument("--cars", type=int, default=None,
                      help="cars per race (default: 2, or the size of --lineup; at most 20); 1: a time trial, each "
                      "agent alone on every grid, ranked by mean finish time; more than the agents: one field per "
                      "grid, every agent a fair share of the cars, shuffled over the slots, rated by its cars' places")
    tour.add_argument("--seed", type=int, default=0, help="tournament seed: it seeds the start grids (default: 0)")
    tour.add_argument("--max-steps", type=int, default=3000,
                      help="truncate races after this many steps of 0.1 s (default: 3000)")
    tour.add_argument("--step-budget", type=float, default=None, metavar="SECONDS",
                      help="report the actions of each agent slower than this [s] (counted per car, printed after the "
                      "leaderboard); the races go on as without it (default: no budget: a busy machine never "
                      "decides a race)")
    tour.add_argument("--enforce-budget", action="store_true",
                      help="with --step-budget: an action slower than the budget (the first of a race exempt) loses "
                      "the race, which stops there")
    tour.add_argument("--jerk-weight", type=float, default=None,
                      help="every car's jerk weight r (R = r I) in the race's game, which the planners plan with "
                      "(default: 0.01, racing_env.costs.RACING_JERK_WEIGHT, the env's own default for races; "
                      "CostWeights' default 1 is for single solves; scaled by (30 / jerk limit)^2 for a --car whose "
                      "jerk limits are not 30 m/s^3)")
    tour.add_argument("--scenario", default="grid", choices=SCENARIO_CHOICES,
                      help="the start: grid (a seeded rolling grid per --grids, the default), paper (the paper's "
                      "overtaking scene: the first slot's car, v_max 20 m/s, 10 m ahead of the second, v_max 25 m/s, "
                      "2 m to its left; each pair races once each way round), side_by_side (these two need "
                      "--cars 2 --grids 1) or anywhere (per --grids a seeded close-quarters scene anywhere on the "
                      "lap, cars up to 15 m apart at 5-19 m/s, at least 100 m before the finish)")
    tour.add_argument("--collision", default="penalty", choices=INCIDENT_CHOICES,
                      help="what contact does: penalty (counted, the default) or ignore (counted too: the two "
                      "differ only in the env's reward, which tournaments do not use), terminate or both (the cars "
                      "in contact retire and place behind every finisher, by distance)")
    tour.add_argument("--off-track", default="penalty", choices=INCIDENT_CHOICES,
                      help="what leaving the track does, as for --collision (default: penalty)")
    _add_contact_arguments(tour)
    tour.add_argument("--out", default="runs/tournament", help="output folder (default: runs/tournament)")
    tour.add_argument("--no-gif", action="store_true", help="do not render a GIF of the first race")
    tour.add_argument("--fresh", action="store_true", help="discard earlier results in --out and start over")
    tour.set_defaults(func=_cmd_tournament)

    replay = sub.add_parser(
        "replay", help="draw a recorded race of a tournament or sweep again, to a GIF or MP4",
        description="Tournaments and sweeps keep every race's replay in OUT/replays. Without --race, lists the "
        "recorded races of RUN (index, id, order, steps, whether plans were kept). With --race K, renders race "
        "K with the follow camera, the agents' names, a heads-up line and (when the run kept them with --plans) "
        "each planner's plan and predictions. Guide: docs/viewing.md.",
    )
    replay.add_argument("run", metavar="RUN", help="a tournament's or a sweep's output folder")
    replay.add_argument("--race", type=int, default=None, metavar="K",
                        help="the race to render: its index in the run's schedule (racing replay RUN lists them)")
    replay.add_argument("--out", default=None,
                        help="the file to write: .gif or .mp4 (MP4 needs the video extra), or .png with --steps "
                        "(default: RUN/replay-K.gif, or RUN/replay-K.png with --steps)")
    replay.add_argument("--steps", default=None, metavar="K,K,...",
                        help="instead of a video, the frames of these steps side by side in one PNG (a figure)")
    replay.add_argument("--every", type=int, default=3,
                        help="draw every this many steps of 0.1 s (default: 3; the video plays in race time)")
    replay.add_argument("--size", type=int, default=480, help="frame side [px] (default: 480)")
    replay.add_argument("--camera", default="auto", choices=["auto", "follow", "track"],
                        help="follow: a window that keeps the cars large, with an inset map; track: the whole "
                        "circuit; auto (default): follow for up to 4 cars")
    replay.add_argument("--no-plans", dest="plans", action="store_false",
                        help="do not draw the plans and predictions even when the replay has them")
    replay.set_defaults(func=_cmd_replay)

    conv = sub.add_parser(
        "convergence", parents=[cache],
        help="how often the game solvers converge from random close-quarters starts (table, JSON, PNG)",
        description="Per track and number of cars, draw --scenes seeded random close-quarters starts anywhere on "
        "the track (cars up to --spread apart, at --speed, not in contact) and solve them cold, as one batch per "
        "solver mode. Reports the converged fraction, the other outcomes, the iterations of the converged "
        "solves and, in open loop, how near an equilibrium every solve ended (its first-order Nash residual); "
        "writes OUT/convergence.json (after every row: Ctrl-C keeps what was measured) and "
        "OUT/convergence.png (fraction converged within k iterations). Guides: docs/solvers.md, "
        "docs/experiments/convergence.md.",
    )
    conv.add_argument("--track", nargs="+", default=["trefoil"],
                      help="built-in track names or TUMFTM CSV paths (default: trefoil)")
    conv.add_argument("--cars", nargs="+", type=int, default=[2], help="numbers of cars per scene (default: 2)")
    conv.add_argument("--scenes", type=int, default=64, help="random starts per track and number of cars (default: 64)")
    conv.add_argument("--seed", type=int, default=0, help="seed of the random starts (default: 0)")
    conv.add_argument("--spread", type=float, default=15.0,
                      help="the cars start up to this far apart along the track [m] (default: 15)")
    conv.add_argument("--speed", type=float, nargs=2, default=[10.0, 19.0], metavar=("LO", "HI"),
                      help="range of the start speeds [m/s], capped at 95%% of each car's v_max (default: 10 19)")
    conv.add_argument("--modes", nargs="+", default=["feedback", "open_loop"],
                      choices=["feedback", "open_loop", "open_loop_from_feedback"],
                      help="solver modes (default: feedback open_loop); open_loop_from_feedback starts open loop "
                      "from the feedback solution of the same scene and reports that second solve")
    conv.add_argument("--max-iterations", type=int, default=100, help="the solver's iteration cap (default: 100)")
    conv.add_argument("--tolerance", type=float, default=1e-6,
                      help="convergence when a full step moves the trajectory by at most this much (state units; "
                      "default: the solver's 1e-6; the agents re-plan with 1e-3)")
    conv.add_argument("--step-control", choices=["trust_region", "residual", "none"], default="trust_region",
                      help="the solver's step-size control: trust_region (default), residual (also "
                      "backtrack until the open-loop Nash residual decreases; with --modes open_loop) or "
                      "none, a fixed step --initial-step (the paper's plain update)")
    conv.add_argument("--initial-step", type=float, default=1.0, metavar="ETA",
                      help="step size eta tried first (trust_region, residual) or always (none), in (0, 1] "
                      "(default: 1)")
    conv.add_argument("--solver-option", action="append", metavar="NAME=VALUE",
                      help="any further planners.ilq.SolverOptions field, e.g. trust_radius=10 or "
                      "oscillation_damping=false (repeatable)")
    conv.add_argument("--jerk-weight", type=float, default=None,
                      help="every car's jerk weight r (default: CostWeights' default 1, the solver's for single "
                      "solves; races use 0.01, racing_env.costs.RACING_JERK_WEIGHT)")
    conv.add_argument("--out", default="runs/convergence", help="output folder (default: runs/convergence)")
    conv.set_defaults(func=_cmd_convergence)

    train = sub.add_parser(
        "train", parents=[car, cache],
        help="train an RL agent (stable-baselines3, or PPO in JAX with --learner jax) against planner or scripted opponents (resumable)",
        description="Train an SB3 policy (MlpPolicy) to drive one car against --opponents (or alone: "
        "--time-trial) on seeded rolling grids, "
        "--envs copies of the race side by side (the learner a different car in each). Every --eval-every "
        "steps the policy is raced against the opponents under tournament rules (each starting slot, --eval-grids "
        "grids). Writes OUT/model.zip (race it with: racing tournament --agents rl:OUT/model.zip ...), "
        "checkpoints, episodes.jsonl, evaluations.jsonl, learning_curve.png and train.json. Ctrl-C saves a "
        "checkpoint; the same command resumes, and a larger --timesteps trains further. Needs the rl extra "
        "(pip install 'racing-games[rl]'). Guide: docs/rl.md.",
    )
    train.add_argument("--opponents", nargs="+", default=None,
                       help="agent specs of the other cars (default: lane-keeping); e.g. ilqgame-fb, ilqr, "
                       "rl:PATH.zip; with --pool, the drivers to draw from")
    train.add_argument("--time-trial", action="store_true",
                       help="race the learner alone (no opponents; evaluations report its finish time); charge "
                       "for time with --reward time=-1")
    train.add_argument("--pool", action="store_true",
                       help="every episode, draw each opponent car's driver at random from --opponents (a spec "
                       "given twice is drawn twice as often); evaluations race each of them in turn")
    train.add_argument("--pool-cars", type=int, default=2, help="cars per race with --pool (default: 2)")
    train.add_argument("--algo", default="ppo", choices=["ppo", "sac", "td3", "a2c", "ddpg"],
                       help="stable-baselines3 algorithm (default: ppo)")
    train.add_argument("--timesteps", type=int, default=200_000, help="environment steps in all (default: 200000)")
    train.add_argument("--track", default="trefoil", help="track name (racing tracks lists them) or TUMFTM CSV path (default: trefoil)")
    train.add_argument("--laps", type=int, default=1, help="laps per episode on closed tracks (default: 1)")
    train.add_argument("--race-distance", type=float, default=None, help="finish line [m]; overrides --laps")
    train.add_argument("--max-steps", type=int, default=3000,
                       help="truncate episodes after this many steps of 0.1 s (default: 3000)")
    train.add_argument("--start", default="grid", choices=START_CHOICES,
                       help="where training episodes start: grid (a rolling grid behind the line, the default) or "
                       "anywhere (a seeded close-quarters scene anywhere on the lap, racing to the same finish line, "
                       "so that on a long circuit the policy meets every corner early) or mixed (the even copies of "
                       "--envs on the grid, the odd ones anywhere); evaluations start on the grid")
    train.add_argument("--seed", type=int, default=0, help="seed of the policy and the start grids (default: 0)")
    train.add_argument("--learner", default="sb3", choices=["sb3", "jax"],
                       help="sb3 (default): stable-baselines3, every --algo. jax: PPO in JAX, the model in "
                       "OUT/model.npz (raced as rl:OUT/model.npz); against opponents that are JAX functions of the "
                       "state (lane-keeping, constant-speed, a time trial) from the grid, the races and the updates "
                       "are one compiled program (tens of thousands of steps/s), against planners the races step "
                       "from Python with batched re-plans. Same outputs, evaluations and resumption as sb3; "
                       "--hyperparameter takes PPO's names (n_steps, batch_size, n_epochs, learning_rate, ...)")
    train.add_argument("--envs", type=int, default=None,
                       help="copies of the race stepped side by side; in copy k the learner drives car k mod cars "
                       "(default: 2, or 256 with --learner jax; with --vector, 16 to 256 copies train 3 to 6 times "
                       "as many steps per second). "
                       "PPO's defaults follow it: n_steps = 4096/envs (a multiple of 8, 16 to 2048) and batch_size "
                       "= n_steps*envs/8, so an update trains on about 4096 steps in 8 minibatches whatever --envs "
                       "is; --hyperparameter n_steps=... or batch_size=... win")
    train.add_argument("--vector", action=argparse.BooleanOptionalAction, default=True,
                       help="--vector (default): step the copies as vectorised races, all copies of a learner car "
                       "and start in one compiled call with batched opponents: use it, with many --envs, "
                       "wherever it runs. --no-vector: one Gymnasium env per copy (SB3's DummyVecEnv), as "
                       "slow as --envs single races: for an opponent the batched form cannot drive, or to "
                       "compare the two. Both race the same episodes (to rounding; a --pool draws its drivers "
                       "differently); only --vector runs (PPO, A2C) resume exactly where Ctrl-C stopped them")
    train.add_argument("--subprocesses", action="store_true",
                       help="step each copy of the race as a Gymnasium env in a worker process of its own "
                       "(implies --no-vector): for planner opponents the vectorised races cannot batch, whose "
                       "solves then use every core (same results as in one process)")
    train.add_argument("--no-normalize", dest="normalize", action="store_false",
                       help="do not normalise observations and rewards (VecNormalize)")
    train.add_argument("--off-track", default="terminate", choices=INCIDENT_CHOICES,
                       help="what leaving the track does in training (default: terminate the episode)")
    train.add_argument("--eval-off-track", default=None, choices=INCIDENT_CHOICES,
                       help="what leaving the track does in the evaluations (default: the tournaments' rule, "
                       "counted but not ending the race; terminate retires a learner that leaves the track)")
    train.add_argument("--collision", default="penalty", choices=INCIDENT_CHOICES,
                       help="what contact does to the learner's reward in training (default: penalty: the reward's "
                       "fault and collision terms)")
    _add_contact_arguments(train)
    train.add_argument("--jerk-weight", type=float, default=None,
                       help="every car's jerk weight r in the race's game, which planner opponents plan with "
                       "(default: 0.01, racing_env.costs.RACING_JERK_WEIGHT, as in tournaments and sweeps)")
    train.add_argument("--checkpoint-every", type=int, default=20_000, help="steps between checkpoints (default: 20000)")
    train.add_argument("--eval-every", type=int, default=50_000,
                       help="steps between evaluations (default: 50000; 0: only at the end)")
    train.add_argument("--eval-grids", type=int, default=2,
                       help="start grids per evaluation, each raced from every slot (default: 2)")
    train.add_argument("--reward", action="append", metavar="TERM=WEIGHT",
                       help="a reward weight of the training race (repeatable): progress (per metre, default 0.1), "
                       "position (per step, times (cars behind - cars ahead)/(N-1), default 0), collision (per step "
                       "in contact, 0), fault (per incident the steward finds the learner caused, -10), off_track (per step, -1), finish (times (N - place)/(N - 1), 10), lead (per "
                       "metre gained on the lead over the furthest rival, 0; sums to the lead at the line minus the "
                       "lead at the start), time (per second raced, 0; e.g. -1 charges for time: over a finished "
                       "race it sums to the weight times the finish time)")
    train.add_argument("--hyperparameter", action="append", metavar="NAME=VALUE",
                       help="a keyword argument of the algorithm, e.g. n_steps=1024 or learning_rate=1e-4 "
                       "(repeatable; values are Python literals)")
    train.add_argument("--init-model", default=None, metavar="PATH.zip",
                       help="train this saved model further (same --algo; its VecNormalize statistics come "
                       "along), e.g. one trained against the lane keeper before a planner. A model of fewer cars (a --time-trial "
                       "one) gets zero weights on the new cars' features, so it starts out driving as it did; "
                       "their normalisation statistics are measured over 2,048 steps of the new race first")
    train.add_argument("--imitate", default=None, metavar="SPEC",
                       help="before training, clone a fresh policy from this agent's driving (e.g. ilqr): it drives "
                       "the learner's car for --imitate-episodes seeded episodes of the training race; the policy, "
                       "its value and the normaliser are fitted to them, and the clone (imitation.zip) is evaluated "
                       "at 0 steps. PPO and A2C; not with --init-model. Fine-tune a clone with a learning rate "
                       "below PPO's default (e.g. --hyperparameter learning_rate=3e-5), which can undo it: "
                       "docs/rl.md")
    train.add_argument("--imitate-episodes", type=int, default=20,
                       help="the expert's episodes for --imitate (default: 20)")
    train.add_argument("--imitate-noise", type=float, default=0.2,
                       help="standard deviation of the noise added to the expert's actions (normalised, in [-1, 1]) "
                       "while it drives for --imitate, so that the demonstrations show it recovering (default: 0.2; "
                       "0: its own line only)")
    train.add_argument("--imitate-spread", type=float, default=None,
                       help="the cloned policy's standard deviation per action (normalised), which training "
                       "explores with (default: --imitate-noise; with no noise, PPO's initial 1.0)")
    train.add_argument("--out", default="runs/train", help="output folder (default: runs/train)")
    train.add_argument("--fresh", action="store_true", help="discard an earlier run in --out and start over")
    train.set_defaults(func=_cmd_train)

    exploit = sub.add_parser(
        "exploit", parents=[car, cache, backends],
        help="exploitability: train best responses against agents and race them against every agent (resumable)",
        description="For every target agent, train a best response per seed (--seeds) with a budget of --timesteps "
        "steps (racing train against the target alone), then race each best response against its own target and "
        "every other target (cross-play), two cars, from both starting slots on --grids seeded grids, the same "
        "grids for every best response. Prints and writes (OUT/exploit.json) each target's exploitability: its "
        "best responses' win rate against it with a 95% Wilson interval (races pooled over seeds and grids) and a "
        "95% t interval over the seeds' win rates, and their mean finish margin [s] with a t interval; the "
        "cross-play matrix as cross_play.csv and cross_play.png; learning_curves.png; every training in "
        "OUT/best-responses/<target>/seed-<k> (training.jsonl lists them) and every race in results.jsonl, with "
        "its replay in OUT/replays. A training that fails is reported and its best response left out; a car that "
        "raises loses its race. Ctrl-C keeps what is done; the same command resumes (trainings from their last "
        "checkpoint, skipping recorded races); --fresh starts over.",
    )
    exploit.add_argument("--targets", nargs="+", default=list(EXPLOIT_TARGETS), metavar="SPEC",
                         help="agent specs to train best responses against (default: "
                         f"{' '.join(EXPLOIT_TARGETS)}); options allowed, e.g. ilqgame-fb:replan_every=5, rl:PATH")
    exploit.add_argument("--seeds", type=int, default=3, help="best responses per target, seeds 0.. (default: 3)")
    exploit.add_argument("--timesteps", type=int, default=200_000,
                         help="environment steps each best response trains for (default: 200000)")
    exploit.add_argument("--learner", choices=["jax", "sb3"], default=None,
                         help="jax (the JAX PPO) or sb3 (stable-baselines3 PPO) (default: jax where installed, else "
                         "sb3)")
    exploit.add_argument("--envs", type=int, default=None,
                         help="copies of the training race stepped side by side (default: 256 with jax, 16 with sb3)")
    exploit.add_argument("--grids", type=int, default=2,
                         help="seeded start grids of the cross-play and of each training's evaluations, each raced "
                         "from both slots (default: 2)")
    exploit.add_argument("--eval-every", type=int, default=0,
                         help="steps between a training's evaluations (default: 0: only the final one)")
    exploit.add_argument("--track", default="trefoil", help="track name (racing tracks lists them) or TUMFTM CSV path (default: trefoil)")
    exploit.add_argument("--laps", type=int, default=1, help="laps per race on closed tracks (default: 1)")
    exploit.add_argument("--race-distance", type=float, default=None, help="finish line [m]; overrides --laps")
    exploit.add_argument("--max-steps", type=int, default=3000,
                         help="a race (and a training episode) is truncated after this many steps (default: 3000)")
    exploit.add_argument("--hp", "--hyperparameter", dest="hyperparameter", action="append", metavar="NAME=VALUE",
                         help="a setting of the learner (repeatable), as racing train --hyperparameter, e.g. "
                         "n_steps=256")
    exploit.add_argument("--out", default="runs/exploit", help="output folder (default: runs/exploit)")
    exploit.add_argument("--fresh", action="store_true",
                         help="discard an earlier study in --out (trainings and races) and start over")
    exploit.set_defaults(func=_cmd_exploit)

    sweep = sub.add_parser(
        "sweep", parents=[cache, backends, recording, _car_option(None)],
        help="races over a grid of settings from a TOML file, on local worker processes or a Ray cluster",
        description="Race a lineup of agents at every combination of the parameters in a TOML file (its keys: "
        "docs/sweeps.md), or in an example sweep shipped with the package, named by FILE (e.g. aggression; an "
        "unknown name lists them), on --grids seeded grids per point, once per rotation "
        "of the starting slots (a lineup with counts, \"SPEC*K\" for K cars: one field per grid). Records go to OUT/results.jsonl as races end; rerunning the same command resumes. "
        "Prints a table per point and agent; writes summary.csv, summary.json, sweep.png, report.html and every "
        "race's replay (OUT/replays, for racing replay). Backends: local "
        "(--workers processes; 1 runs in this process) or ray (--address of a running cluster, or a local one "
        "with --workers CPUs).",
    )
    sweep.add_argument("file", metavar="FILE", help="the sweep's TOML file, or the name of an example sweep")
    sweep.add_argument("--out", default=None, help="output folder (default: runs/sweep/<file or example name>)")
    sweep.add_argument("--fresh", action="store_true", help="discard earlier results in --out and start over")
    sweep.set_defaults(func=_cmd_sweep)

    study = sub.add_parser(
        "study", help="a declared study of several sweeps raced as one resumable run, its page and the page's check",
        description="A study is a TOML file of named parts, each a sweep (docs/sweeps.md#studies). "
        "racing study run races every part's races as one run: records go to OUT/results.jsonl as races end, one "
        "progress bar with the time left covers the whole study, rerunning the same command resumes it. "
        "racing study report writes its page from the run folder; racing study check compares a page with it.",
    )
    study_commands = study.add_subparsers(dest="study_command", metavar="SUBCOMMAND", required=True)
    study_run = study_commands.add_parser(
        "run", parents=[cache, backends], help="race (or resume) a study",
        description="Race every race of the study's parts (resumable), here, on --workers local processes or on "
        "Ray; writes OUT/results.jsonl, OUT/study.json (its settings), OUT/summary.json (each part's summary) and "
        "every race's replay (OUT/replays, for racing replay).",
    )
    study_run.add_argument("file", metavar="FILE", help="the study's TOML file, e.g. docs/studies/outlook.toml")
    study_run.add_argument("--out", default=None, help="output folder (default: runs/study/<the study's name>)")
    study_run.add_argument("--fresh", action="store_true", help="discard earlier races in --out and start over")
    study_run.set_defaults(func=_cmd_study)
    study_report = study_commands.add_parser(
        "report", help="write a study's page from its run folder",
        description="Write the page of a study of the paper's outlook (experiments.outlook: its parts named duel-*, "
        "fields, place-*) from its run folder: per agent and car class, head to head, every claim with its "
        "interval and verdict, fields and place-switched weights; with --figures, the win-rate matrix, the "
        "margins' distributions and, from the replays, a map per car class of where on each circuit the duels' "
        "passes happened, as PNGs.",
    )
    study_report.add_argument("run", metavar="RUN", help="the study's run folder (racing study run --out)")
    study_report.add_argument("--page", required=True, help="the Markdown page to write (e.g. outlook.md in docs/experiments)")
    study_report.add_argument("--figures", default=None, help="folder of the figures (default: none drawn)")
    study_report.add_argument("--study", default=None,
                              help="how the page names the study's file (default: docs/studies/<its name>.toml)")
    study_report.set_defaults(func=_cmd_study_report)
    study_check = study_commands.add_parser(
        "check", help="check every number of a study's page against its run folder",
        description="Compute the page again from RUN and compare it line by line with PAGE; exit status 1 and the "
        "differing lines if any number differs.",
    )
    study_check.add_argument("page", metavar="PAGE", help="a page written by racing study report")
    study_check.add_argument("--run", required=True, help="the run folder the page was written from")
    study_check.set_defaults(func=_cmd_study_check)

    bench = sub.add_parser(
        "bench", help="performance figures as JSON (stdout) and a table (stderr)",
        description="Performance figures as JSON (stdout) and a table (stderr). It does not use the on-disk "
        "compilation cache, so its compile times are real compilations (unless JAX_COMPILATION_CACHE_DIR is set; "
        "the report names the cache in use). Each row is printed as soon as it is measured; with --json the file "
        "is rewritten after every row, and Ctrl-C stops the run, keeps the rows measured so far (marked "
        '"interrupted": true) and exits with status 130. Sections: env, solvers, agents, rl, certificates, render (the JSON records each '
        "section's seconds). Guide: docs/performance.md.",
    )
    bench.add_argument("--only", action="append", help="section(s) to run, e.g. --only env (repeatable or comma-separated)")
    bench.add_argument("--json", help="also write the JSON report to this file")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``racing`` command ``argv`` (default: the process's arguments); returns its
    exit status.

    A command starts with :func:`racing_env.xla_setup.configure_for_racing` (float64, the
    solvers' loop kernels, inline dispatch), before any JAX computation: importing the
    packages sets none of it. ``--help`` and parse errors end before that.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()
    try:
        if getattr(args, "compile_cache", False):
            from planners.compile_cache import enable_compile_cache

            enable_compile_cache()
        return args.func(args)
    except (ValueError, KeyError) as err:
        print(f"racing {args.command}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a missing file, a folder given as a file, --out naming a file, ...
        where = f"{err.filename}: " if err.filename is not None else ""
        print(f"racing {args.command}: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2


def console_main() -> None:
    """The ``racing`` executable: :func:`main`, ending at once with status 130 on Ctrl-C.

    An interrupt can arrive while XLA compiles in native code, and a normal interpreter
    shutdown after that can crash in XLA's teardown (a SIGSEGV after an interrupted
    ``racing bench``). What the commands keep on interruption is written
    before they return, so after one the process flushes its output and exits directly;
    atexit handlers do not run, so a command that starts workers (e.g. a local Ray
    cluster) must stop them itself on KeyboardInterrupt.
    """
    try:
        code = main()
    except KeyboardInterrupt:
        print("racing: interrupted", file=sys.stderr)
        code = 130
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    sys.exit(code)


if __name__ == "__main__":
    console_main()
