"""racing_env: the race world (track, car model, game definition, PettingZoo/Gymnasium envs).

Importing the package switches JAX to 64-bit floats: the game solvers check Nash conditions
to 1e-8 and the env must be bit-for-bit deterministic, both of which want float64. It also
lets XLA:CPU compile each of the solvers' sequential loops into one kernel, if JAX has not
started yet (:mod:`racing_env.xla_setup`; ``RACING_XLA_LOOP_KERNELS=off`` opts out), and
runs single-device CPU computations on the calling thread, which makes an env step faster
(docs/performance.md; ``RACING_INLINE_DISPATCH=off`` keeps JAX's asynchronous dispatch).

The envs: :func:`parallel_env` (PettingZoo) and :class:`RaceEnv` (Gymnasium, registered as
``racing_env/Race-v0``), configured by :class:`RaceConfig`. Guides: docs/env.md (envs,
rewards, incidents, scenarios) and docs/model.md (car model, game, costs, tracks).
"""

import jax

from racing_env.xla_setup import configure_inline_dispatch, configure_loop_kernels

configure_loop_kernels()
configure_inline_dispatch()
jax.config.update("jax_enable_x64", True)

from racing_env.config import RaceConfig, RewardConfig  # noqa: E402
from racing_env.costs import CostWeights  # noqa: E402
from racing_env.env import RacingParallelEnv, parallel_env  # noqa: E402
from racing_env.game import RaceGame  # noqa: E402
from racing_env.single_agent import OpponentPool, RaceEnv, register  # noqa: E402
from racing_env.track import Track  # noqa: E402
from racing_env.vehicle import VehicleParams  # noqa: E402

register()

__all__ = [
    "CostWeights",
    "OpponentPool",
    "RaceConfig",
    "RaceEnv",
    "RaceGame",
    "RacingParallelEnv",
    "RewardConfig",
    "Track",
    "VehicleParams",
    "parallel_env",
]
