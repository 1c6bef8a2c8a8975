"""`racing bench --only rl`: the throughput of the loops RL trains in.

Rows: the PettingZoo env and the vectorised env (:mod:`racing_env.vector`) at B = 1, 64 and
1,024 races with random actions, in the same run; the vectorised env at 1,024 races on Monza
against the lane keeper, with endless races and with short episodes that autoreset every few
dozen steps (the cost of a reset); ``GymnaxRace`` against the lane keeper, 256 races under
one jitted ``lax.scan``, with ``jax_enable_x64`` on and off, beside the vectorised env at
the same batch; the vectorised env against each kind of
opponent at B = 64, re-planning every step and every 5 steps (the learner's car driven by the
lane keeper, and, for the planners, by random actions); and stable-baselines3 PPO
training against the lane keeper and against feedback iLQGame, today's path (copies of the
single env in a ``DummyVecEnv``) beside the vectorised one; and the JAX learner
(:mod:`experiments.rl.train_jax`) on the same tasks: the lane keeper inside its compiled
update at B = 256 and 1,024, feedback iLQGame re-planning every 5 steps at B = 64. Every rate counts race-steps (one
step of one race) per second of run time after a first call that compiles; the compile time
is reported apart.
"""

from __future__ import annotations

import time
from typing import Any, Iterator

import numpy as np

#: The race every row runs: two cars on the trefoil, a race long enough never to end while timed,
#: leaving the track penalised (the learner faces' own default retires the learner: a race
#: of random actions would then restart while timed).
RACE = dict(track="trefoil", max_steps=10**9, laps=1000, on_off_track="penalty")
#: Batch sizes of the random-action rows.
BATCHES = (1, 64, 1024)
#: Opponents of the opponent rows, and the re-plan intervals they are raced with.
#: The real-time feedback planner (two iterations a re-plan), in float64 and in float32.
REAL_TIME = "ilqgame-fb:iterations=2,trust_radius=10"
REAL_TIME_FLOAT32 = f"{REAL_TIME},precision=float32"
OPPONENTS = ("lane-keeping", "ilqr", "ilqgame-ol", "ilqgame-fb", "ilqgame-fb:max_iterations=5", REAL_TIME,
             REAL_TIME_FLOAT32)
#: Opponents of the rows whose learner acts at random (as a learner does at the start of a training).
RANDOM_LEARNER_OPPONENTS = ("ilqr", "ilqgame-fb", REAL_TIME, REAL_TIME_FLOAT32)
REPLAN_EVERY = (1, 5)


def _rate(step, count: int, repeats: int) -> tuple[float, list[float]]:
    """Median race-steps per second of ``step(k)`` called ``count`` times, over ``repeats``."""
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        done = sum(step(k) for k in range(count))
        rates.append(done / (time.perf_counter() - start))
    return float(np.median(rates)), rates


def _random_action_rate(envs, num_envs: int, calls: int, repeats: int) -> tuple[float, list[float], float]:
    """The vectorised env ``envs`` (``num_envs`` races) reset with seed 0 and stepped with
    uniform random learner actions: its median race-steps per second over ``repeats`` runs of
    ``calls`` steps (:func:`_rate`), the runs' rates, and the first step's time (its compile) [s]."""
    actions = np.random.default_rng(0).uniform(-1, 1, (calls, num_envs, 2))
    envs.reset(seed=0)
    start = time.perf_counter()
    envs.step(actions[0])
    compile_s = time.perf_counter() - start

    def step(k: int) -> int:
        envs.step(actions[k])
        return num_envs

    rate, rates = _rate(step, calls, repeats)
    return rate, rates, compile_s

def _vector_env(num_envs: int, opponents: list | None = None, **race: Any):
    import gymnasium

    import racing_env  # noqa: F401 - registers racing_env/Race-v0

    return gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                              opponents=opponents, **RACE, **race)


def _vector_env_on(num_envs: int, track: str, **race: Any):
    """The vectorised env on ``track`` against the lane keeper, with the race settings ``race``."""
    import gymnasium

    import racing_env  # noqa: F401 - registers racing_env/Race-v0

    return gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                              opponents=["lane-keeping"], track=track, **race)


