"""The pieces both learners share, stable-baselines3 (:mod:`experiments.rl.train`) and PPO in
JAX (:mod:`experiments.rl.train_jax`): the vectorised training race
(:func:`make_vector_env`), the run folder's records (episodes, evaluations, the resumption
check) and the end of a run (:func:`finish_report`: ``train.json``, the learning curve).

It sits below both learners and imports neither; its names are importable from
:mod:`experiments.rl.train` too.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from experiments.files import replace_atomically, write_json_atomically
from experiments.jsonl import append_jsonl, read_jsonl
from experiments.rl.config import ADDED_LATER, CONFIG, EPISODES, EVALUATIONS, RESUMABLE_CHANGES, TrainConfig, config_json
from experiments.rl.evaluation import evaluate, evaluation_line, plot_learning_curve


def make_vector_env(config: TrainConfig):
    """The ``config.envs`` copies of the training race as one
    :class:`experiments.rl.vec_env.RaceVecEnv`: copy ``k`` races the learner as car
    ``k % N`` from the scenario :meth:`TrainConfig.scenario` gives it, against the opponent
    specs (with ``pool``, every opponent car draws from all of them)."""
    from experiments.rl.vec_env import RaceVecEnv

    specs = list(config.opponents)
    opponents = [specs for _ in range(config.cars - 1)] if config.pool else specs
    races = [(k % config.cars, config.race_config(copy=k)) for k in range(config.envs)]
    return RaceVecEnv(races, opponents)


def drop_episodes_after(out: Path, timesteps: int) -> None:
    """Forget the episodes logged after ``timesteps``: their steps will be collected again."""
    if not (out / EPISODES).exists():
        return
    kept = [e for e in read_jsonl(out / EPISODES) if e["timesteps"] <= timesteps]
    replace_atomically(lambda tmp: tmp.write_text("".join(json.dumps(e) + "\n" for e in kept)), out / EPISODES)


def episode_fields(info: dict[str, Any]) -> dict[str, Any]:
    """An ``episodes.jsonl`` line's fields from the info of the step that ended the episode
    (with the ``episode`` record of :class:`experiments.rl.vec_env.RaceVecEnv` or SB3's
    ``Monitor``): return, length [steps], finished, place, out, finish time [s],
    truncated, and a pool's drawn ``opponents``."""
    episode = info["episode"]
    return {"return": float(episode["r"]), "length": int(episode["l"]), "finished": bool(episode["finished"]),
            "place": int(episode["position"]), "out": bool(episode["out"]), "finish_time": episode["finish_time"],
            "truncated": bool(info.get("TimeLimit.truncated", False)),
            **({"opponents": info["opponents"]} if "opponents" in info else {})}


def record_evaluation(config: TrainConfig, model_path: Path, timesteps: int, out: Path, console) -> None:
    """Race the saved policy under tournament rules (:func:`evaluate`), append the record to
    ``evaluations.jsonl`` and print its line."""
    record = evaluate(config, model_path, timesteps)
    append_jsonl(out / EVALUATIONS, record)
    console.print(evaluation_line(record))


def evaluate_final(config: TrainConfig, model_path: Path, timesteps: int, out: Path, console) -> None:
    """The final policy's evaluation, unless the last one logged is already of ``timesteps``."""
    evaluations = read_jsonl(out / EVALUATIONS)
    if not evaluations or evaluations[-1]["timesteps"] != timesteps:
        record_evaluation(config, model_path, timesteps, out, console)


def finish_report(config: TrainConfig, out: Path, report: dict[str, Any], model_path: Path, title: str,
                  console) -> None:
    """Close a run: its final evaluation into ``report``, ``train.json``, the learning curve
    (titled ``title``) and, for a completed run, how to race the model."""
    evaluations = read_jsonl(out / EVALUATIONS)
    report["final_evaluation"] = evaluations[-1] if evaluations else None
    write_json_atomically(report, out / CONFIG)
    plot_learning_curve(read_jsonl(out / EPISODES), evaluations, out / "learning_curve.png",
                        title=f"{title} {config.description()} on {Path(config.track).stem}",
                        time_trial=config.time_trial)
    if report["status"] == "completed":
        # a time-trial policy observes one car: it races alone, against others' laps
        race_it = ("--cars 1 --agents rl:{} ilqr lane-keeping" if config.time_trial
                   else "--agents rl:{} " + " ".join(dict.fromkeys(config.opponents))).format(model_path)
        console.print(f"wrote {model_path} (race it: racing tournament {race_it}), "
                      f"{out / 'learning_curve.png'}, {out / EVALUATIONS}")


def next_multiple(steps: int, every: int) -> int | None:
    """The first multiple of ``every`` after ``steps`` (None for ``every == 0``: never)."""
    return None if every == 0 else (steps // every + 1) * every


def check_resumable(config: TrainConfig, out: Path, has_checkpoint: bool) -> None:
    """Refuse to train into ``out`` when it holds a run (a checkpoint or episodes) made with
    settings other than ``config``'s (besides those a resumption may change)."""
    config_path = out / CONFIG
    if not config_path.exists():
        return
    wanted = config_json(config)
    previous = json.loads(config_path.read_text())["config"]
    differs = sorted(k for k in wanted
                     if k not in RESUMABLE_CHANGES and previous.get(k, ADDED_LATER.get(k)) != wanted[k])
    if differs and (has_checkpoint or (out / EPISODES).exists()):
        raise ValueError(f"{out} holds a training run with other settings ({', '.join(differs)}); "
                         "use another --out folder or --fresh to start over")
