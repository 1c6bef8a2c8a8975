"""Wall-clock timing of jitted calls, compilation kept apart from run time."""

from __future__ import annotations

import time
from typing import Any, Callable

import jax
import numpy as np


def time_jax_call(fn: Callable[[], Any], repeats: int = 3) -> tuple[Any, float, float]:
    """Call ``fn()`` once (compiling), then ``repeats`` times.

    Returns ``(result, first_call_s, median_later_call_s)``; results are blocked on so
    JAX's asynchronous dispatch does not hide the work.
    """
    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return result, first, float(np.median(runs))