def pettingzoo_row(steps: int = 2000, repeats: int = 3) -> dict[str, Any]:
    """The PettingZoo env, two cars, random actions: the baseline of the vectorised rows."""
    from racing_env import parallel_env

    env = parallel_env(num_agents=2, **RACE)
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, 2, 2)).astype(np.float32)
    env.reset(seed=0)
    start = time.perf_counter()
    env.step({a: actions[0, i] for i, a in enumerate(env.agents)})
    compile_s = time.perf_counter() - start

    def step(k: int) -> int:
        env.step({a: actions[k, i] for i, a in enumerate(env.possible_agents)})
        return 1

    rate, rates = _rate(step, steps, repeats)
    return {"name": "pettingzoo_env_2_cars", "steps_per_s": rate, "compile_s": compile_s,
            "repeats": [round(r) for r in rates]}


def vector_rows(baseline: float, calls: int = 300, repeats: int = 3, batches: tuple[int, ...] = BATCHES
                ) -> Iterator[dict[str, Any]]:
    """The vectorised env at each of :data:`BATCHES`, random learner actions against a coasting
    car; ``vs_pettingzoo`` is the ratio to ``baseline`` (the PettingZoo row of this run)."""
    for num_envs in batches:
        rate, rates, compile_s = _random_action_rate(_vector_env(num_envs), num_envs, calls, repeats)
        yield {"name": f"vector_env_B{num_envs}", "races": num_envs, "steps_per_s": rate,
               "vs_pettingzoo": rate / baseline, "compile_s": compile_s, "repeats": [round(r) for r in rates],
               "target_steps_per_s": 1_000_000 if num_envs == 1024 else None}


def _opponent_target(spec: str, replan_every: int) -> float | None:
    if not spec.startswith("ilqgame-fb"):
        return None
    return 4_000 if replan_every == 1 else 12_000


def opponent_rows(num_envs: int = 64, calls: int = 30, opponents: tuple[str, ...] = OPPONENTS,
                  learner_acts: str = "lane-keeping", replan_every: tuple[int, ...] = REPLAN_EVERY
                  ) -> Iterator[dict[str, Any]]:
    """The vectorised env at ``num_envs`` races against each of :data:`OPPONENTS`, re-planning
    every step and every 5 steps (:data:`REPLAN_EVERY`; the scripted driver does not plan, so
    it has one row). The learner's car is driven by the lane keeper (its JAX law, outside the
    timed env step's opponent but inside the timing), so the opponent races a realistic rival
    as in the tournaments' gauntlets; with ``learner_acts="random"`` it acts uniformly at
    random (seeded), as a learner does at the start of a training. Each row also reports the
    opponents' converged share and the median and 95th percentile of iterations per re-plan."""
    from planners.agents.batched import make_batched_opponent

    for spec in opponents:
        for every in replan_every if spec != "lane-keeping" else (1,):
            full = spec if every == 1 else f"{spec}{',' if ':' in spec else ':'}replan_every={every}"
            envs = _vector_env(num_envs, [full])
            learner = make_batched_opponent("lane-keeping", envs.unwrapped.game, 0, num_envs)
            everyone = np.ones(num_envs, dtype=bool)
            learner.reset(everyone, np.arange(num_envs))
            racing = np.ones((num_envs, 2), dtype=bool)
            rng = np.random.default_rng(0)

            def learner_step():
                if learner_acts == "random":
                    return envs.step(rng.uniform(-1.0, 1.0, (num_envs, 2)).astype(np.float32))
                actions, _ = learner.act(np.zeros((num_envs, 1), np.float32), envs.unwrapped.state(), racing)
                return envs.step(actions)

            envs.reset(seed=0)
            start = time.perf_counter()
            for _ in range(every):  # the first re-plan and the steps that follow it compile
                learner_step()
            compile_s = time.perf_counter() - start
            converged, iterations = [], []

            def step(k: int) -> int:
                infos = learner_step()[4]
                diagnostics = infos.get("opponents", {}).get("car_1", {})
                if "replanned" in diagnostics:
                    replanned = np.asarray(diagnostics["replanned"], dtype=bool)
                    converged.extend(np.asarray(diagnostics["converged"])[replanned].tolist())
                    iterations.extend(np.asarray(diagnostics["iterations"])[replanned].tolist())
                return num_envs

            rate, rates = _rate(step, calls * every, 1)
            random = learner_acts == "random"
            target = (3_000 if spec.startswith("ilqgame-fb") else None) if random else _opponent_target(spec, every)
            row = {"name": f"opponent_{full}_B{num_envs}" + ("_random_learner" if random else ""), "opponent": full,
                   "replan_every": every, "learner": learner_acts, "steps_per_s": rate, "compile_s": compile_s,
                   "target_steps_per_s": target}
            if converged:
                row["converged_share"] = float(np.mean(converged))
                row["iterations_median"] = float(np.median(iterations))
                row["iterations_p95"] = float(np.percentile(iterations, 95))
            yield row


