"""The drawings of docs/rules.md: each steward's rule on a scene that it decides.

``python -m experiments.rules_figure [PATH]`` races every scene of :data:`SCENES` in the
PettingZoo env (two coasting cars on a straight, contact physics and the steward at their
defaults) and draws, per scene, the cars' footprints at the start, at the contact and at the end, with the steward's verdict as the panel's title. Default path:
docs/figures/rules.png.
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


def race_scene(starts: tuple[tuple[float, ...], ...], steps: int = STEPS):
    """Coast the cars of a scene: their joint states ``(T+1, N, 6)`` and the first incident
    (the env's info of car 0) or None."""
    import racing_env
    from racing_env import track as tr

    x0 = np.zeros((len(starts), 6))
    for i, car in enumerate(starts):
        x0[i, :len(car)] = car
    env = racing_env.parallel_env(track=tr.straight(length=200.0), num_agents=len(starts), race_distance=190.0)
    env.reset(seed=0, options={"x0": x0})
    xs, first = [env.state()], None
    for k in range(steps):
        _, _, _, _, infos = env.step({a: np.zeros(2) for a in env.agents})
        xs.append(env.state())
        if first is None and infos["car_0"]["incidents"]:
            first = {"step": k + 1, **infos["car_0"]["incidents"][0],
                     "at_fault_car": next((a for a, info in infos.items()
                                           if any(i["at_fault"] for i in info["incidents"])), None)}
    return np.stack(xs), first


def draw(path: Path) -> Path:
    """Draw every scene into one figure at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    from racing_env import track as tr
    from racing_env.render import car_colour, car_polygons
    from racing_env.vehicle import VehicleParams, stack_vehicles

    track = tr.straight(length=200.0)
    vehicles = stack_vehicles([VehicleParams()] * 2)
    fig, axes = plt.subplots(len(SCENES), 1, figsize=(9, 2.1 * len(SCENES)))
    for ax, (rule, (what, starts)) in zip(axes, SCENES.items()):
        xs, incident = race_scene(starts)
        ax.axhline(6.0, color="0.3")
        ax.axhline(-6.0, color="0.3")
        contact = incident["step"] if incident else len(xs) - 1
        for k, alpha in ((0, 0.2), (contact, 0.55), (len(xs) - 1, 1.0)):
            for i, corners in enumerate(car_polygons(track, xs[k], vehicles)):
                ax.add_patch(Polygon(corners, closed=True, facecolor=np.asarray(car_colour(i)) / 255, alpha=alpha,
                                     edgecolor="k", linewidth=0.5))
        fault = incident["at_fault_car"] if incident else None
        verdict = incident["verdict"] if incident else "no contact"
        ax.set_title(f"{rule}: {what} -> {verdict}" + (f", {fault} answers" if fault else ", nobody answers"),
                     fontsize=9)
        ax.set_xlim(5.0, 60.0)
        ax.set_ylim(-7.0, 7.0)
        ax.set_aspect("equal")
        ax.set_yticks([-6, 0, 6])
        ax.set_ylabel("n [m]")
    axes[-1].set_xlabel(f"s [m]  (car_0 blue, car_1 orange: at the start, at the contact and {STEPS * 0.1:g} s "
                        f"after the start, fainter = earlier)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


if __name__ == "__main__":
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()
    print(draw(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures/rules.png")))
