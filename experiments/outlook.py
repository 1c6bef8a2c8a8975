"""The page of a study of the seed paper's outlook (the study of docs/studies/outlook.toml),
generated from the study's run folder, and the check of a page against its run.

The study (:mod:`experiments.study`, e.g. ``docs/studies/outlook.toml``) names its parts by
what they race: ``duel-*`` two agents against each other, ``fields`` fields of the same
agents, ``place-*`` a planner with its weights switched by its place (first in the lineup)
against itself unswitched. Each part races its circuits with the car classes of its ``car``
parameter. From the run folder's records (``results.jsonl``), settings (``study.json``) and
run log (``run.json``) the page gives:

* per agent, over its duels, per car class: the win rate (95% Wilson interval), the mean
  finish-time margin, at-fault incidents and time off the track per race and the lap time
  over the car class's limit (95% bootstrap intervals, :mod:`experiments.claims`);
* the duels' win-rate matrix (also a figure), the margins' distributions (a figure) and,
  where the run kept its replays, a map per car class of where on each circuit the duels'
  passes happened (:func:`duel_passes`, :func:`draw_pass_maps`);
* every claim of the paper's outlook and of Rowold et al. (arXiv 2402.01918) as a head-to-head
  win rate or a paired comparison against the same opponents (:func:`experiments.claims.compare`),
  overall, per car class and per circuit class (fast or slow, many or few corners: each
  half of the study's circuits by the AV-21's mean speed at its lap-time limit and by
  :func:`racing_env.track.count_corners`), with its verdict: reproduced, refuted or not
  separated (the interval contains no difference); the verdicts also as one table at the
  top, and for a head-to-head claim the other measures in the same races
  (:func:`experiments.claims.duel_difference`);
* the fields (mean place per agent) and the place-switched weights (win rate against the
  unswitched planner).

``racing study report RUN --page PAGE [--figures DIR]`` writes the page (and its figures);
``racing study check PAGE --run RUN`` computes the page again from RUN and compares it line
by line: every number on it comes from the run, so a changed number (or a run that changed)
fails the check. The figures are drawn from the same numbers and are not compared. The
authors' reading of the results, between the lines ``<!-- reading -->`` and
``<!-- /reading -->``, is prose: the report keeps it where it was when it writes the page
again, and the check leaves it out.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from experiments.claims import (CarRace, Comparison, MEASURES, Mean, agent_mean, bootstrap_mean, compare,
                                duel_difference, head_to_head)
from experiments.formatting import markdown_table
from experiments.jsonl import read_jsonl
from experiments.standings import wilson_interval, won_race
from experiments.study import CONFIG, RESULTS, RUN_LOG

FIGURE_WIN_RATES = "outlook-win-rates.png"
FIGURE_MARGINS = "outlook-margins.png"
FIGURE_PASSES = "outlook-pass-map-{car}.png"
SCOPES = ("all", "av21", "paper", "fast", "slow", "many corners", "few corners")
"""The subsets every claim is judged on: every duel, each car class, each circuit class."""
PER_RACE = ("win", "margin [s]", "at-fault incidents", "time off track [s]", "lap time over the limit")
"""The measures of the per-agent table."""
SEQUENTIAL, OPEN_LOOP, FEEDBACK = "ilqr", "ilqgame-ol", "ilqgame-fb"
SPEED_CLASS = "av21"  # the car class whose limit lap ranks the circuits fast or slow


@dataclasses.dataclass(frozen=True)
class Claim:
    """A claim: ``a`` beats ``b`` head to head (``measure`` None: ``a``'s win rate in their
    duels is above one half) or ``a`` is higher than ``b`` on ``measure`` against the same
    opponents (a paired comparison)."""

    source: str
    text: str
    a: str
    b: str
    measure: str | None = None


CLAIMS = (
    Claim("outlook", "feedback beats open-loop iLQGame head to head", FEEDBACK, OPEN_LOOP),
    Claim("outlook", "feedback wins more than open loop against the same opponents", FEEDBACK, OPEN_LOOP, "win"),
    Claim("outlook", "feedback iLQGame beats the sequential planner (iLQR)", FEEDBACK, SEQUENTIAL),
    Claim("outlook", "open-loop iLQGame beats the sequential planner (iLQR)", OPEN_LOOP, SEQUENTIAL),
    Claim("2402.01918", "more aggressive: feedback passes more than iLQR", FEEDBACK, SEQUENTIAL, "passes made"),
    Claim("2402.01918", "more aggressive: open loop passes more than iLQR", OPEN_LOOP, SEQUENTIAL, "passes made"),
    Claim("2402.01918", "less conservative: iLQR laps further over the limit than feedback", SEQUENTIAL, FEEDBACK,
          "lap time over the limit"),
    Claim("2402.01918", "less conservative: iLQR laps further over the limit than open loop", SEQUENTIAL, OPEN_LOOP,
          "lap time over the limit"),
    Claim("2402.01918", "yet safer: iLQR causes more incidents than feedback", SEQUENTIAL, FEEDBACK,
          "at-fault incidents"),
    Claim("2402.01918", "yet safer: iLQR causes more incidents than open loop", SEQUENTIAL, OPEN_LOOP,
          "at-fault incidents"),
)


def agent_name(spec: str) -> str:
    """The agent of a spec, without its options (``ilqgame-fb:iterations=2`` -> ``ilqgame-fb``)."""
    return spec.split(":", 1)[0]


@dataclasses.dataclass(frozen=True)
class Run:
    """A study's run folder read back: its ``settings`` (``study.json``), ``records`` in
    schedule order of the parts, and ``log`` (``run.json``)."""

    settings: dict[str, Any]
    records: tuple[dict[str, Any], ...]
    log: dict[str, Any]

    @classmethod
    def read(cls, folder: Path) -> "Run":
        folder = Path(folder)
        for name in (CONFIG, RESULTS):
            if not (folder / name).is_file():
                raise ValueError(f"{folder} is not a study's run folder: it has no {name}")
        log = json.loads((folder / RUN_LOG).read_text()) if (folder / RUN_LOG).is_file() else {"invocations": []}
        records = sorted(read_jsonl(folder / RESULTS), key=lambda r: r["id"])  # an order that does not depend on workers
        return cls(settings=json.loads((folder / CONFIG).read_text()), records=tuple(records), log=log)

    def part_records(self, prefix: str) -> list[dict[str, Any]]:
        return [r for r in self.records if r["part"].startswith(prefix)]

    def point(self, record: dict[str, Any]) -> dict[str, str]:
        """The circuit (``track``) and ``car`` class of a record's race: its point's, else its
        part's settings (a part's ``car`` left out of ``study.json`` is the default, the paper's)."""
        part = self.settings["parts"][record["part"]]
        return {"track": record["point"].get("track", part["track"]),
                "car": record["point"].get("car", part.get("car", "paper"))}