#: What makes the episodes of the short-episode row short: 150 m races, retired off the track.
SHORT_EPISODES = dict(race_distance=150.0, on_off_track="terminate")


def _timed_in_turns(envs: dict[str, Any], actions: np.ndarray, repeats: int
                    ) -> tuple[dict[str, list[float]], dict[str, float], dict[str, int]]:
    """Step each of the vectorised ``envs`` (by name) through ``actions (calls, B, 2)`` in
    turns, ``repeats`` times, after a warm-up of 50 steps from seed 0 (past the first
    episodes' common length, so resets spread out): the seconds of each run, each env's first
    step (its compile) [s] and the episodes that ended while timed."""
    compile_s, ends = {}, {name: 0 for name in envs}
    for name, env in envs.items():
        env.reset(seed=0)
        start = time.perf_counter()
        env.step(actions[0])
        compile_s[name] = time.perf_counter() - start
        for a in actions[1:50]:
            env.step(a)
    seconds: dict[str, list[float]] = {name: [] for name in envs}
    for _ in range(repeats):
        for name, env in envs.items():
            start = time.perf_counter()
            for a in actions:
                _, _, terminated, truncated, _ = env.step(a)
                ends[name] += int(np.sum(terminated | truncated))
            seconds[name].append(time.perf_counter() - start)
    return seconds, compile_s, ends


def contact_rows(num_envs: int = 1024, calls: int = 200, repeats: int = 3) -> Iterator[dict[str, Any]]:
    """The vectorised env (:data:`RACE`, random learner actions against a coasting car) with
    contact physics and the steward, and with ghost cars and no penalties (the race before
    either existed), timed in turns: the physics row reports its rate against the ghost one
    (target: at least 0.8 of it)."""
    actions = np.random.default_rng(0).uniform(-1, 1, (calls, num_envs, 2))
    seconds, compile_s, _ = _timed_in_turns({"physics": _vector_env(num_envs),
                                             "ghost": _vector_env(num_envs, contact="ghost", penalties="none")},
                                            actions, repeats)
    rate = {name: num_envs * calls / float(np.median(times)) for name, times in seconds.items()}
    for name in ("ghost", "physics"):
        yield {"name": f"vector_env_B{num_envs}_contact_{name}", "races": num_envs, "contact": name,
               "steps_per_s": rate[name], "compile_s": compile_s[name],
               **({"vs_ghost": rate["physics"] / rate["ghost"], "target_vs_ghost": 0.8} if name == "physics" else {}),
               "repeats": [round(num_envs * calls / t) for t in seconds[name]]}


