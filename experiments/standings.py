"""Leaderboard statistics of race records, shared by the tournament, the sweep, the
exploitability study and the report.

A race record is what :func:`experiments.tournament.race_lineup` returns: the finishing
``order`` (agent specs) and per car its ``place``, ``finish_time``, incidents, action times
and solver shares. From records this module computes whether a car won
(:func:`won_race`), the 95% Wilson interval of a win rate (:func:`wilson_interval`) and a
leaderboard of agents (:func:`standings`: win rates, head to head, Plackett-Luce ratings,
finish times, solver health). It imports nothing of the run modules, so every one of them
(and :mod:`experiments.report`) can read it.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Sequence

import numpy as np


def wilson_interval(wins: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a win rate (``(0, 1)`` for no races)."""
    if n == 0:
        return (0.0, 1.0)
    p = wins / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def won_race(car: dict[str, Any], num_cars: int) -> bool:
    """Whether a car's record of a race of ``num_cars`` cars is a win: first place, and in a
    time trial (one car, always first) a finished lap."""
    return car["place"] == 1 and (num_cars > 1 or car["finish_time"] is not None)


def rating_ranks(order: Sequence[str]) -> tuple[list[str], list[float]]:
    """The agents of a race with finishing ``order`` (specs, first first; an agent may drive
    several cars) and their ranks for the Plackett-Luce update: each agent once, ranked by the
    mean place of its cars (equal means are a tie). With one car per agent, the order itself
    and the ranks 1, 2, ...

    Why one player per agent, ranked by its cars' mean place: an agent's cars are one driver
    (one spec, the same policy), so they share one rating. Making each car a member of its
    agent's openskill team would rate the team by the sum of its members' ratings, so an
    agent with four cars would count as a stronger unit than one with three for the same
    driving. The best place of its cars is biased the same way: of equally good drivers,
    the best of four cars beats the best of three more often than not. The mean place is
    not: where every car of the field is equally good, every car's place has the same
    distribution, and the mean place of an agent's cars has the same expectation, (N + 1) / 2,
    whatever their number. So a lineup that gives an agent more cars than another (an
    explicit lineup, or the extra cars of :func:`experiments.tournament.field_lineup` in
    one grid) does not favour it."""
    places: dict[str, list[int]] = {}
    for place, spec in enumerate(order, 1):
        places.setdefault(spec, []).append(place)
    specs = sorted(places, key=lambda spec: (np.mean(places[spec]), places[spec][0]))
    return specs, [float(np.mean(places[spec])) if len(places[spec]) > 1 else places[spec][0] for spec in specs]


