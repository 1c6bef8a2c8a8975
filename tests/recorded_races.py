"""Races recorded with the PettingZoo env, replayed by tests/test_race_core.py.

Each race is a config, a reset seed, its start and a seeded sequence of actions; the recording holds
every step's observations, rewards, terminations, truncations and infos. The races were
chosen to exercise every rule: contacts and retirements on contact, off-track penalties and
retirements, finishes (in turn, with places and finish times), a lap of a closed track, a
truncation at ``max_steps``, the lead and time reward terms, and three cars.

``python tests/recorded_races.py`` writes ``tests/data/recorded_races.json`` and
``tests/data/recorded_contact_races.json``. The first file was written by the env as it was
before its rules moved into :mod:`racing_env.race` and before cars collided: its races run
with ghost cars, no steward penalties and that time's reward (:data:`LEGACY`), and the
replay checks that neither change altered such a race. The second holds races with contact
physics and the steward (:data:`CONTACT_RACES`), so that a race with contact replays bit for
bit from then on.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

import racing_env
from racing_env import track as tr
from racing_env.config import RewardConfig

RECORDING = Path(__file__).parent / "data" / "recorded_races.json"
CONTACT_RECORDING = Path(__file__).parent / "data" / "recorded_contact_races.json"

#: The rules the races of RECORDING were recorded under: cars that drive through each other,
#: no steward penalties, and the reward's per-step collision term of the time (no fault term).
LEGACY = dict(contact="ghost", penalties="none")
LEGACY_REWARD = dict(collision=-5.0, fault=0.0)
#: What the env's infos and reward terms hold since then, left out of the comparison with RECORDING.
NEW_INFO_KEYS = ("penalty", "faults", "incidents")
NEW_TERMS = ("fault",)

#: name -> (config keyword arguments, reset seed, action seed, action bias per car (jx, jy), steps)
RACES: dict[str, tuple[dict[str, Any], int, int, list[tuple[float, float]], int]] = {
    # side by side, steering into each other: contacts, then a retirement on contact
    "contact_retire": (dict(track="straight", num_agents=2, scenario="side_by_side", on_collision="both",
                            race_distance=300.0, reward=RewardConfig(**LEGACY_REWARD), **LEGACY),
                       0, 1, [(0.6, -0.3), (0.5, 0.3)], 200),
    # three cars on the trefoil, random steering: off-track penalties, lead/time/position terms
    "trefoil_three": (dict(track="trefoil", num_agents=3, scenario="grid", on_off_track="penalty",
                           reward=RewardConfig(position=0.1, lead=0.05, time=-0.01, **LEGACY_REWARD), max_steps=120,
                           **LEGACY), 3, 2, [(0.8, 0.0)] * 3, 130),
    # a short race to the finish: places, finish times, off-track retirements
    "finish": (dict(track="straight", num_agents=3, scenario="grid", race_distance=90.0,
                    reward=RewardConfig(lead=0.1, time=-0.05, **LEGACY_REWARD), **LEGACY), 5, 3, [(1.0, 0.0)] * 3,
               120),
}

#: Races with contact physics and the steward at their defaults (CONTACT_RECORDING).
CONTACT_RACES: dict[str, tuple[dict[str, Any], int, int, list[tuple[float, float]], int]] = {
    # side by side, steering into each other: collisions, verdicts, time penalties at the finish
    "side_by_side": (dict(track="straight", num_agents=2, scenario="side_by_side", race_distance=300.0),
                     0, 1, [(0.6, -0.3), (0.5, 0.3)], 200),
    # three cars on the trefoil, random steering and throttle: rear-ends and side contacts
    "trefoil_three": (dict(track="trefoil", num_agents=3, scenario="grid", max_steps=150), 3, 2,
                      [(0.9, 0.0), (0.3, 0.0), (0.6, 0.0)], 150),
}


#: name -> the race's start (N, 6): the one its reset seed drew when the races were recorded
#: (starts were drawn with NumPy then, with JAX now: racing_env.starts), so the recording
#: still replays bit for bit.
STARTS: dict[str, list[list[float]]] = {
    "contact_retire": [[5.0, 15.0, 2.0, 0.0, 0.0, 0.0], [5.0, 15.0, -2.0, 0.0, 0.0, 0.0]],
    "trefoil_three": [[-8.692617416305596, 14.935846164142829, -2.2705262481871182, 0.0, 0.0, 0.0],
                      [-5.6668878928426105, 15.986729875709726, 2.2463709130390614, 0.0, 0.0, 0.0],
                      [-12.66450909277142, 15.531390784119777, 2.056374913879123, 0.0, 0.0, 0.0]],
    "finish": [[4.464881676378395, 15.737536205260314, 2.0990010152027527, 0.0, 0.0, 0.0],
               [13.00592620415999, 15.133973390867684, 2.059297194836673, 0.0, 0.0, 0.0],
               [8.764178828646653, 14.008118384735129, -2.16088941622003, 0.0, 0.0, 0.0]],
}


#: name -> the start of a race of CONTACT_RACES that does not draw its own (None: drawn).
CONTACT_STARTS: dict[str, list[list[float]] | None] = {
    "side_by_side": STARTS["contact_retire"],
    "trefoil_three": None,
}


def _actions(num: int, seed: int, bias: list[tuple[float, float]], steps: int) -> np.ndarray:
    """Seeded actions ``(steps, num, 2)``: each car's ``bias`` plus noise, mostly inside the
    box, some outside it (the env clips them)."""
    rng = np.random.default_rng(seed)
    return np.asarray(bias) + rng.normal(0.0, 0.4, (steps, num, 2))


def _track(name: str):
    return {"straight": lambda: tr.straight(length=400.0), "trefoil": tr.trefoil}[name]()


def replay(name: str, races: dict = RACES, starts: dict = STARTS) -> list[dict[str, Any]]:
    """Race ``name`` of ``races`` from its start in ``starts`` in the PettingZoo env; every
    step as plain Python values."""
    config, seed, action_seed, bias, steps = races[name]
    # recorded in physical units; the scaled ones are the same times fixed weights
    # (tests/test_race_core.py, test_scaled_observations_are_the_physical_ones_times_their_weights)
    config = {**config, "track": _track(config["track"]), "observation_units": "physical"}
    env = racing_env.parallel_env(**config)
    start = starts[name]
    obs, infos = env.reset(seed=seed, options=None if start is None else {"x0": np.array(start)})
    frames = [{"obs": {a: o.tolist() for a, o in obs.items()}, "infos": infos}]
    actions = _actions(env.num_cars, action_seed, bias, steps)
    for k in range(steps):
        if not env.agents:
            break
        act = {a: actions[k, env.possible_agents.index(a)] for a in env.agents}
        obs, rewards, terms, truncs, infos = env.step(act)
        frames.append({"obs": {a: o.tolist() for a, o in obs.items()}, "rewards": rewards,
                       "terminations": terms, "truncations": truncs, "infos": infos,
                       "state": env.state().tolist()})
    return frames


def main() -> None:
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()  # float64, as the tests race
    RECORDING.parent.mkdir(exist_ok=True)
    RECORDING.write_text(json.dumps({name: replay(name) for name in RACES}))
    CONTACT_RECORDING.write_text(json.dumps({name: replay(name, CONTACT_RACES, CONTACT_STARTS) for name in CONTACT_RACES}))


if __name__ == "__main__":
    main()
