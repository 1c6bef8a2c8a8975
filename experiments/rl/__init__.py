"""The reinforcement-learning layer: stable-baselines3 training against planner or scripted
opponents (:mod:`experiments.rl.train`, ``racing train``) on the vectorised races
(:mod:`experiments.rl.vec_env`, an SB3 ``VecEnv``) and PPO in JAX
(:mod:`experiments.rl.train_jax`); below both learners, what a run is
(:mod:`experiments.rl.config`, :class:`~experiments.rl.config.TrainConfig`) and what they share
(:mod:`experiments.rl.common`: the vectorised training race, the run folder's records);
the evaluations and learning curve of a policy in training
(:mod:`experiments.rl.evaluation`), behaviour cloning of an expert
as a warm start (:mod:`experiments.rl.imitation`) and carrying a saved policy into a race
with more cars (:mod:`experiments.rl.widen`). The adapter that races a saved model as an
agent is :class:`planners.agents.SB3Agent`.

Only ``racing train`` imports this package, so the other commands never load torch or
stable-baselines3. Guide: docs/rl.md.
"""