def standings(names: Sequence[str], records: Sequence[dict[str, Any]], *, time_trial: bool) -> dict[str, Any]:
    """The leaderboard of agents ``names`` over race ``records`` taken in the order given
    (the ratings are updated race by race, so the order is part of the result).

    Returns ``{"rows": [...], "head_to_head": {"agents": names, "wins": matrix}}``: per agent
    its races (a car in a race: an agent with several cars in a field counts each), wins, win
    rate with its 95% Wilson interval, mean place, the share of the other agents' cars its
    cars beat (``beaten_share``, with a Wilson interval over those pairs: the place-based
    figure of a field, where a win rate says little), passes made and suffered
    (``overtakes``, ``overtaken``), Plackett-Luce rating (openskill, updated once per race
    with each agent ranked by its cars' mean place, :func:`rating_ranks`; ``rating`` is
    mu - 3 sigma), races finished, retired and faulted, contact steps, incidents its cars
    answered for (``faults``), mean
    finish-time margin over the other cars (races all finished), mean and best finish
    time, time off track (seconds, steps and races with any), mean action time, and for planners the mean shares of converged
    and of certified re-plans (None without any). Rows are ranked by rating, or in a time
    trial (``time_trial``) by races finished, then mean finish time; a time trial's ratings
    stay at the prior and its head-to-head matrix is zero.
    """
    from openskill.models import PlackettLuce

    names = list(names)
    model = PlackettLuce()
    ratings = {n: model.rating(name=n) for n in names}
    h2h = np.zeros((len(names), len(names)), dtype=int)
    stats = {n: {"races": 0, "wins": 0, "finished": 0, "retired": 0, "errors": 0, "collision_steps": 0, "faults": 0, "act_times": [],
                 "margins": [], "finish_times": [], "limit_ratios": [], "off_track_s": 0.0, "off_track_steps": 0,
                 "off_track_races": 0, "converged": [], "certified": [], "places": [], "beaten": 0, "faced": 0,
                 "overtakes": 0, "overtaken": 0} for n in names}
    for record in records:
        order = record["order"]
        if len(order) > 1:  # a time trial has no one to be rated against
            specs, ranks = rating_ranks(order)
            teams = [[ratings[n]] for n in specs]
            for n, [new] in zip(specs, model.rate(teams, ranks=ranks)):
                ratings[n] = new
        for a, b in itertools.combinations(order, 2):  # a finished ahead of b
            if a != b:
                h2h[names.index(a), names.index(b)] += 1
        for car in record["cars"]:
            st = stats[car["agent"]]
            st["races"] += 1
            st["wins"] += won_race(car, len(order))
            st["places"].append(car["place"])
            rivals = [other for other in record["cars"] if other["agent"] != car["agent"]]
            st["faced"] += len(rivals)
            st["beaten"] += sum(other["place"] > car["place"] for other in rivals)
            st["overtakes"] += car.get("overtakes", 0)  # records from before the count: none
            st["overtaken"] += car.get("overtaken", 0)
            st["finished"] += car["finish_time"] is not None
            if car["finish_time"] is not None:
                st["finish_times"].append(car["finish_time"])
                if car.get("limit_ratio") is not None:  # records from before the limit: none
                    st["limit_ratios"].append(car["limit_ratio"])
            st["off_track_s"] += car["time_off_track"]
            steps_off = car.get("off_track_steps")  # records from before the count: None for the agent
            if steps_off is None or st["off_track_steps"] is None:
                st["off_track_steps"] = st["off_track_races"] = None
            else:
                st["off_track_steps"] += steps_off
                st["off_track_races"] += steps_off > 0
            st["retired"] += bool(car.get("retired", False))  # records from before incident rules: none
            st["errors"] += car["error"] is not None
            st["collision_steps"] += car["collision_steps"]
            st["faults"] += car.get("faults", 0)  # records from before the steward: none
            if np.isfinite(car["act_time_mean_s"]):  # NaN: the car faulted before a timed action
                st["act_times"].append(car["act_time_mean_s"])
            if car.get("solver_converged_fraction") is not None:  # planners only
                st["converged"].append(car["solver_converged_fraction"])
            if car.get("certified_share") is not None:  # game agents with certify on; none in older records
                st["certified"].append(car["certified_share"])
            others = [c["finish_time"] for c in record["cars"] if c is not car]
            if others and car["finish_time"] is not None and all(t is not None for t in others):
                st["margins"].append(float(np.mean(others)) - car["finish_time"])
    rows = []
    for n in names:
        st = stats[n]
        lo, hi = wilson_interval(st["wins"], st["races"])
        beaten_lo, beaten_hi = wilson_interval(st["beaten"], st["faced"])
        r = ratings[n]
        rows.append({"agent": n, "races": st["races"], "wins": st["wins"],
                     "win_rate": st["wins"] / st["races"] if st["races"] else float("nan"),
                     "win_rate_ci95": [lo, hi],
                     # place (1 = first) over its cars' races; the share of the other agents' cars
                     # that finished behind its cars, with a Wilson interval over those pairs
                     "mean_place": float(np.mean(st["places"])) if st["places"] else None,
                     "beaten": st["beaten"], "faced": st["faced"],
                     "beaten_share": st["beaten"] / st["faced"] if st["faced"] else None,
                     "beaten_share_ci95": [beaten_lo, beaten_hi],
                     "overtakes": st["overtakes"], "overtaken": st["overtaken"], "rating_mu": r.mu, "rating_sigma": r.sigma,
                     "rating": r.mu - 3 * r.sigma, "finished": st["finished"], "retired": st["retired"], "errors": st["errors"], "collision_steps": st["collision_steps"],
                     # contact incidents the steward found its cars to blame for
                     "faults": st["faults"],
                     # finish-time lead over the mean of the other cars, in races where all finished
                     "mean_margin_s": float(np.mean(st["margins"])) if st["margins"] else None,
                     # over the races it finished
                     "mean_finish_time_s": float(np.mean(st["finish_times"])) if st["finish_times"] else None,
                     "best_finish_time_s": min(st["finish_times"]) if st["finish_times"] else None,
                     # finish time over the race's lap-time limit, over the races it finished (1.04: 4% slower)
                     "mean_limit_ratio": float(np.mean(st["limit_ratios"])) if st["limit_ratios"] else None,
                     "best_limit_ratio": min(st["limit_ratios"]) if st["limit_ratios"] else None,
                     "time_off_track_s": st["off_track_s"],
                     # steps after which the car was off the track, summed, and the races with any
                     # (None where a record predates the count)
                     "off_track_steps": st["off_track_steps"], "off_track_races": st["off_track_races"],
                     "mean_act_time_s": float(np.mean(st["act_times"])) if st["act_times"] else float("nan"),
                     # a planner's share of re-plans that converged, averaged over its races
                     "converged_fraction": float(np.mean(st["converged"])) if st["converged"] else None,
                     # its share of certified re-plans at a local Nash equilibrium, averaged over its races
                     "certified_share": float(np.mean(st["certified"])) if st["certified"] else None})
    if time_trial:  # the most races finished, then the fastest
        rows.sort(key=lambda row: (-row["finished"], row["mean_finish_time_s"] or math.inf))
    else:
        rows.sort(key=lambda row: -row["rating"])
    return {"rows": rows, "head_to_head": {"agents": names, "wins": h2h.tolist()}}
