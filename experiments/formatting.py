"""Formatting, and the means of optional numbers, shared by the experiments' tables,
progress lines and reports."""

from __future__ import annotations

from typing import Iterable

import numpy as np


def mean_or_none(values: Iterable[float | None]) -> float | None:
    """The mean of the values that are not None (None if there are none: e.g. the converged
    share of an agent that never plans)."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def or_dash(value: float | None, form: str) -> str:
    """``form`` (a ``str.format`` template such as ``"{:+.2f} s"``) applied to ``value``, or
    ``-`` when there is no value (e.g. a mean over no finished races)."""
    return "-" if value is None else form.format(value)
