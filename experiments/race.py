"""Run one race in the PettingZoo env with one policy per car and record it."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from racing_env.env import RacingParallelEnv

Policy = Callable[[np.ndarray, np.ndarray], Any]


@dataclasses.dataclass
class RaceRecord:
    """What happened in a race: states ``xs (T+1, N, 6)``, per-car summaries, frames."""

    xs: np.ndarray
    summary: list[dict[str, Any]]
    frames: list[np.ndarray]
    steps: int


def run_race(
    env: RacingParallelEnv,
    policies: Sequence[Policy],
    seed: int = 0,
    render_every: int = 0,
    progress: bool = False,
) -> RaceRecord:
    """Race ``policies`` (one per car, ``policy(observation, joint_state) -> action``).

    Renders every ``render_every``-th step when > 0 (the env needs ``render_mode='rgb_array'``).
    """
    if len(policies) != env.num_cars:
        raise ValueError(f"need {env.num_cars} policies, got {len(policies)}")
    index = {agent: i for i, agent in enumerate(env.possible_agents)}
    observations, infos = env.reset(seed=seed)
    xs, frames = [env.state()], []
    off_steps = np.zeros(env.num_cars, dtype=int)
    contact_steps = np.zeros(env.num_cars, dtype=int)
    last_info = dict(infos)
    bar = tqdm(total=env.config.max_steps, desc="race", disable=not progress, leave=False)
    step = 0
    while env.agents:
        if render_every and step % render_every == 0:
            frames.append(env.render())
        state = env.state()
        actions = {a: policies[index[a]](observations[a], state) for a in env.agents}
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
                "finish_time": info["finish_time"],
                "distance": float(xs[-1, i, 0] - xs[0, i, 0]),
                "mean_speed": float(np.mean(xs[:, i, 1])),
                "collision_steps": int(contact_steps[i]),
                "time_off_track": float(off_steps[i] * dt),
            }
        )
    return RaceRecord(xs=xs, summary=summary, frames=frames, steps=step)
