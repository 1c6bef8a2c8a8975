"""Does a standard third-party learner learn to race? rejax's PPO, at its defaults plus
observation normalisation, trained on :class:`racing_env.vector.GymnaxRace` with no adapter,
then raced: how many of its races it finishes, in what time and place.

``python -m experiments.rl.third_party [--opponents lane-keeping] [--off-track penalty]
[--seeds 0 1 2] [--timesteps 2000000] [--json FILE]`` trains one learner per seed and prints
one JSON line per seed (study: docs/experiments/rl-third-party.md). Needs the ``jaxrl`` extra
(gymnax 0.0.x and rejax). It runs with JAX's default float32, as a learner's own script
does (importing the package sets nothing).

The evaluation is this module's, not rejax's: rejax reports only each evaluation episode's
length and return, which do not say whether the car finished or left the track. Here each
of ``races`` races is driven by the trained policy exactly as rejax's evaluations drive it
(its ``make_act``: an action sampled from the policy, clipped to the action space) until the
learner's race ends, and the race's own info says whether and when it finished.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.config import INCIDENT_MODES
from racing_env.vector import LEARNER_OFF_TRACK, GymnaxRace


def make_race(opponents: Sequence[str] = (), off_track: str = LEARNER_OFF_TRACK, track: str = "trefoil",
              **config: Any) -> GymnaxRace:
    """The learner's race: alone (no ``opponents``: a time trial) or against them, one lap of
    ``track``, leaving the track handled by ``off_track`` (``terminate``, GymnaxRace's default:
    the car is out; ``both``: out and charged the ``off_track`` weight once; ``penalty``,
    the tournaments' rule: charged every step off the track, racing on)."""
    return GymnaxRace(opponents=list(opponents), track=track, on_off_track=off_track, **config)


def race_policy(env: GymnaxRace, act, key: jax.Array, races: int = 32) -> dict[str, float]:
    """Race ``act(obs, key) -> action`` on ``races`` races drawn from ``key`` until each
    learner's race ends (finished, out or cut at ``max_steps``): the share finished, the mean
    finish time of those [s], the mean place among the finished, the share out, the mean
    number of steps in contact with another car, the mean return and episode length [steps]."""
    params = env.default_params

    def one_race(key):
        key_start, key_steps = jax.random.split(key)
        obs, state = env.reset_env(key_start, params)

        def step(carry, key):
            # after the learner's race ends (``done``) the race_step has restarted it; nothing
            # of the new race is counted
            obs, state, done, ret, length, contacts, finished, finish_time, place, out = carry
            key_act, key_step = jax.random.split(key)
            obs, state, reward, ends, info = env.race_step(key_step, state, act(obs, key_act), params)
            live = ~done
            ends_here = live & ends
            carry = (obs, state, done | ends, ret + jnp.where(live, reward, 0.0), length + live,
                     contacts + (live & info["collided"]),
                     jnp.where(ends_here, info["finished"], finished),
                     jnp.where(ends_here, info["finish_time"], finish_time),
                     jnp.where(ends_here, info["position"], place), jnp.where(ends_here, info["out"], out))
            return carry, None

        init = (obs, state, jnp.array(False), jnp.float32(0.0), jnp.int32(0), jnp.int32(0), jnp.array(False),
                jnp.float32(jnp.nan), jnp.int32(0), jnp.array(False))
        carry, _ = jax.lax.scan(step, init, jax.random.split(key_steps, int(params.max_steps)))
        return carry[3:]

    ret, length, contacts, finished, finish_time, place, out = jax.jit(jax.vmap(one_race))(jax.random.split(key, races))
    finished = np.asarray(finished)
    return {
        "races": races,
        "finished": float(finished.mean()),
        "finish_time_s": float(np.asarray(finish_time)[finished].mean()) if finished.any() else None,
        "place": float(np.asarray(place)[finished].mean()) if finished.any() else None,
        "out": float(np.asarray(out).mean()),
        "contact_steps": float(np.asarray(contacts).mean()),
        "return": float(np.asarray(ret).mean()),
        "length": float(np.asarray(length).mean()),
    }


def train_and_race(env: GymnaxRace, seed: int = 0, timesteps: int = 2_000_000, evaluations: int = 8,
                   races: int = 32, normalize_observations: bool = True) -> dict[str, Any]:
    """rejax's PPO at its defaults (plus ``normalize_observations``) for ``timesteps`` steps,
    ``evaluations`` rejax evaluations along the way; then :func:`race_policy`. Returns the
    seed, the training's seconds (compiling included), rejax's evaluations (mean return and
    length each) and the final races'."""
    import rejax

    algo = rejax.PPO.create(env=env, env_params=env.default_params, total_timesteps=timesteps,
                            eval_freq=max(timesteps // evaluations, 1), normalize_observations=normalize_observations)
    started = time.perf_counter()
    train_state, (lengths, returns) = jax.jit(algo.train)(jax.random.key(seed))
    jax.block_until_ready(train_state)
    seconds = time.perf_counter() - started
    return {
        "seed": seed,
        "timesteps": timesteps,
        "seconds": round(seconds, 1),
        "evaluation_returns": np.asarray(returns).mean(axis=1).round(1).tolist(),
        "evaluation_lengths": np.asarray(lengths).mean(axis=1).round(1).tolist(),
        "races": race_policy(env, algo.make_act(train_state), jax.random.key(10_000 + seed), races),
    }


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.rl.third_party", description=__doc__.split("\n\n")[0])
    parser.add_argument("--opponents", nargs="*", default=[], help="JAX opponents (agent specs); none: a time trial")
    parser.add_argument("--off-track", default=LEARNER_OFF_TRACK, choices=INCIDENT_MODES,
                        help="what leaving the track does (default: %(default)s, GymnaxRace's)")
    parser.add_argument("--track", default="trefoil")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--timesteps", type=int, default=2_000_000)
    parser.add_argument("--races", type=int, default=32, help="races of the final evaluation")
    parser.add_argument("--json", type=Path, help="also append the JSON lines to this file")
    args = parser.parse_args(argv)
    if args.timesteps < 1 or args.races < 1:
        parser.error("--timesteps and --races must be >= 1")
    env = make_race(args.opponents, args.off_track, args.track)
    for seed in args.seeds:
        row = {"opponents": args.opponents, "off_track": args.off_track, "track": args.track,
               **train_and_race(env, seed, args.timesteps, races=args.races)}
        line = json.dumps(row)
        print(line, flush=True)
        if args.json is not None:
            with args.json.open("a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
