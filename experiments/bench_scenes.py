"""The solver benches' scenes: the paper's scene for two and three cars, and a batch of its
perturbations (shared by :mod:`experiments.bench` and :mod:`experiments.bench_roofline`)."""

from __future__ import annotations

import numpy as np

#: v_max [m/s] of the bench's cars: the paper's ego and opponent, then the three-car scene's
#: second opponent.
BENCH_V_MAX = (20.0, 25.0, 24.0)


def solver_game(num_cars: int):
    """The paper's scene for 2 cars; for 3 cars a second opponent 2 m to the right."""
    from experiments.paper import paper_game
    from racing_env import CostWeights, RaceGame, VehicleParams

    game, x0 = paper_game()
    if num_cars == 2:
        return game, x0
    vehicles = [VehicleParams(v_max=v) for v in BENCH_V_MAX]
    game = RaceGame.create(game.track, vehicles, CostWeights(), dt=game.dt, horizon=game.horizon)
    third = x0[1].copy()
    third[2] = -2.0
    third[0] -= 4.0
    return game, np.vstack([x0, third])


def perturbed_scenes(x0: np.ndarray, batch: int) -> np.ndarray:
    """``batch`` copies of the paper's scene, the opponent's lateral offset and speed drawn
    at random (seed 0): ``(batch, 2, 6)``."""
    rng = np.random.default_rng(0)
    x0s = np.repeat(x0[None], batch, axis=0)
    x0s[:, 1, 2] += rng.uniform(-0.5, 0.5, batch)  # different lateral offsets of the opponent
    x0s[:, 1, 1] += rng.uniform(-1.0, 1.0, batch)
    return x0s