def short_episode_rows(num_envs: int = 1024, calls: int = 200, repeats: int = 3, track: str = "Monza"
                       ) -> Iterator[dict[str, Any]]:
    """The vectorised env on a real circuit against the lane keeper with random learner
    actions: races that never end while timed, and short episodes (:data:`SHORT_EPISODES`:
    the first hour of a training that retires cars off the track) that autoreset every few
    dozen steps. The two are timed in turns, ``calls`` steps each, ``repeats`` times; the
    short row reports its rate against the endless one (target: at least half of it), the
    episode ends per step and the cost of one reset, ``(time per step, short - endless) /
    resets per step``."""
    actions = np.random.default_rng(0).uniform(-1, 1, (calls, num_envs, 2))
    seconds, compile_s, ends = _timed_in_turns({"endless": _vector_env_on(num_envs, track, max_steps=10**9, laps=1000,
                                                                       on_off_track="penalty"),
                                                "short": _vector_env_on(num_envs, track, **SHORT_EPISODES)},
                                               actions, repeats)
    rate = {name: num_envs * calls / float(np.median(times)) for name, times in seconds.items()}
    resets_per_step = ends["short"] / (repeats * calls)
    per_step = {name: float(np.median(times)) / calls for name, times in seconds.items()}
    yield {"name": f"vector_env_{track}_lane-keeping_B{num_envs}", "races": num_envs, "track": track,
           "steps_per_s": rate["endless"], "compile_s": compile_s["endless"], "episode_ends_per_step": 0.0,
           "repeats": [round(num_envs * calls / t) for t in seconds["endless"]]}
    yield {"name": f"vector_env_{track}_lane-keeping_B{num_envs}_short_episodes", "races": num_envs, "track": track,
           **SHORT_EPISODES, "steps_per_s": rate["short"], "compile_s": compile_s["short"],
           "vs_endless": rate["short"] / rate["endless"], "target_vs_endless": 0.5,
           "episode_ends_per_step": resets_per_step,
           "ms_per_reset": 1e3 * (per_step["short"] - per_step["endless"]) / resets_per_step if resets_per_step else None,
           "repeats": [round(num_envs * calls / t) for t in seconds["short"]]}


#: Races of the gymnax rows: one ``lax.scan`` of ``jax.vmap`` over this many races.
GYMNAX_RACES = 256


def _gymnax_scan(num_envs: int, steps: int, track: str):
    """A jitted run of ``steps`` steps of ``num_envs`` :class:`~racing_env.vector.GymnaxRace`
    races against the lane keeper under one ``lax.scan``, random learner actions (uniform
    in ``[-1, 1]^2``, float32), and the races' first state. Built and traced in the x64
    setting of the caller."""
    import jax
    import jax.numpy as jnp

    from racing_env.vector import GymnaxRace

    # the vector env's rules (RACE: a penalty off the track, no retiring), so the rows race the same races
    env = GymnaxRace(opponents=["lane-keeping"], **{**RACE, "track": track})
    params = env.default_params
    step = jax.vmap(env.race_step, in_axes=(0, 0, 0, None))

    def body(state, key):
        k_act, k_step = jax.random.split(key)
        actions = jax.random.uniform(k_act, (num_envs, 2), jnp.float32, -1.0, 1.0)
        _, state, reward, done, _ = step(jax.random.split(k_step, num_envs), state, actions, params)
        return state, (reward.sum(), done.sum())

    run = jax.jit(lambda state, key: jax.lax.scan(body, state, jax.random.split(key, steps)))
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(jax.random.key(0), num_envs), params)
    return run, state


