"""Run one race in the PettingZoo env with one policy per car and record it."""

from __future__ import annotations

import dataclasses
import time
import traceback
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from racing_env.env import RacingParallelEnv

Policy = Callable[[np.ndarray, np.ndarray], Any]


@dataclasses.dataclass
class RaceRecord:
    """What happened in a race.

    Attributes:
        xs: joint states ``(T+1, N, 6)``, the start included.
        summary: per car: ``agent``, ``position``, ``finished``, ``retired`` (by an incident
            rule), ``finish_time`` [s] (None if not finished), ``distance`` [m],
            ``mean_speed`` [m/s], ``collision_steps``, ``time_off_track`` [s].
        frames: rendered RGB frames (empty unless ``render_every``).
        steps: env steps taken.
        act_times: per car, the wall time [s] of every action after the first (which may
            compile).
        faults: car index -> what went wrong (a raised exception or a blown time budget);
            the race stops at the first step with a fault.
    """

    xs: np.ndarray
    summary: list[dict[str, Any]]
    frames: list[np.ndarray]
    steps: int
    act_times: list[list[float]] = dataclasses.field(default_factory=list)
    faults: dict[int, str] = dataclasses.field(default_factory=dict)


def run_race(
    env: RacingParallelEnv,
    policies: Sequence[Policy],
    seed: int = 0,
    render_every: int = 0,
    progress: bool = False,
    step_budget_s: float | None = None,
    catch_errors: bool = False,
) -> RaceRecord:
    """Race ``policies`` (one per car, ``policy(observation, joint_state) -> action``).

    Renders every ``render_every``-th step when > 0 (the env needs ``render_mode='rgb_array'``).
    With ``catch_errors`` a policy that raises is recorded in ``faults`` instead of raising;
    with ``step_budget_s`` an action slower than that (the first action exempt) is a fault.
    Either fault ends the race after the step in which it happened.
    """
    if len(policies) != env.num_cars:
        raise ValueError(f"need {env.num_cars} policies, got {len(policies)}")
    index = {agent: i for i, agent in enumerate(env.possible_agents)}
    observations, infos = env.reset(seed=seed)
    xs, frames = [env.state()], []
    off_steps = np.zeros(env.num_cars, dtype=int)
    contact_steps = np.zeros(env.num_cars, dtype=int)
    act_times: list[list[float]] = [[] for _ in range(env.num_cars)]
    faults: dict[int, str] = {}
    last_info = dict(infos)
    bar = tqdm(total=env.config.max_steps, desc="race", disable=not progress, leave=False)
    step = 0
    while env.agents and not faults:
        if render_every and step % render_every == 0:
            frames.append(env.render())
        state = env.state()
        actions = {}
        for agent in env.agents:
            i = index[agent]
            start = time.perf_counter()
            try:
                actions[agent] = policies[i](observations[agent], state)
            except Exception as err:
                if not catch_errors:
                    raise
                faults[i] = f"step {step}: {type(err).__name__}: {err}\n{traceback.format_exc(limit=3)}"
                continue
            elapsed = time.perf_counter() - start
            if step > 0:
                act_times[i].append(elapsed)
                if step_budget_s is not None and elapsed > step_budget_s:
                    faults[i] = f"step {step}: took {elapsed:.3f} s, over the budget of {step_budget_s} s"
        if faults:
            break
        observations, _, _, _, infos = env.step(actions)
        for agent, info in infos.items():
            i = index[agent]
            off_steps[i] += info["off_track"]
            contact_steps[i] += info["collided"]
            last_info[agent] = info
        xs.append(env.state())
        step += 1
        bar.update(1)
    bar.close()
    if render_every:
        frames.append(env.render())
    xs = np.stack(xs)
    dt = env.config.dt
    summary = []
    for i, agent in enumerate(env.possible_agents):
        info = last_info[agent]
        summary.append(
            {
                "agent": agent,
                "position": info["position"],
                "finished": info["finished"],
                "retired": info["out"],
                "finish_time": info["finish_time"],
                "distance": float(xs[-1, i, 0] - xs[0, i, 0]),
                "mean_speed": float(np.mean(xs[:, i, 1])),
                "collision_steps": int(contact_steps[i]),
                "time_off_track": float(off_steps[i] * dt),
            }
        )
    return RaceRecord(xs=xs, summary=summary, frames=frames, steps=step, act_times=act_times, faults=faults)