def duel_rows(run: Run) -> list[tuple[CarRace, dict[str, str]]]:
    """Each car's race in the duels of ``run`` (its ``duel-*`` parts' records, two agents
    each), as a :class:`experiments.claims.CarRace` whose ``track`` is ``circuit/car class``
    (so a paired comparison matches circuit, car, grid, slot and opponent), with the race's
    circuit and car (:meth:`Run.point`)."""
    rows = []
    for record in run.part_records("duel-"):
        cars = record["agents"]
        if len(cars) != 2:
            raise ValueError(f"race {record['id']!r} of a duel part has {len(cars)} cars")
        race = {"cars": cars}
        point = run.point(record)
        for me, other in ((0, 1), (1, 0)):
            car = cars[me]
            rows.append((CarRace(agent=agent_name(car["agent"]), opponent=agent_name(cars[other]["agent"]),
                                 track=f"{point['track']}/{point['car']}", grid=int(record["grid"]),
                                 slot=int(car["start_place"]), values={n: f(car, race) for n, f in MEASURES.items()}),
                         point))
    return rows


def circuit_classes(circuits: Sequence[str]) -> dict[str, dict[str, str]]:
    """Per circuit its ``speed`` class (``fast``: the mean speed of the fastest car class,
    :data:`SPEED_CLASS`, at its lap-time limit at or above the median of ``circuits``, else
    ``slow``; the paper's car is held to its top speed on most straights, so its mean speed
    ranks circuits by their tightest corners) and ``corners`` class (``many``:
    :func:`racing_env.track.count_corners` at or above the median, else ``few``)."""
    from racing_env.car_classes import get_car
    from racing_env.limits import lap_time_limit
    from racing_env.track import count_corners, get_track

    speed, corners = {}, {}
    car = get_car(SPEED_CLASS)
    for name in sorted(set(circuits)):
        track = get_track(name)
        speed[name] = track.length / lap_time_limit(track, car)
        corners[name] = count_corners(track)
    mid_speed, mid_corners = float(np.median(list(speed.values()))), float(np.median(list(corners.values())))
    return {name: {"speed": "fast" if speed[name] >= mid_speed else "slow",
                   "corners": "many" if corners[name] >= mid_corners else "few"} for name in speed}


