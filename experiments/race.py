"""Run one race in the PettingZoo env with one policy per car and record it.

The record keeps what a frame of every step shows (the joint states, each car's status
and position, and on request the planners' plans), so that the frames drawn while the
race runs and those drawn later from its replay (``experiments.replay``) are the same.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from racing_env.dynamics import N_LAT, S
from racing_env.env import RacingParallelEnv
from racing_env.render import Scene, car_status

Policy = Callable[[np.ndarray, np.ndarray], Any]


@dataclasses.dataclass
class RaceRecord:
    """What happened in a race.

    Attributes:
        xs: joint states ``(T+1, N, 6)``, the start included.
        summary: per car: ``agent``, ``position``, ``finished``, ``retired`` (by an incident
            rule), ``finish_time`` [s] (None if not finished), ``distance`` [m],
            ``mean_speed`` [m/s], ``collision_steps``, ``time_off_track`` [s], ``off_track_steps``
            (the steps after which the car was off the track), ``penalty`` (the steward's time
            penalties [s]), ``race_time`` (finish time plus penalties [s], None if not
            finished: what orders the finishers), ``faults`` (incidents it answered for).
        incidents: every contact incident, in order: ``step`` (the step it began in, 1 for
            the first), ``time`` [s], ``cars`` (the pair's indices), ``verdict``
            (:data:`racing_env.steward.VERDICTS`), ``at_fault`` (the index of the car that
            answers, None for a racing incident) and ``closing_speed`` [m/s].
        frames: rendered RGB frames (empty unless ``render_every``).
        steps: env steps taken.
        status: ``(T+1, N)`` int8 each car's status at each step
            (:data:`racing_env.render.RACING`, ``FINISHED`` or ``RETIRED``).
        position: ``(T+1, N)`` int16 race positions (1 = leading).
        plans: with ``plans`` on: per step ``0..T`` and car, None or what the car's agent
            planned from that step's state, ``(H, N, 2)`` float32 ``[s, n]`` [m] (its own
            plan in its row, its predictions of the others in theirs); else None.
        labels: a name per car for frames (the agents' names unless given).
        dt: the env's time step [s].
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
    status: np.ndarray | None = None
    position: np.ndarray | None = None
    plans: list[list[np.ndarray | None]] | None = None
    labels: tuple[str, ...] = ()
    dt: float = 0.1
    incidents: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    def scene(self, k: int) -> Scene:
        """What the frame of step ``k`` shows (:class:`racing_env.render.Scene`)."""
        return Scene(x=self.xs[k], time=k * self.dt, status=np.asarray(self.status[k], dtype=np.int8),
                     position=np.asarray(self.position[k], dtype=np.int16), labels=self.labels,
                     plans=None if self.plans is None else self.plans[k],
                     notes=incident_notes(self.incidents, k, self.labels, self.dt))


NOTE_SECONDS = 3.0
"""[s] How long a frame shows an incident's verdict after it began."""


def incident_notes(incidents: Sequence[dict[str, Any]], k: int, labels: Sequence[str], dt: float) -> list[str]:
    """The verdicts a frame of step ``k`` shows: the incidents (:attr:`RaceRecord.incidents`)
    begun in the last :data:`NOTE_SECONDS`, one line each."""
    notes = []
    for incident in incidents:
        if 0 <= k - incident["step"] < NOTE_SECONDS / dt:
            first, second = (labels[i] for i in incident["cars"])
            fault = incident["at_fault"]
            who = "nobody answers" if fault is None else f"{labels[fault]} answers"
            notes.append(f"t {incident['time']:.1f} s  {first} / {second}: {incident['verdict']}, {who} "
                         f"({incident['closing_speed']:.1f} m/s)")
    return notes


def plan_of(policy: Policy) -> np.ndarray | None:
    """What a policy's agent plans now: its diagnostics' ``plan`` ``(H, N, 6)`` as
    ``(H, N, 2)`` float32 ``[s, n]`` (None for a policy without a plan). ``policy``: an
    agent, or an agent's bound ``act``."""
    agent = policy if hasattr(policy, "diagnostics") else getattr(policy, "__self__", None)
    plan = agent.diagnostics().get("plan") if hasattr(agent, "diagnostics") else None
    if plan is None:
        return None
    return np.asarray(plan)[:, :, [S, N_LAT]].astype(np.float32)


def incidents_of(infos: dict[str, dict[str, Any]], index: dict[str, int], step: int, dt: float
                 ) -> list[dict[str, Any]]:
    """The incidents that began in step ``step`` (1 for the first) from the env's ``infos``,
    each once (see :attr:`RaceRecord.incidents`); ``index`` maps agents to car indices."""
    found = []
    for agent, info in infos.items():
        i = index[agent]
        for incident in info["incidents"]:
            j = index[incident["with"]]
            if i < j:
                other_fault = any(mine["at_fault"] for mine in infos.get(incident["with"], {}).get("incidents", [])
                                  if mine["with"] == agent)
                at_fault = i if incident["at_fault"] else (j if other_fault else None)
                found.append({"step": step, "time": round(step * dt, 9), "cars": [i, j],
                              "verdict": incident["verdict"], "at_fault": at_fault,
                              "closing_speed": float(incident["closing_speed"])})
    return found


def _solve_field(policies: Sequence[Policy], observations: Sequence[Any], state: np.ndarray,
                 catch_errors: bool) -> dict[int, float]:
    """The field's batched re-plans of this step (:func:`planners.agents.field.solve_field`);
    the seconds charged to each policy by its position. A policy whose set-up for the batch
    raises is left to fail in its own action."""
    from planners.agents.field import solve_field

    try:
        return solve_field(policies, observations, state)["charged"]
    except Exception:  # noqa: BLE001 - each policy then solves (and fails) in its own act
        if not catch_errors:
            raise
        return {}


def run_race(
    env: RacingParallelEnv,
    policies: Sequence[Policy],
    seed: int = 0,
    render_every: int = 0,
    progress: bool = False,
    step_budget_s: float | None = None,
    catch_errors: bool = False,
    plans: bool = False,
    labels: Sequence[str] | None = None,
    batch_field: bool = True,
    reset_options: dict[str, Any] | None = None,
) -> RaceRecord:
    """Race ``policies`` (one per car, ``policy(observation, joint_state) -> action``).

    Renders every ``render_every``-th step when > 0 with the env's renderer (after the
    policies acted, so a frame shows the plans they acted on), labelling the cars with
    ``labels`` (default: the agents' names). ``plans`` records what each policy's agent
    planned at every step (:func:`plan_of`) into the record and the frames.
    With ``catch_errors`` a policy that raises is recorded in ``faults`` instead of raising;
    with ``step_budget_s`` an action slower than that (the first action exempt) is a fault.
    Either fault ends the race after the step in which it happened.
    With ``batch_field`` the re-plans of the game planners that play local games (a field
    larger than their rivals) are solved as one batch per step
    (:func:`planners.agents.field.solve_field`), each car's action time charged its share.
    ``reset_options`` go to the env's reset (e.g. ``{"x0": start}``).
    """
    if len(policies) != env.num_cars:
        raise ValueError(f"need {env.num_cars} policies, got {len(policies)}")
    index = {agent: i for i, agent in enumerate(env.possible_agents)}
    labels = tuple(env.possible_agents) if labels is None else tuple(str(label) for label in labels)
    if len(labels) != env.num_cars:
        raise ValueError(f"need {env.num_cars} labels, got {len(labels)}")
    observations, infos = env.reset(seed=seed, options=reset_options)
    record = RaceRecord(xs=np.empty(0), summary=[], frames=[], steps=0, labels=labels, dt=env.config.dt,
                        plans=[] if plans else None)
    xs, status, position = [env.state()], [], []
    off_steps = np.zeros(env.num_cars, dtype=int)
    contact_steps = np.zeros(env.num_cars, dtype=int)
    act_times: list[list[float]] = [[] for _ in range(env.num_cars)]
    faults: dict[int, str] = {}
    last_info = dict(infos)

    def standing() -> None:  # each car's status and position now, from its last info
        infos_now = [last_info[a] for a in env.possible_agents]
        status.append(car_status([info["finished"] for info in infos_now], [info["out"] for info in infos_now]))
        position.append(env.positions.tolist())  # every car's, penalties included

    def draw(k: int) -> None:
        record.xs, record.status, record.position = xs, status, position  # lists: scene(k) indexes them
        record.frames.append(env.renderer.draw(record.scene(k)))

    standing()
    bar = tqdm(total=env.config.max_steps, desc="race", disable=not progress, leave=False)
    step = 0
    while env.agents and not faults:
        state = env.state()
        actions = {}
        charged = _solve_field([policies[index[a]] for a in env.agents], [observations[a] for a in env.agents],
                               state, catch_errors) if batch_field else {}
        for slot, agent in enumerate(env.agents):
            i = index[agent]
            start = time.perf_counter() - charged.get(slot, 0.0)
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
        if plans:
            record.plans.append([plan_of(policies[index[a]]) if a in actions else None
                                 for a in env.possible_agents])
        if render_every and step % render_every == 0:
            draw(step)
        if faults:
            break
        observations, _, _, _, infos = env.step(actions)
        for agent, info in infos.items():
            i = index[agent]
            off_steps[i] += info["off_track"]
            contact_steps[i] += info["collided"]
            last_info[agent] = info
        record.incidents.extend(incidents_of(infos, index, step + 1, env.config.dt))
        xs.append(env.state())
        standing()
        step += 1
        bar.update(1)
    bar.close()
    if plans:
        record.plans.extend([None] * env.num_cars for _ in range(len(xs) - len(record.plans)))
    if render_every and not (faults and step % render_every == 0):  # the final state (unless just drawn)
        draw(len(xs) - 1)
    xs = np.stack(xs)
    dt = env.config.dt
    summary = []
    final_positions = env.positions
    for i, agent in enumerate(env.possible_agents):
        info = last_info[agent]
        summary.append(
            {
                "agent": agent,
                "position": int(final_positions[i]),
                "finished": info["finished"],
                "retired": info["out"],
                "finish_time": info["finish_time"],
                "distance": float(xs[-1, i, 0] - xs[0, i, 0]),
                "mean_speed": float(np.mean(xs[:, i, 1])),
                "collision_steps": int(contact_steps[i]),
                "time_off_track": float(off_steps[i] * dt),
                "off_track_steps": int(off_steps[i]),
                "penalty": float(info["penalty"]),
                "race_time": None if info["finish_time"] is None else info["finish_time"] + float(info["penalty"]),
                "faults": int(info["faults"]),
            }
        )
    record.xs, record.status, record.position = xs, np.array(status, np.int8), np.array(position, np.int16)
    record.summary, record.steps, record.act_times, record.faults = summary, step, act_times, faults
    return record
