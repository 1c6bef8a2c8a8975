"""What the physics and the game give for cars without drag, recorded before drag existed;
tests/test_slipstream.py checks that they are unchanged bit for bit.

``python tests/drag_free_baseline.py`` writes ``tests/data/drag_free_baseline.json``: for the
drag-free classes (``paper``, ``f1tenth``), a PettingZoo race of three cars driven by seeded
random actions (every car's state after every step), and the planners' view of the game of
those cars (a rollout of seeded jerks, the players' costs along it, and the dynamics
Jacobians the iLQ solvers linearise), in float64 (``jax_enable_x64``, as the ``racing``
commands run, with XLA's full optimisations: tests/test_drag_free.py is an ``optimized``
module). Floats are stored as ``float.hex`` strings, exact.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

BASELINE = Path(__file__).parent / "data" / "drag_free_baseline.json"
CLASSES = ("paper", "f1tenth")
STEPS = 40
CARS = 3


def _hex(array) -> list:
    return [float(v).hex() for v in np.asarray(array, dtype=np.float64).ravel()]


def compute() -> dict[str, dict[str, list]]:
    """Every drag-free class's race states, rollout, costs and Jacobians (hex floats, flat);
    needs ``jax_enable_x64`` on."""
    import jax

    import racing_env
    from planners import race_problem
    from racing_env.car_classes import get_car

    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError("the drag-free baseline is float64: turn on jax_enable_x64")
    out = {}
    for name in CLASSES:
        car = get_car(name)
        env = racing_env.parallel_env(track="trefoil", num_agents=CARS, vehicles=car, max_steps=STEPS + 5)
        env.reset(seed=3)
        rng = np.random.default_rng(7)
        states = []
        for _ in range(STEPS):
            actions = {agent: rng.uniform(-1.0, 1.0, 2).astype(np.float32) for agent in env.agents}
            env.step(actions)
            states.append(np.asarray(env.state(), dtype=np.float64))
        game = env.game.replace(horizon=20)
        x0 = states[0]
        us = np.random.default_rng(11).normal(0.0, 5.0, (game.horizon, CARS, 2))
        xs = np.asarray(game.rollout(x0, us))
        costs = np.asarray(game.costs(xs, us))
        A, B = race_problem.race_dynamics_jacobians(game, 0, x0.reshape(-1), us[0])
        out[name] = {"states": _hex(states), "rollout": _hex(xs), "costs": _hex(costs),
                     "A": _hex(A), "B": _hex(B)}
    return out


if __name__ == "__main__":
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()  # float64 and XLA's settings, as the racing commands run
    BASELINE.write_text(json.dumps(compute()) + "\n")
    print(f"wrote {BASELINE}")