def in_scope(point: dict[str, str], scope: str, classes: dict[str, dict[str, str]]) -> bool:
    """Whether a race at ``point`` (its ``track`` and ``car``) is in ``scope`` (:data:`SCOPES`)."""
    if scope == "all":
        return True
    if scope in ("av21", "paper"):
        return point["car"] == scope
    circuit = classes[point["track"]]
    return circuit["speed"] == scope if scope in ("fast", "slow") else circuit["corners"] == scope.split()[0]


# --- formatting ------------------------------------------------------------------------------------
def _number(value: float, form: str) -> str:
    return "-" if value is None or not np.isfinite(value) else form.format(value)


def _mean(mean: Mean, form: str) -> str:
    if mean.n == 0:
        return "-"
    return f"{_number(mean.value, form)} [{_number(mean.low, form)}, {_number(mean.high, form)}]"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    return [*markdown_table(header, rows), ""]


FORMS = {"win": "{:.2f}", "margin [s]": "{:+.2f}", "at-fault incidents": "{:.2f}", "time off track [s]": "{:.2f}",
         "lap time over the limit": "{:.3f}", "passes made": "{:.2f}", "contact": "{:.2f}"}


def _verdict(low: float, high: float, middle: float) -> str:
    """A win rate's verdict against one half (``middle``) from its Wilson interval."""
    return "reproduced" if low > middle else "refuted" if high < middle else "not separated"


def judge(claim: Claim, rows: Sequence[CarRace]) -> str:
    """A claim's cell on ``rows``: the head-to-head win rate with its interval, or the paired
    difference with its interval, and the verdict."""
    return _assess(claim, rows)[0]


def _assess(claim: Claim, rows: Sequence[CarRace]) -> tuple[str, str]:
    """A claim's cell on ``rows`` (:func:`judge`) and its verdict alone (``not raced``: no
    duel of the two, ``not measured``: no matched races)."""
    if claim.measure is None:
        wins = [r.values["win"] for r in rows if r.agent == claim.a and r.opponent == claim.b]
        if not wins:
            return "not raced", "not raced"
        low, high = wilson_interval(int(sum(wins)), len(wins))
        verdict = _verdict(low, high, 0.5)
        return f"{np.mean(wins):.2f} [{low:.2f}, {high:.2f}] of {len(wins)}: {verdict}", verdict
    comparison = compare(rows, claim.a, claim.b, claim.measure)
    if comparison.pairs == 0:  # no matched races, or the measure undefined in them (a lap time: no full laps)
        return "not measured", "not measured"
    return f"{_difference(comparison)} of {comparison.pairs} pairs: {comparison.verdict}", comparison.verdict