def gymnax_rows(num_envs: int = GYMNAX_RACES, steps: int = 200, repeats: int = 5, track: str = "trefoil"
                ) -> Iterator[dict[str, Any]]:
    """:class:`~racing_env.vector.GymnaxRace` against the lane keeper, ``num_envs`` races
    stepped ``steps`` times inside one jitted ``lax.scan`` (the opponent and the autoreset
    inside the step), with ``jax_enable_x64`` on and off (scoped with ``jax.enable_x64``: the
    race runs in float64 or float32), timed in turns ``repeats`` times each after a first
    call that compiles; then the vectorised env at the same batch (random learner actions
    from the host, the lane keeper compiled in its step)."""
    import jax

    settings = (True, False)
    runs, compile_s, seconds, dtypes = {}, {}, {x64: [] for x64 in settings}, {}
    for x64 in settings:
        with jax.enable_x64(x64):
            run, state = _gymnax_scan(num_envs, steps, track)
            start = time.perf_counter()
            jax.block_until_ready(run(state, jax.random.key(1)))
            compile_s[x64] = time.perf_counter() - start
            runs[x64], dtypes[x64] = (run, state), str(state.x.dtype)
    for k in range(repeats):
        for x64 in settings:
            with jax.enable_x64(x64):  # a call traced under the other setting would compile again
                run, state = runs[x64]
                start = time.perf_counter()
                jax.block_until_ready(run(state, jax.random.key(2 + k)))
                seconds[x64].append(time.perf_counter() - start)
    for x64 in settings:
        yield {"name": f"gymnax_{track}_lane-keeping_B{num_envs}_x64_{'on' if x64 else 'off'}", "races": num_envs,
               "track": track, "x64": x64, "race_dtype": dtypes[x64],
               "steps_per_s": num_envs * steps / float(np.median(seconds[x64])), "compile_s": compile_s[x64],
               "repeats": [round(num_envs * steps / t) for t in seconds[x64]]}
    envs = _vector_env_on(num_envs, track, max_steps=RACE["max_steps"], laps=RACE["laps"],
                          on_off_track=RACE["on_off_track"])
    rate, rates, compile_s = _random_action_rate(envs, num_envs, steps, repeats)
    yield {"name": f"vector_env_{track}_lane-keeping_B{num_envs}", "races": num_envs, "track": track,
           "steps_per_s": rate, "compile_s": compile_s, "repeats": [round(r) for r in rates]}


#: (opponent spec, target steps/s) of the training rows.
TRAINING_OPPONENTS = (("lane-keeping", 5_000), ("ilqgame-fb", 1_500), ("ilqgame-fb:replan_every=5", 1_500))
#: (label, envs, vector) of the training paths: today's copies in a DummyVecEnv and the vectorised race.
TRAINING_PATHS = (("dummy_vec_env", 2, False), ("vector_env", 64, True))


