"""The drawings of docs/rules.md: each steward's rule on a scene that it decides.

``python -m experiments.rules_figure [PATH]`` races every scene of :data:`SCENES` in the
PettingZoo env (two coasting cars on a straight, contact physics and the steward at their
defaults) and the optional rule's scene (:func:`defend`: a car weaving in front of a car
that closes on it, with ``weaving`` among the rules), and draws, per scene, the cars'
footprints at the start, at the contact and at the end (and the weaver's path), with the
steward's verdict as the panel's title. Default path: docs/figures/rules.png.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

#: rule -> (what the scene shows, the cars' starts as (s [m], V [m/s], n [m], chi [rad], ax [m/s^2]))
SCENES: dict[str, tuple[str, tuple[tuple[float, ...], ...]]] = {
    "rear-end": ("the car behind is 5 m/s faster on the same line", ((10.0, 20.0), (20.0, 15.0))),
    "brake-test": ("the car ahead brakes at 10 m/s^2 where nothing asks for it",
                   ((10.0, 20.0, 0.0, 0.0, 0.0), (16.5, 12.0, 0.0, 0.0, -10.0))),
    "moved-across": ("the car alongside moves across at 3 m/s", ((10.0, 20.0, -2.0), (12.0, 20.0, 1.0, -0.15))),
    "squeeze": ("the same move, the victim 1.1 m from the edge", ((10.0, 20.0, -3.9), (12.0, 20.0, -1.0, -0.15))),
    "racing-incident": ("side by side, neither moves across", ((10.0, 20.0, -0.9), (11.0, 20.0, 0.9))),
}
STEPS = 12
DEFEND_STEPS = 45
"""Steps of the ``weaving`` scene (:func:`defend`)."""


def _env(num_cars: int, x0: np.ndarray, **config):
    import racing_env
    from racing_env import track as tr

    env = racing_env.parallel_env(track=tr.straight(length=400.0), num_agents=num_cars, race_distance=390.0,
                                  **config)
    env.reset(seed=0, options={"x0": x0})
    return env


def _first_incident(infos: dict, step: int) -> dict | None:
    """The first incident of a step's infos (car 0's view) with the car at fault, or None."""
    if not infos["car_0"]["incidents"]:
        return None
    return {"step": step, **infos["car_0"]["incidents"][0],
            "at_fault_car": next((a for a, info in infos.items() if any(i["at_fault"] for i in info["incidents"])),
                                 None)}


def defend(moves: int, rules: tuple[str, ...], steps: int = DEFEND_STEPS):
    """The ``weaving`` scene: car_0, 14 m behind at 17.5 m/s, closes on car_1 at 15 m/s,
    which moves across the straight at 1.5 m/s, left and right by turns, for ``moves``
    moves of 0.8 s, then holds its line (its lateral jerk is a proportional controller on
    its lateral speed); the steward judges by ``rules``. Returns the joint states ``(T+1,
    2, 6)``, every incident as ``(step, car, incident dict)`` seen from each car, and the
    first incident as :func:`race_scene` gives it (or None)."""
    from racing_env.dynamics import AY, CHI, V

    x0 = np.zeros((2, 6))
    x0[:, :2] = ((10.0, 17.5), (24.0, 15.0))
    env = _env(2, x0, rules=rules)
    xs, incidents, first = [env.state()], [], None
    for k in range(steps):
        ahead = xs[-1][1]
        wanted = (1.5 if (k // 8) % 2 == 0 else -1.5) if k < 8 * moves else 0.0  # [m/s] lateral speed
        lateral_accel = 3.0 * (wanted - ahead[V] * np.sin(ahead[CHI]))
        steer = float(np.clip(0.3 * (lateral_accel - ahead[AY]), -1.0, 1.0))
        _, _, _, _, infos = env.step({"car_0": np.zeros(2), "car_1": np.array([0.0, steer])})
        xs.append(env.state())
        incidents += [(k + 1, agent, i) for agent, info in infos.items() for i in info["incidents"]]
        first = first or _first_incident(infos, k + 1)
    return np.stack(xs), incidents, first


def race_scene(starts: tuple[tuple[float, ...], ...], steps: int = STEPS):
    """Coast the cars of a scene: their joint states ``(T+1, N, 6)`` and the first incident
    (the env's info of car 0) or None."""
    x0 = np.zeros((len(starts), 6))
    for i, car in enumerate(starts):
        x0[i, :len(car)] = car
    env = _env(len(starts), x0)
    xs, first = [env.state()], None
    for k in range(steps):
        _, _, _, _, infos = env.step({a: np.zeros(2) for a in env.agents})
        xs.append(env.state())
        first = first or _first_incident(infos, k + 1)
    return np.stack(xs), first


def draw(path: Path) -> Path:
    """Draw every scene into one figure at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    from racing_env import track as tr
    from racing_env.dynamics import N_LAT, S
    from racing_env.render import car_colour, car_polygons
    from racing_env.vehicle import VehicleParams, stack_vehicles

    from racing_env.steward import RULES

    track = tr.straight(length=400.0)
    vehicles = stack_vehicles([VehicleParams()] * 2)
    scenes = [(rule, what, *race_scene(starts), (5.0, 60.0)) for rule, (what, starts) in SCENES.items()]
    xs, _, weave = defend(5, RULES)
    scenes.append(("weaving (optional)", "the car ahead moves left, right, left... as the car behind closes",
                   xs, weave, (5.0, 100.0)))
    fig, axes = plt.subplots(len(scenes), 1, figsize=(9, 2.1 * len(scenes)))
    for ax, (rule, what, xs, incident, xlim) in zip(axes, scenes):
        ax.axhline(6.0, color="0.3")
        ax.axhline(-6.0, color="0.3")
        contact = incident["step"] if incident else len(xs) - 1
        for k, alpha in ((0, 0.2), (contact, 0.55), (len(xs) - 1, 1.0)):
            for i, corners in enumerate(car_polygons(track, xs[k], vehicles)):
                ax.add_patch(Polygon(corners, closed=True, facecolor=np.asarray(car_colour(i)) / 255, alpha=alpha,
                                     edgecolor="k", linewidth=0.5))
        for i in range(xs.shape[1]):
            ax.plot(xs[:, i, S], xs[:, i, N_LAT], color=np.asarray(car_colour(i)) / 255, linewidth=0.6)
        fault = incident["at_fault_car"] if incident else None
        verdict = incident["verdict"] if incident else "no contact"
        ax.set_title(f"{rule}: {what} -> {verdict}" + (f", {fault} answers" if fault else ", nobody answers"),
                     fontsize=9)
        ax.set_xlim(*xlim)
        ax.set_ylim(-7.0, 7.0)
        ax.set_aspect("equal")
        ax.set_yticks([-6, 0, 6])
        ax.set_ylabel("n [m]")
    axes[-1].set_xlabel("s [m]: car_0 blue, car_1 orange, at the start, the contact and the end (fainter = earlier), "
                        "and their paths", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


if __name__ == "__main__":
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()
    print(draw(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures/rules.png")))