def _difference(comparison: Comparison) -> str:
    """A comparison's difference with its interval, signed."""
    form = FORMS[comparison.measure]
    form = form if "+" in form else form.replace(":", ":+")
    return f"{form.format(comparison.difference)} [{form.format(comparison.low)}, {form.format(comparison.high)}]"


def _in_their_duels(claim: Claim, duels: Sequence[tuple[CarRace, dict[str, str]]],
                    classes: dict[str, dict[str, str]]) -> list[str]:
    """A head-to-head claim's other measures, per scope: ``a``'s margin over ``b`` and ``a``'s
    at-fault incidents, time off the track and lap time over the limit less ``b``'s in the
    same race, with 95% bootstrap intervals."""
    table = []
    for scope in SCOPES:
        rows = [row for row, point in duels if in_scope(point, scope, classes)]
        margin = agent_mean(rows, claim.a, "margin [s]", opponents=[claim.b])
        cells = [_mean(margin, FORMS["margin [s]"])]
        for measure in PER_RACE[2:]:
            comparison = duel_difference(rows, claim.a, claim.b, measure)
            cells.append(f"{_difference(comparison)} ({comparison.pairs})" if comparison.pairs else "-")
        table.append([scope, *cells])
    return [f"In their duels: {claim.a}'s margin over {claim.b}, and {claim.a}'s measure less {claim.b}'s in the "
            "same race (races).", "", *_table(["races", "margin [s]", *(f"{m}, difference" for m in PER_RACE[2:])],
                                               table)]


# --- the page ---------------------------------------------------------------------------------------
def page(run: Run, run_name: str, study_file: str, figures: str | None = None,
         pass_maps: Sequence[str] = ()) -> str:
    """The page's Markdown, every number from ``run`` (module docstring); ``run_name`` and
    ``study_file`` are how the page names the run folder and the study's file,
    ``figures`` the folder of the figures relative to the page (None: no figures),
    ``pass_maps`` the file names of its pass maps there (drawn from the replays)."""
    duels = duel_rows(run)
    rows = [row for row, _ in duels]
    points = [point for _, point in duels]
    classes = circuit_classes({point["track"] for point in points}) if points else {}
    agents = sorted({row.agent for row in rows})
    lines = [f"# {run.settings['question']}", "",
             f"<!-- generated by `racing study report {run_name} --page PAGE`; every number below comes from that "
             f"run folder: `racing study check PAGE --run {run_name}` -->", ""]
    lines += _provenance(run, run_name, study_file)
    lines += ["## Verdicts", "",
              "Each claim (below, with its numbers) on every duel, each car class and each circuit class.", ""]
    lines += _table(["claim", *SCOPES], [[claim.text, *(_assess(claim, [row for row, point in duels
                                                                         if in_scope(point, scope, classes)])[1]
                                                       for scope in SCOPES)] for claim in CLAIMS])
    lines += ["## Agents in their duels", "",
              "Each agent over all its duels (both slots, every circuit), per car class: the win rate with its 95% "
              "Wilson interval, the others with 95% bootstrap intervals (margins over the races both cars finished, "
              "lap times over the limit over the races the car finished).", ""]
    for scope in ("all", "av21", "paper"):
        scoped = [row for row, point in duels if in_scope(point, scope, classes)]
        if not scoped:
            continue
        lines += [f"**{scope if scope != 'all' else 'Both cars'}**" + (" car" if scope != "all" else ""), ""]
        table = [[agent, str(agent_mean(scoped, agent, "win").n),
                  *(_mean(agent_mean(scoped, agent, measure), FORMS[measure]) for measure in PER_RACE)]
                 for agent in agents]
        lines += _table(["agent", "races", *PER_RACE], table)
    lines += ["## Head to head", "", "The row agent's win rate against the column agent in their duels (races).", ""]
    matrix = head_to_head(rows, agents)
    counts = {(a, b): sum(1 for r in rows if r.agent == a and r.opponent == b) for a in agents for b in agents}
    lines += _table(["", *agents], [[a, *("-" if i == j or counts[a, b] == 0 else f"{matrix[i, j]:.2f} ({counts[a, b]})"
                                          for j, b in enumerate(agents))] for i, a in enumerate(agents)])
    if figures is not None:
        lines += [f"![Win rates]({figures}/{FIGURE_WIN_RATES})", "", f"![Margins]({figures}/{FIGURE_MARGINS})", ""]
        for name in pass_maps:
            lines += [f"![Where the passes happened]({figures}/{name})", ""]
    lines += ["## The claims", "",
              "Head to head: the first agent's win rate against the second (95% Wilson interval); reproduced when the "
              "interval lies above one half. Paired: the first agent's mean less the second's over races against the "
              "same opponent on the same circuit, car, grid and slot (95% bootstrap interval); reproduced when the "
              "interval lies above zero, refuted below, not separated when it holds zero. Circuit classes: "
              + _class_line(classes) + ".", ""]
    for claim in CLAIMS:
        lines += [f"**{claim.text}** ({'paper outlook' if claim.source == 'outlook' else 'arXiv ' + claim.source}; "
                  + ("head to head" if claim.measure is None else f"paired, {claim.measure}") + ")", ""]
        lines += _table(["races", "result"], [[scope, judge(claim, [row for row, point in duels
                                                                     if in_scope(point, scope, classes)])]
                                              for scope in SCOPES])
        if claim.measure is None and any(row.agent == claim.a and row.opponent == claim.b for row in rows):
            lines += _in_their_duels(claim, duels, classes)
    lines += _fields(run)
    lines += _place(run)
    return "\n".join(lines).rstrip() + "\n"


