"""Cars without drag are what they were before drag was modelled: the drag-free classes'
PettingZoo race, game rollout, costs and dynamics Jacobians against those recorded by
tests/drag_free_baseline.py with the optimised programs the ``racing`` commands run.

Bit for bit where this run compiles as they do (``make test-all``, ``RACING_TEST_OPTIMIZED=1``).
The default run compiles with XLA:CPU's older code generator (tests/conftest.py), whose
rounding differs in the last bits, and code recorded before drag existed differs from the
recording by as much there: in that run the values agree to the rounding those differences
grow to over the race's 40 steps (one ulp, 2e-16 relative, measured; 1e-12 allowed)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import drag_free_baseline  # noqa: E402
from conftest import optimized_run  # noqa: E402

# slow: the paper's car, the default class, is held to its recorded races bit for bit in the
# default run (tests/test_race_core.py); this file adds the other drag-free classes
pytestmark = [pytest.mark.optimized, pytest.mark.slow]


def test_cars_without_drag_are_unchanged():
    recorded = json.loads(drag_free_baseline.BASELINE.read_text())
    now = drag_free_baseline.compute()
    for name in drag_free_baseline.CLASSES:
        for key, values in recorded[name].items():
            if optimized_run():
                assert now[name][key] == values, (name, key)
            else:
                old = np.array([float.fromhex(v) for v in values])
                new = np.array([float.fromhex(v) for v in now[name][key]])
                np.testing.assert_allclose(new, old, rtol=1e-12, atol=1e-300, err_msg=f"{name} {key}")
