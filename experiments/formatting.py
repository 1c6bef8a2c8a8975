"""Formatting, and the means of optional numbers, shared by the experiments' tables,
progress lines and reports."""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np


def mean_or_none(values: Iterable[float | None]) -> float | None:
    """The mean of the values that are not None (None if there are none: e.g. the converged
    share of an agent that never plans)."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def share_with_interval(share: float | None, interval: tuple[float, float] | None) -> str:
    """A share and its interval as a console table shows them, e.g. ``0.62 [0.51, 0.72]``;
    ``-`` when there is no share (e.g. an agent that faced no rival)."""
    if share is None:
        return "-"
    lo, hi = interval
    return f"{share:.2f} [{lo:.2f}, {hi:.2f}]"


def or_dash(value: float | None, form: str) -> str:
    """``form`` (a ``str.format`` template such as ``"{:+.2f} s"``) applied to ``value``, or
    ``-`` when there is no value (e.g. a mean over no finished races)."""
    return "-" if value is None else form.format(value)


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    """A Markdown table's lines: the header, its rule and one line per row of cells."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(row) + " |" for row in rows)]
