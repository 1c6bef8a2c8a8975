"""The reinforcement-learning layer: stable-baselines3 training against planner or scripted
opponents (:mod:`experiments.rl.train`, ``racing train``) on the vectorised races
(:mod:`experiments.rl.vec_env`, an SB3 ``VecEnv``), the evaluations and learning curve
of a policy in training (:mod:`experiments.rl.evaluation`), behaviour cloning of an expert
as a warm start (:mod:`experiments.rl.imitation`) and carrying a saved policy into a race
with more cars (:mod:`experiments.rl.widen`). The adapter that races a saved model as an
agent is :class:`planners.agents.SB3Agent`.

Only ``racing train`` imports this package, so the other commands never load torch or
stable-baselines3. Guide: docs/rl.md.
"""
