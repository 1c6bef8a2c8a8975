"""Train stable-baselines3's PPO at its defaults on ``gymnasium.make("racing_env/Race-v0")``
at the env's defaults, evaluating as it goes: a script, run in a subprocess by
``tests/test_sb3_default_race.py`` (JAX's default float32, as a user's process has it; the
tests' own process runs with 64-bit floats).

``python tests/sb3_default_race.py --seed S --budget STEPS [--every STEPS] [--races R]
[--needed K] [--vecnormalize] [--physical]`` trains ``PPO("MlpPolicy", env, seed=S)`` for
up to ``--budget`` steps on the env as it comes (its observations in their default, scaled
units; ``--physical``: in SI units; ``--vecnormalize``: wrapped in SB3's
``VecNormalize(norm_obs=True, norm_reward=False)``, the observations scaled by their running
mean and deviation). Every ``--every`` steps (default 16,384: eight of PPO's 2,048-step
rollouts) it races the policy, acting deterministically (on observations normalised with the
training's statistics, under ``--vecnormalize``), in ``--races`` evaluation races (default 5,
seeded 1000, 1001, ...)
and prints one JSON line: ``timesteps``, ``train_s`` (training's wall time [s],
evaluations excluded), ``wall_s`` (everything [s]), ``finished`` (races finished), and per
race ``distance_m`` (the learner's arc length at the end [m]), ``steps``, ``out`` and
``finish_time_s``. It stops after the first evaluation with at least ``--needed``
(default 3) races finished.

PyTorch runs on one thread (``main``): PPO's defaults are kept, only the wall time changes.
Training in chunks of ``--every`` steps (``learn(..., reset_num_timesteps=False)``, a
multiple of the rollout's 2,048) trains exactly as one call would: the rollouts go on from
the last observation, and PPO's default learning rate and clip range are constants.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium
import numpy as np
import racing_env  # noqa: F401 - registers racing_env/Race-v0
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

ENV_ID = "racing_env/Race-v0"


def evaluate(model: PPO, normalizer: VecNormalize | None, env: gymnasium.Env, races: int) -> list[dict]:
    """Race ``model`` deterministically in ``races`` races of ``env`` (seeds 1000, ...), its
    observations scaled by ``normalizer``'s statistics as they stand (not updated)."""
    results = []
    for k in range(races):
        obs, info = env.reset(seed=1000 + k)
        steps, ended = 0, False
        while not ended:
            seen = normalizer.normalize_obs(obs) if normalizer is not None else obs
            action, _ = model.predict(np.asarray(seen, np.float32), deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            steps += 1
            ended = terminated or truncated
        results.append({"finished": bool(info["finished"]), "out": bool(info["out"]),
                        "distance_m": round(float(info["s"]), 1), "steps": steps,
                        "finish_time_s": None if info["finish_time"] is None else float(info["finish_time"])})
    return results


def main(seed: int, budget: int, every: int = 16_384, races: int = 5, needed: int = 3, vecnormalize: bool = False,
         physical: bool = False) -> None:
    # torch's update on one thread: on a 2-core CPU shared with JAX's threads (and other
    # processes) its two threads contend, and PPO's update took 22 times as long
    torch.set_num_threads(1)
    options = {"observation_units": "physical"} if physical else {}
    envs = DummyVecEnv([lambda: gymnasium.make(ENV_ID, **options)])
    normalizer = VecNormalize(envs, norm_obs=True, norm_reward=False) if vecnormalize else None
    model = PPO("MlpPolicy", normalizer or envs, seed=seed)
    evaluation_env = gymnasium.make(ENV_ID, **options)
    started, train_s = time.perf_counter(), 0.0
    while model.num_timesteps < budget:
        chunk = time.perf_counter()
        model.learn(min(every, budget - model.num_timesteps), reset_num_timesteps=False)
        train_s += time.perf_counter() - chunk
        results = evaluate(model, normalizer, evaluation_env, races)
        finished = sum(r["finished"] for r in results)
        print(json.dumps({"seed": seed, "vecnormalize": vecnormalize, "physical": physical, "timesteps": model.num_timesteps, "train_s": round(train_s, 1),
                          "wall_s": round(time.perf_counter() - started, 1), "finished": finished,
                          "races": results}), flush=True)
        if finished >= needed:
            break


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--budget", type=int, required=True, help="training steps at most")
    parser.add_argument("--every", type=int, default=16_384, help="training steps between evaluations")
    parser.add_argument("--races", type=int, default=5, help="races per evaluation")
    parser.add_argument("--needed", type=int, default=3, help="finished races that end the run")
    parser.add_argument("--vecnormalize", action="store_true", help="observations normalised by SB3's VecNormalize")
    parser.add_argument("--physical", action="store_true", help="the env's observations in SI units")
    main(**vars(parser.parse_args()))
