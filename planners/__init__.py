"""planners: game-theoretic and single-agent planners for the racing arena (JAX).

Importing it imports :mod:`racing_env` first, whose JAX settings (float64, the solvers'
loops compiled as single XLA:CPU kernels) must be in place before the first computation.
"""

import racing_env  # noqa: F401  (JAX settings, see racing_env.xla_setup)
