"""racing_env: the race world (track, car model, game definition, PettingZoo/Gymnasium envs).

Importing the package switches JAX to 64-bit floats: the game solvers check Nash conditions
to 1e-8 and the env must be bit-for-bit deterministic, both of which want float64.
"""

import jax

jax.config.update("jax_enable_x64", True)

from racing_env.config import RaceConfig, RewardConfig  # noqa: E402
from racing_env.costs import CostWeights  # noqa: E402
from racing_env.env import RacingParallelEnv, parallel_env  # noqa: E402
from racing_env.game import RaceGame  # noqa: E402
from racing_env.single_agent import RaceEnv, register  # noqa: E402
from racing_env.track import Track  # noqa: E402
from racing_env.vehicle import VehicleParams  # noqa: E402

register()

__all__ = [
    "CostWeights",
    "RaceConfig",
    "RaceEnv",
    "RaceGame",
    "RacingParallelEnv",
    "RewardConfig",
    "Track",
    "VehicleParams",
    "parallel_env",
]
