"""The step budget of tournaments and sweeps: a wall-clock limit on an agent's action.

Races are deterministic: the same configuration gives the same races on any machine, in
this process or on workers, however busy. A wall-clock budget would make a busy machine
decide them, so by default there is none. A budget given (``step_budget_s``, ``racing
tournament --step-budget``) is *reported*: every car's record counts its actions slower than
the budget (``over_budget_steps``), and the run prints them, but the race goes on as
without it. ``enforce_budget`` (``--enforce-budget``) makes it decide: an action slower than
the budget (the first of a race exempt: it may compile) loses the race, which stops there
(:func:`experiments.race.run_race`). Guide: docs/sweeps.md.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

from racing_env.config import is_number


@dataclasses.dataclass(frozen=True, kw_only=True)
class StepBudget:
    """The step budget fields of ``TournamentConfig`` and ``SweepConfig``.

    Attributes:
        step_budget_s: an agent's action slower than this [s] is counted in its car's record
            (``over_budget_steps``); None (the default): no budget, no count.
        enforce_budget: such an action loses the race (the race stops at it); needs
            ``step_budget_s``.
    """

    step_budget_s: float | None = None
    enforce_budget: bool = False

    def check_budget(self) -> None:
        """Refuse a budget that is not a number of seconds > 0, and enforcement without one."""
        budget = self.step_budget_s
        if budget is not None and (not is_number(budget) or not budget > 0):
            # a budget of 0 s would count (or fault) every action
            raise ValueError(f"step_budget_s must be a number of seconds > 0 (or left out: no budget), got {budget!r}")
        if not isinstance(self.enforce_budget, bool):
            raise ValueError(f"enforce_budget must be true or false, got {self.enforce_budget!r}")
        if self.enforce_budget and budget is None:
            raise ValueError("enforce_budget needs a step budget to enforce: give step_budget_s (--step-budget SECONDS)")

    @property
    def enforced_budget_s(self) -> float | None:
        """The budget an action must meet to stay in its race: ``step_budget_s`` when
        enforced, else None."""
        return self.step_budget_s if self.enforce_budget else None

    def added_later(self, fields: tuple[str, ...]) -> tuple[str, ...]:
        """The fields left out of the run's settings file at their defaults (``fields``),
        and ``enforce_budget`` without a budget: a run written before it existed resumes
        when it has no budget (nothing changed), not when it had one (its budget was
        enforced, a budget now is reported)."""
        return fields + (("enforce_budget",) if self.step_budget_s is None else ())


def over_budget(act_times: Sequence[float], budget_s: float | None) -> int | None:
    """How many of a car's action times [s] exceed ``budget_s`` (None without a budget)."""
    return None if budget_s is None else sum(t > budget_s for t in act_times)


def budget_line(cars: Sequence[dict[str, Any]], budget: StepBudget) -> str | None:
    """What a run's console says about its budget, from its cars' records (each with
    ``agent`` and ``over_budget_steps``): the actions over it by agent, and whether they
    decided races. None without a budget."""
    if budget.step_budget_s is None:
        return None
    counts: dict[str, int] = {}
    for car in cars:
        counts[car["agent"]] = counts.get(car["agent"], 0) + (car.get("over_budget_steps") or 0)
    over = {agent: n for agent, n in counts.items() if n}
    if not over:
        return f"step budget {budget.step_budget_s:g} s: no action over it"
    by_agent = ", ".join(f"{agent} {n}" for agent, n in over.items())
    rule = ("enforced: each such car lost its race" if budget.enforce_budget
            else "reported only, the races went on (--enforce-budget or enforce_budget makes such an action lose)")
    return f"step budget {budget.step_budget_s:g} s, actions over it: {by_agent} ({rule})"