def training_row(opponent: str, path: str, envs: int, vector: bool, rollouts: int = 2,
                 target: float | None = None) -> dict[str, Any]:
    """SB3 PPO training steps per second on the trefoil against ``opponent``: the run's
    training env (:func:`experiments.rl.train.make_training_env`) under ``VecNormalize``, with
    the PPO settings ``racing train`` gives ``envs`` copies; a first rollout and update
    (compiling the race and the opponent's solver) are timed apart, then ``rollouts`` more."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from experiments.rl.train import TrainConfig, make_training_env, model_settings

    import torch

    from experiments.rl.train import TORCH_THREADS

    torch.set_num_threads(TORCH_THREADS)  # as racing train trains
    config = TrainConfig(opponents=(opponent,), envs=envs, vector=vector, seed=0)
    venv = VecNormalize(make_training_env(config))
    settings = model_settings(config)
    rollout = settings.get("n_steps", 2048) * envs
    model = PPO("MlpPolicy", venv, seed=0, verbose=0, **settings)
    start = time.perf_counter()
    model.learn(total_timesteps=rollout)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    model.learn(total_timesteps=rollouts * rollout, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    venv.close()
    return {"name": f"ppo_{opponent}_{path}", "opponent": opponent, "envs": envs, "vector": vector,
            "steps_per_s": rollouts * rollout / seconds, "steps": rollouts * rollout,
            "first_rollout_s": compile_s, "target_steps_per_s": target if vector else None}


def training_rows() -> Iterator[dict[str, Any]]:
    for opponent, target in TRAINING_OPPONENTS:
        for path, envs, vector in TRAINING_PATHS:
            yield training_row(opponent, path, envs, vector, target=target)


#: (opponent spec, envs, target steps/s) of the JAX learner's rows: the lane keeper inside the compiled
#: update, and feedback iLQGame re-planning every 5 steps on the host races (its batched solves).
JAX_TRAINING = (("lane-keeping", 256, 50_000), ("lane-keeping", 1024, 50_000),
                ("ilqgame-fb:replan_every=5", 64, 8_000), (REAL_TIME, 64, 3_000), (REAL_TIME_FLOAT32, 64, 3_000),
                (f"{REAL_TIME},replan_every=5", 64, 8_000), (f"{REAL_TIME_FLOAT32},replan_every=5", 64, 8_000))


def jax_training_row(opponent: str, envs: int, updates: int = 4, target: float | None = None,
                     hyperparameters: tuple = (), host: bool = False) -> dict[str, Any]:
    """The JAX learner's training steps per second on the trefoil against ``opponent``
    (:mod:`experiments.rl.train_jax`, the PPO settings ``racing train --learner jax`` gives
    ``envs`` races): a first update (compiling the update, or the policy's steps and the
    opponent's solves) timed apart, then ``updates`` more, rollouts and fits together.
    ``host``: race on the host (a pool of the one opponent, which the compiled form does not
    take) even where the races could be compiled with the policy."""
    import jax

    from experiments.rl import ppo_jax
    from experiments.rl.train import TrainConfig
    from experiments.rl.train_jax import make_races, ppo_settings

    config = TrainConfig(opponents=(opponent,), envs=envs, learner="jax", seed=0, hyperparameters=hyperparameters,
                         pool=host)
    settings = ppo_settings(config)
    races = make_races(config, settings)
    learner = ppo_jax.init_learner(jax.random.PRNGKey(0), races.observation_size, envs, settings)
    learner, in_flight = races.start(learner, 0)
    start = time.perf_counter()
    learner, in_flight, _, _ = races.update(learner, in_flight)
    jax.block_until_ready(learner.params)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(updates):
        learner, in_flight, _, _ = races.update(learner, in_flight)
    jax.block_until_ready(learner.params)
    seconds = time.perf_counter() - start
    races.close()
    steps = updates * settings.n_steps * envs
    return {"name": f"jax_ppo_{opponent}_B{envs}" + ("_host" if host else ""), "opponent": opponent, "envs": envs,
            "races": races.kind,
            "steps_per_s": steps / seconds, "steps": steps, "first_update_s": compile_s,
            "n_steps": settings.n_steps, "batch_size": settings.batch_size, "n_epochs": settings.n_epochs,
            "target_steps_per_s": target}


def jax_training_rows() -> Iterator[dict[str, Any]]:
    for opponent, envs, target in JAX_TRAINING:
        yield jax_training_row(opponent, envs, updates=20 if opponent == "lane-keeping" else 4, target=target)


def real_time_rows() -> Iterator[dict[str, Any]]:
    """The rows of ``racing bench --only realtime``: the real-time feedback planner in float64
    and in float32 against each throughput target, in one run: as the vectorised env's
    opponent at B = 64 re-planning every step and every 5 steps, against a learner acting at
    random, and in the JAX learner's training every step and every 5 steps; last, what the
    every-5-steps training's host races cost without any solve: the JAX learner against the
    lane keeper raced on the host the same way (``_host``), the ceiling of that loop."""
    planners = (REAL_TIME, REAL_TIME_FLOAT32)
    yield from opponent_rows(opponents=planners)
    yield from opponent_rows(opponents=planners, learner_acts="random", replan_every=(1,))
    for opponent, envs, target in JAX_TRAINING:
        if opponent.startswith(REAL_TIME):
            yield jax_training_row(opponent, envs, target=target)
    yield jax_training_row("lane-keeping", 64, host=True)


def bench_rl() -> Iterator[dict[str, Any]]:
    """The rows of ``racing bench --only rl`` (module docstring)."""
    baseline = pettingzoo_row()
    yield baseline
    yield from vector_rows(baseline["steps_per_s"])
    yield from contact_rows()
    yield from short_episode_rows()
    yield from gymnax_rows()
    yield from opponent_rows()
    yield from opponent_rows(opponents=RANDOM_LEARNER_OPPONENTS, learner_acts="random", replan_every=(1,))
    yield from training_rows()
    yield from jax_training_rows()
