"""Train rejax's learners on ``GymnaxRace`` with no adapter: a script, run in a subprocess by
``tests/test_gymnax.py`` (the JAX precision is per process, and the tests' process runs with
64-bit floats on) and, with a fresh virtual environment's Python, by
``tests/test_install_rejax.py``.

``python tests/rejax_train.py {on|off} ALGO[:normalize] ...``: with ``jax_enable_x64`` on or
off (set after importing racing_env, which changes no JAX setting), trains each learner a
few thousand steps against the lane keeper on the trefoil and prints one JSON line per
run: ``algo``, ``normalize``,
``x64``, ``steps``, ``seconds`` (compiling included), ``eval_returns`` (the evaluations'
mean returns, one per evaluation) and ``finite`` (every metric finite).
"""

from __future__ import annotations

import json
import sys
import time

import racing_env  # noqa: F401 - imported before the setting below, as a user would
import jax
import numpy as np


def train(name: str, normalize: bool, steps: int = 4096) -> dict:
    """Train rejax's ``name`` (ppo, sac, td3) for ``steps`` steps: its metrics as a dict."""
    import rejax

    from racing_env.vector import GymnaxRace

    env = GymnaxRace(opponents=["lane-keeping"], track="trefoil", max_steps=256)
    common = dict(env=env, env_params=env.default_params, total_timesteps=steps, eval_freq=steps // 2,
                  normalize_observations=normalize)
    if name == "ppo":
        algo = rejax.PPO.create(num_envs=16, num_steps=64, num_epochs=2, num_minibatches=4, **common)
    else:
        algo = getattr(rejax, name.upper()).create(num_envs=16, fill_buffer=512, buffer_size=8192, batch_size=128,
                                                   **common)
    started = time.perf_counter()
    train_state, (lengths, returns) = jax.jit(algo.train)(jax.random.key(0))
    jax.block_until_ready(train_state)
    seconds = time.perf_counter() - started
    # the learner's numbers (the races' state holds NaN finish times until a car finishes)
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(train_state.replace(env_state=None))
              if jax.numpy.issubdtype(getattr(leaf, "dtype", np.dtype(type(leaf))), jax.numpy.floating)]
    return {
        "algo": name, "normalize": normalize, "x64": bool(jax.config.read("jax_enable_x64")), "steps": steps,
        "seconds": seconds, "eval_returns": np.asarray(returns).mean(axis=1).tolist(),
        "eval_lengths": np.asarray(lengths).mean(axis=1).tolist(),
        "finite": bool(np.all(np.isfinite(returns)) and all(np.all(np.isfinite(leaf)) for leaf in leaves)),
    }


def main(argv: list[str]) -> None:
    jax.config.update("jax_enable_x64", argv[0] == "on")
    for run in argv[1:]:
        name, _, option = run.partition(":")
        print(json.dumps(train(name, option == "normalize")), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
