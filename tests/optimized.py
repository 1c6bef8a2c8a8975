"""Running a test's part with the optimised programs users run.

The default test run compiles with XLA's backend optimisations mostly off
(``tests/conftest.py``): compiling is most of its time. A test whose claim is about the
optimised program's bits (a recording it wrote), or whose races run long enough that the
slower code costs more than the quicker compile saves, runs that part through
:func:`run_optimized`: a fresh Python process with the ``racing`` commands' JAX settings
(``configure_for_racing``: float64, loop kernels, inline dispatch), sharing the run's
compilation cache. In an optimised run (``RACING_TEST_OPTIMIZED=1``, ``make
test-all``) the child has the same settings as the test process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

QUICK_COMPILE_VAR = "JAX_DISABLE_MOST_OPTIMIZATIONS"
OPTIMIZED_VAR = "RACING_TEST_OPTIMIZED"
TESTS = Path(__file__).resolve().parent
_RESULT_MARK = "@@optimized-result@@"


def optimized_run() -> bool:
    """Whether this run compiles with XLA's full optimisations (``RACING_TEST_OPTIMIZED``)."""
    return os.environ.get(OPTIMIZED_VAR, "").strip().lower() in {"1", "true", "yes", "on"}


def run_optimized(code: str, timeout: float = 600.0) -> Any:
    """Run ``code`` in a fresh process with XLA's full optimisations and return the JSON
    value it leaves in ``result`` (a variable the code sets). ``tests/`` is on its import
    path. Raises ``AssertionError`` with the child's output tail if it fails."""
    script = (f"import json, sys\nsys.path.insert(0, {str(TESTS)!r})\n"
              "from racing_env.xla_setup import configure_for_racing\nconfigure_for_racing()\n"
              f"{code}\nprint({_RESULT_MARK!r} + json.dumps(result))\n")
    env = {k: v for k, v in os.environ.items() if k != QUICK_COMPILE_VAR}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout,
                          env={**env, OPTIMIZED_VAR: "1"})
    last = done.stdout.rstrip().rpartition("\n")[2]
    assert done.returncode == 0 and last.startswith(_RESULT_MARK), (
        f"the optimised child failed\n{done.stderr[-4000:]}\n{done.stdout[-1000:]}")
    return json.loads(last[len(_RESULT_MARK):])
