"""Formatting shared by the experiments' tables and progress lines."""

from __future__ import annotations


def or_dash(value: float | None, form: str) -> str:
    """``form`` (a ``str.format`` template such as ``"{:+.2f} s"``) applied to ``value``, or
    ``-`` when there is no value (e.g. a mean over no finished races)."""
    return "-" if value is None else form.format(value)