def _provenance(run: Run, run_name: str, study_file: str) -> list[str]:
    invocations = run.log.get("invocations", [])
    seconds = sum(i["seconds"] for i in invocations)
    commits = sorted({i["commit"] for i in invocations if i.get("commit")})
    machines = sorted({f"{i['cpu']} ({i['cpu_count']} CPUs), {i['backend']} backend, workers: {i['workers']}"
                       for i in invocations})
    parts = run.settings.get("parts", {})
    timed = sum(i["races"] for i in invocations)
    untimed = len(run.records) - timed
    pace = f", {seconds / timed:.1f} s a race" if timed else ""
    return [f"**Study:** `{study_file}` ({len(parts)} parts); {len(run.records)} races recorded. Reproduce: "
            f"`racing study run {study_file} --out {run_name}`, then `racing study report {run_name} --page PAGE`.", "",
            f"**Ran:** {len(invocations)} invocation(s) of `racing study run`, {seconds / 3600:.2f} h for "
            f"{timed} races{pace}"
            + (f" ({untimed} more races were run by invocations killed before they logged their time)"
               if untimed > 0 else "")
            + f"; commit(s) {', '.join(f'`{c}`' for c in commits) or 'unknown'}; "
            f"{'; '.join(machines) or 'machine unknown'}.", ""]


def _class_line(classes: dict[str, dict[str, str]]) -> str:
    def names(key: str, value: str) -> str:
        return ", ".join(name for name, c in sorted(classes.items()) if c[key] == value) or "none"
    return f"fast: {names('speed', 'fast')}; many corners: {names('corners', 'many')}"


CAR_SCOPES = ("both", "av21", "paper")
"""The car classes the fields and the place-switched weights are given for (``both``: pooled)."""


