"""experiments: the ``racing`` commands and what they orchestrate.

Tournaments, sweeps (one resumable job runner, :mod:`experiments.runner`, on local or Ray
backends), the paper's reproduction, convergence studies and benchmarks; the race they run
is declared once (:mod:`experiments.race_spec`). The RL layer, stable-baselines3 training,
behaviour cloning and policy widening, is the subpackage :mod:`experiments.rl`, imported
only by ``racing train``. No model or solver math lives here: the car, the game and its
costs are racing_env's, the solvers and agents planners'. Guides: README.md and docs/.
"""
