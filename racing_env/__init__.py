"""racing_env: the race world (track, car model, game definition, PettingZoo/Gymnasium envs).

Importing the package changes nothing in JAX: no config, no XLA flag, no dispatch mode.
The race, the envs and the JAX learner run in the caller's precision (float32 with JAX's
default, float64 with ``jax_enable_x64`` on); the game solvers and their certificates need
float64 and refuse float32 with a clear ``RuntimeError``. The ``racing`` commands start with
:func:`racing_env.xla_setup.configure_for_racing`: float64, each solver loop compiled as one
XLA:CPU kernel, and single-device CPU computations on the calling thread. Call it
(``racing_env.configure_for_racing()``) at the top of a script, before the first JAX
computation, to run as the commands do (docs/performance.md, "XLA settings and dispatch").

The envs: :func:`parallel_env` (PettingZoo's parallel API), :func:`env` (PettingZoo's AEC
API, the same race with the cars acting in turn) and :class:`RaceEnv` (Gymnasium,
registered as ``racing_env/Race-v0``), configured by :class:`RaceConfig`. As in PettingZoo's
own environments, ``racing_env.env`` is the AEC factory; the module of the parallel env is
imported by name (``from racing_env.env import RacingParallelEnv``). Guides: docs/env.md (envs,
rewards, incidents, scenarios) and docs/model.md (car model, game, costs, tracks).
"""

from typing import Any

from pettingzoo import AECEnv

from racing_env.config import RaceConfig, RewardConfig
from racing_env.costs import CostWeights
from racing_env.env import RacingParallelEnv, parallel_env
from racing_env.game import RaceGame
from racing_env.single_agent import OpponentPool, RaceEnv, register
from racing_env.track import Track
from racing_env.vehicle import VehicleParams
from racing_env.xla_setup import configure_for_racing

register()


def env(**config: Any) -> AECEnv:
    """The race as a PettingZoo AEC env (PettingZoo's ``env()`` beside ``parallel_env()``):
    :func:`parallel_env` with ``config`` (:class:`RaceConfig` fields), turned into turns by
    ``pettingzoo.utils.conversions.parallel_to_aec``. The cars act one after another and the
    race steps once all have acted, so an AEC episode is the parallel env's, step for step;
    ``env.unwrapped`` is the :class:`RacingParallelEnv` (its ``state()`` and ``game``)."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env(**config))


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
    "configure_for_racing",
    "env",
    "parallel_env",
]