def _by_car(run: Run, records: Sequence[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    """``records`` pooled and per car class, leaving out a class they do not race."""
    groups = [(car, [r for r in records if car == "both" or run.point(r)["car"] == car]) for car in CAR_SCOPES]
    return [(car, group) for car, group in groups if group]


def _fields(run: Run) -> list[str]:
    records = run.part_records("fields")
    if not records:
        return []
    table = []
    for car, group in _by_car(run, records):
        places: dict[str, list[float]] = {}
        faults: dict[str, list[float]] = {}
        wins: dict[str, int] = {}
        for record in group:
            for entry in record["agents"]:
                name = agent_name(entry["agent"])
                places.setdefault(name, []).append(float(entry["place"]))
                faults.setdefault(name, []).append(float(entry["faults"]))
                wins[name] = wins.get(name, 0) + int(won_race(entry, len(record["agents"])))
        for name in sorted(places):
            table.append([name, car, str(len(places[name])), _mean(bootstrap_mean(places[name]), "{:.2f}"),
                          str(wins[name]), _mean(bootstrap_mean(faults[name]), "{:.2f}")])
    sizes = sorted({len(r["agents"]) for r in records})
    return ["## Fields", "", f"{len(records)} fields of {', '.join(map(str, sizes))} cars: each agent's cars' places "
            "and at-fault incidents per car (means with 95% bootstrap intervals; cars of one field are not "
            "independent, read them as rough) and wins, both car classes pooled and each alone.", "",
            *_table(["agent", "car", "cars raced", "mean place", "wins", "at-fault incidents"], table)]


def _place(run: Run) -> list[str]:
    records = run.part_records("place-")
    if not records:
        return []
    table = []
    for part in sorted({r["part"] for r in records}):
        for car, mine in _by_car(run, [r for r in records if r["part"] == part]):
            # the switched planner is the lineup's first agent (agent index 0 of the sweep record)
            wins = [int(won_race(r["agents"][0], 2)) for r in mine]
            margins = [MEASURES["margin [s]"](r["agents"][0], {"cars": r["agents"]}) for r in mine]
            low, high = wilson_interval(sum(wins), len(wins))
            mean_margin = bootstrap_mean(margins)
            table.append([agent_name(mine[0]["agents"][0]["agent"]), car, str(len(wins)),
                          f"{np.mean(wins):.2f} [{low:.2f}, {high:.2f}]: {_verdict(low, high, 0.5)}",
                          _mean(mean_margin, "{:+.2f}")])
    return ["## Weights switched by place", "",
            "Each game planner with its weights switched by its place against itself unswitched: the switched "
            "planner's win rate (95% Wilson interval; reproduced: above one half) and mean margin [s], both car "
            "classes pooled and each alone.", "",
            *_table(["planner", "car", "races", "win rate of the switched", "mean margin [s]"], table)]


# --- figures ----------------------------------------------------------------------------------------
def draw_figures(run: Run, folder: Path) -> list[Path]:
    """The win-rate matrix and the margins' distributions per agent and car class, as PNGs in
    ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    duels = duel_rows(run)
    rows = [row for row, _ in duels]
    agents = sorted({row.agent for row in rows})
    folder.mkdir(parents=True, exist_ok=True)
    matrix = head_to_head(rows, agents)
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    image = ax.imshow(matrix, vmin=0.0, vmax=1.0, cmap="RdBu")
    for i in range(len(agents)):
        for j in range(len(agents)):
            if np.isfinite(matrix[i, j]):
                ax.text(j, i, f"{matrix[i, j]:.2f}", ha="center", va="center", fontsize=9)
    ax.set_xticks(range(len(agents)), agents, rotation=30, ha="right")
    ax.set_yticks(range(len(agents)), agents)
    ax.set_title("win rate of the row agent against the column agent")
    fig.colorbar(image, ax=ax, shrink=0.8)
    fig.tight_layout()
    paths = [folder / FIGURE_WIN_RATES]
    fig.savefig(paths[0], dpi=110, metadata={"Software": None})
    plt.close(fig)

    cars = sorted({point["car"] for _, point in duels})
    fig, axes = plt.subplots(1, len(cars), figsize=(5.5 * len(cars), 4.2), squeeze=False, sharey=True)
    for ax, car in zip(axes[0], cars):
        data = [[row.values["margin [s]"] for row, point in duels if row.agent == agent and point["car"] == car
                 and np.isfinite(row.values["margin [s]"])] for agent in agents]
        ax.boxplot([d if d else [np.nan] for d in data], showfliers=False)
        ax.set_xticks(range(1, len(agents) + 1), agents, rotation=30, ha="right")
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_title(f"{car}: finish-time margin in duels [s]")
    fig.tight_layout()
    paths.append(folder / FIGURE_MARGINS)
    fig.savefig(paths[1], dpi=110, metadata={"Software": None})
    plt.close(fig)
    return paths


def duel_passes(folder: Path) -> list[dict[str, Any]]:
    """Every pass in the duels of run folder ``folder`` that kept its replays: per pass the
    circuit (``track``), ``car`` class, the passer's ``lap_s`` [m] and position ``x``, ``y`` [m],
    and its ``zone`` (:func:`experiments.pass_map.track_zones` of that car there)."""
    from experiments.pass_map import ZONES, track_zones, zone_at
    from experiments.replay import load_replay, recorded_races
    from experiments.tournament import pass_events
    from racing_env.car_classes import get_car
    from racing_env.render import RACING
    from racing_env.track import get_track

    run = Run.read(folder)
    zones: dict[tuple[str, str], Any] = {}
    passes = []
    for race in recorded_races(folder):
        record = race["record"]
        if not record["part"].startswith("duel-"):
            continue
        point = run.point(record)
        name, car = point["track"], point["car"]
        track = get_track(name)
        if (name, car) not in zones:
            zones[name, car] = track_zones(track, get_car(car))[0]
        replay = load_replay(race["path"])
        for step, passer, _ in pass_events(replay.xs[:, :, 0], replay.status == RACING):
            lap_s = float(np.mod(replay.xs[step, passer, 0], track.length))
            x, y, _ = track.to_cartesian(lap_s, float(replay.xs[step, passer, 2]))
            zone = ZONES[int(zone_at(np.array([lap_s]), zones[name, car], track.ds, track.length)[0])]
            passes.append({"track": name, "car": car, "lap_s": lap_s, "x": float(x), "y": float(y), "zone": zone})
    return passes


def draw_pass_maps(passes: Sequence[dict[str, Any]], circuits: Sequence[str], folder: Path) -> list[Path]:
    """Per car class, every circuit's outline with the passes of its duels marked by zone
    (:data:`FIGURE_PASSES`), circuits in a grid of small maps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racing_env.track import get_track

    colours = {"braking": "#d62728", "corner": "#1f77b4", "straight": "#2ca02c"}
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for car in sorted({p["car"] for p in passes}):
        columns = min(5, len(circuits))
        grid_rows = -(-len(circuits) // columns)
        fig, axes = plt.subplots(grid_rows, columns, figsize=(3.2 * columns, 3.2 * grid_rows), squeeze=False)
        for ax, name in zip(axes.flat, circuits):
            track = get_track(name)
            for edge in track.boundaries():
                ax.plot(*np.vstack([edge, edge[:1]]).T, color="0.6", lw=0.5)
            mine = [p for p in passes if p["car"] == car and p["track"] == name]
            for zone, colour in colours.items():
                here = [p for p in mine if p["zone"] == zone]
                ax.scatter([p["x"] for p in here], [p["y"] for p in here], s=9, color=colour, label=zone)
            ax.set_title(f"{name}: {len(mine)}", fontsize=8)
            ax.set_aspect("equal")
            ax.axis("off")
        for ax in list(axes.flat)[len(circuits):]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=6, loc="lower left", title="zone", title_fontsize=6)
        fig.suptitle(f"{car}: where the duels' passes happened (circuit: passes)", fontsize=11)
        fig.tight_layout()
        path = folder / FIGURE_PASSES.format(car=car)
        fig.savefig(path, dpi=90, metadata={"Software": None})
        plt.close(fig)
        paths.append(path)
    return paths


# --- commands ---------------------------------------------------------------------------------------
def write_page(run_folder: Path, page_path: Path, study_file: str, figures: Path | None = None) -> Path:
    """Write the page of ``run_folder`` to ``page_path`` (and its figures to ``figures``)."""
    run = Run.read(run_folder)
    relative, pass_maps = None, []
    if figures is not None:
        draw_figures(run, figures)
        relative = _relative(figures, page_path.parent)
        passes = duel_passes(run_folder)
        circuits = sorted({run.point(r)["track"] for r in run.part_records("duel-")})
        pass_maps = [path.name for path in draw_pass_maps(passes, circuits, figures)] if passes else []
    text = page(run, run_folder.name, study_file, relative, pass_maps)
    reading = _reading(page_path.read_text()) if page_path.is_file() else []
    if reading:  # the authors' reading of the page before, kept in its place
        lines = text.splitlines()
        at = lines.index(_READING_BEFORE)
        text = "\n".join(lines[:at] + reading + [""] + lines[at:]) + "\n"
    page_path.parent.mkdir(parents=True, exist_ok=True)
    page_path.write_text(_with_source(text, run_folder, study_file, relative, pass_maps))
    return page_path


_SOURCE = "<!-- source: "
READING_START, READING_END = "<!-- reading -->", "<!-- /reading -->"
"""The lines that open and close the authors' reading of a page: prose the report keeps when
it writes the page again (before the per-agent tables) and the check leaves out."""
_READING_BEFORE = "## Agents in their duels"


def _reading(text: str) -> list[str]:
    """The lines of a page's reading, its markers included (none: the page has none)."""
    lines = text.splitlines()
    if READING_START not in lines:
        return []
    start = lines.index(READING_START)
    if READING_END not in lines[start:]:
        raise ValueError(f"the page's reading opens with {READING_START} and never closes with {READING_END}")
    return lines[start: lines.index(READING_END, start) + 1]


def _without_reading(text: str) -> list[str]:
    """A page's lines without its reading and the blank line after it."""
    lines, reading = text.splitlines(), _reading(text)
    if not reading:
        return lines
    start = lines.index(READING_START)
    end = start + len(reading) + (1 if start + len(reading) < len(lines) and not lines[start + len(reading)] else 0)
    return lines[:start] + lines[end:]


def _with_source(text: str, run_folder: Path, study_file: str, figures: str | None,
                 pass_maps: Sequence[str] = ()) -> str:
    """The page with its last line naming what made it, so that the check can make it again."""
    source = json.dumps({"run": run_folder.name, "study": study_file, "figures": figures,
                         "pass_maps": list(pass_maps)}, sort_keys=True)
    return text + f"\n{_SOURCE}{source} -->\n"


def _relative(path: Path, start: Path) -> str:
    import os

    return Path(os.path.relpath(Path(path).resolve(), Path(start).resolve())).as_posix()


def check_page(page_path: Path, run_folder: Path) -> list[str]:
    """The lines of the page at ``page_path`` that differ from the page computed again from
    ``run_folder`` (none: every number matches), as ``line N: page '...' / run '...'`` (N
    counted without the page's reading, which is prose and not checked)."""
    text = Path(page_path).read_text()
    last = text.rstrip().rsplit("\n", 1)[-1]
    if not last.startswith(_SOURCE):
        raise ValueError(f"{page_path} was not written by racing study report (its last line names its source)")
    source = json.loads(last[len(_SOURCE):].rsplit("-->", 1)[0])
    maps = source.get("pass_maps", [])
    expected = _with_source(page(Run.read(run_folder), source["run"], source["study"], source["figures"], maps),
                            Path(source["run"]), source["study"], source["figures"], maps)
    have, want = _without_reading(text), expected.splitlines()
    differences = [f"line {k + 1}: page {a!r} / run {b!r}" for k, (a, b) in enumerate(zip(have, want)) if a != b]
    if len(have) != len(want):
        differences.append(f"the page has {len(have)} lines, the run gives {len(want)}")
    return differences
