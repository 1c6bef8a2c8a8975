"""A tournament's or a sweep's results as one self-contained page: ``report.html``.

:func:`write_tournament_report` and :func:`write_sweep_report` write ``out/report.html``
from what a run leaves in its folder ``out`` (the race records of ``results.jsonl`` and the
leaderboard or summary built from them). The page has these sections, each an element with
a stable id that links may target:

- ``run``: what was raced (track, length, agents or lineup and swept parameters, grids,
  races recorded of those scheduled) and links to the run's files that exist;
- ``leaderboard``: the ranking with win rates and their 95% Wilson intervals (as numbers
  and as a bar); a time trial ranks by laps finished and finish time; a sweep lists every
  point and agent;
- ``head-to-head``: how often each agent finished ahead of each other one (tournaments
  of more than one car per race) and the run's plot (``head_to_head.png``, ``sweep.png``);
- ``solver-health``: per agent (sweeps: per point and agent) the mean share of converged
  re-plans, mean solver iterations per re-plan, fallbacks, errors and certified share;
- ``races``: every recorded race (schedule index K, id, lineup, winner, gap, overtakes,
  steps), linking to its replay where one is embedded;
- ``incidents``: every contact incident the steward judged (race K, time, cars, verdict, the
  car that answers, closing speed), each linking to its race's replay where one is embedded,
  else to its race's row;
- ``replays``: a few races drawn as animated GIFs (elements ``replay-K``), chosen as
  :func:`pick_replays` says, from the replays the run recorded (``replays/race-0000K.npz``).

The page needs no server, no network and no JavaScript: the CSS is inline, images are
base64 data URIs, and the only links are in-page anchors and relative links to files of
the run folder. Every string taken from records and specs is HTML-escaped.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import math
import tempfile
import urllib.parse
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from experiments.files import replace_atomically
from experiments.formatting import mean_or_none, or_dash
from experiments.race_spec import RaceSpec
from experiments.standings import wilson_interval

REPORT = "report.html"
SECTIONS = ("run", "leaderboard", "head-to-head", "solver-health", "races", "incidents", "replays")
"""The ids of the page's sections, in order."""
TOURNAMENT_FILES = ("tournament.json", "results.jsonl", "summary.csv", "leaderboard.json", "head_to_head.png",
                    "race.gif")
SWEEP_FILES = ("sweep.json", "results.jsonl", "summary.csv", "summary.json", "sweep.png")
REPLAY_EVERY = 4  # a replay GIF draws every 4th step (0.4 s of race per frame) ...
REPLAY_FRAMES = 150  # ... or fewer, so that a GIF has at most this many frames (about 1 MB at 360 px)
REPLAY_SIZE = 360  # [px] its side

_CSS = """
body { font-family: "DejaVu Sans", "Liberation Sans", Helvetica, Arial, sans-serif; font-size: 18px;
       line-height: 1.45; color: #1f2328; background: #ffffff; margin: 0; }
main { max-width: 1200px; margin: 0 auto; padding: 24px 28px 48px; }
h1 { font-size: 30px; margin: 8px 0 4px; }
h2 { font-size: 24px; margin: 36px 0 10px; padding-bottom: 4px; border-bottom: 2px solid #d0d7de; }
nav a { margin-right: 14px; }
a { color: #0550ae; }
p.note { color: #57606a; }
dl.facts { display: grid; grid-template-columns: max-content 1fr; gap: 2px 18px; margin: 8px 0; }
dl.facts dt { font-weight: bold; }
dl.facts dd { margin: 0; overflow-wrap: anywhere; }
table { border-collapse: collapse; margin: 10px 0 14px; font-size: 17px; }
th, td { padding: 5px 10px; border-bottom: 1px solid #d8dee4; vertical-align: top; }
th { background: #f3f4f6; text-align: left; font-weight: bold; }
td.name { min-width: 9em; overflow-wrap: anywhere; }
div.scroll { overflow-x: auto; }
th.num { text-align: right; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tbody tr:nth-child(even) { background: #fafbfc; }
.bar { position: relative; display: inline-block; width: 120px; height: 12px; background: #eaeef2;
       border-radius: 6px; vertical-align: middle; }
.bar .ci { position: absolute; top: 0; height: 12px; background: #7aa7e0; border-radius: 6px; }
.bar .mark { position: absolute; top: -3px; width: 3px; height: 18px; margin-left: -1px; background: #0a3069; }
img.plot { max-width: 100%; border: 1px solid #d8dee4; }
figure { display: inline-block; margin: 8px 18px 18px 0; vertical-align: top; }
figcaption { font-size: 16px; color: #57606a; max-width: 360px; }
"""


class _Html(str):
    """Markup that is already HTML (every other string put on the page is escaped)."""


def _esc(value: Any) -> str:
    """``value`` as text on the page: HTML-escaped (quotes too), or kept if it is :class:`_Html`."""
    return value if isinstance(value, _Html) else html.escape(str(value), quote=True)


def _num(value: float | None, form: str) -> str:
    """``form`` applied to ``value``, or ``-`` for no value (None) or not a number (NaN)."""
    return or_dash(None if value is None or (isinstance(value, float) and math.isnan(value)) else value, form)


@dataclasses.dataclass(frozen=True)
class _Column:
    """A table column: its header, the cell of a row (text, or :class:`_Html`), and its
    kind: ``"num"`` (numbers, right-aligned), ``"name"`` (agent specs and the like, kept
    wide enough to read and wrapped anywhere) or ``""``."""

    header: str
    cell: Callable[[Any], str]
    kind: str = ""


def _table(table_id: str, columns: Sequence[_Column], rows: Iterable[Any],
           row_ids: Callable[[Any], str] | None = None) -> str:
    """An HTML table of ``rows``, one cell per column; ``row_ids`` gives each row's id."""
    kinds = [f' class="{c.kind}"' if c.kind else "" for c in columns]
    head = "".join(f"<th{kind}>{_esc(c.header)}</th>" for c, kind in zip(columns, kinds))
    body = []
    for row in rows:
        cells = "".join(f"<td{kind}>{_esc(c.cell(row))}</td>" for c, kind in zip(columns, kinds))
        row_id = f' id="{_esc(row_ids(row))}"' if row_ids else ""
        body.append(f"<tr{row_id}>{cells}</tr>")
    return (f'<div class="scroll"><table id="{_esc(table_id)}"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table></div>')


def _data_uri(data: bytes, mime: str) -> str:
    """``data`` as a base64 ``data:`` URI."""
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _png(out: Path, name: str, alt: str) -> str:
    """The image ``out/name`` embedded as a data URI, or nothing if the file is not there."""
    path = out / name
    if not path.is_file():
        return ""
    return f'<p><img class="plot" src="{_data_uri(path.read_bytes(), "image/png")}" alt="{_esc(alt)}"></p>'


def _ci_cells(rate: float | None, lo: float, hi: float) -> tuple[str, _Html]:
    """A rate and its 95% interval as ``0.50 [0.20, 0.80]`` and as a bar: the interval shaded
    on [0, 1], the rate marked (no rate, None or NaN: no races, a dash and no mark)."""
    if rate is not None and math.isnan(rate):
        rate = None
    mark = f'<span class="mark" style="left:{100 * rate:.1f}%"></span>' if rate is not None else ""
    bar = (f'<span class="bar" title="95% interval {lo:.2f} to {hi:.2f}">'
           f'<span class="ci" style="left:{100 * lo:.1f}%;width:{100 * (hi - lo):.1f}%"></span>{mark}</span>')
    return f"{_num(rate, '{:.2f}')} [{lo:.2f}, {hi:.2f}]", _Html(bar)


def _wilson_cells(wins: int, races: int) -> tuple[str, _Html]:
    """:func:`_ci_cells` of ``wins`` of ``races`` with the 95% Wilson interval
    (:func:`experiments.standings.wilson_interval`)."""
    return _ci_cells(wins / races if races else None, *wilson_interval(wins, races))


def _section(section_id: str, title: str, body: str) -> str:
    return f'<section id="{section_id}"><h2>{_esc(title)}</h2>{body}</section>'


def _note(text: str) -> str:
    return f'<p class="note">{_esc(text)}</p>'


def _facts(facts: Sequence[tuple[str, Any]]) -> str:
    """A definition list of ``(name, value)`` pairs (values escaped unless :class:`_Html`)."""
    return '<dl class="facts">' + "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in facts) + "</dl>"


def _file_links(out: Path, names: Sequence[str]) -> _Html:
    """Relative links to those of ``names`` that exist in ``out`` (a dash if none does)."""
    links = [f'<a href="{_esc(urllib.parse.quote(name))}">{_esc(name)}</a>' for name in names if (out / name).is_file()]
    return _Html(", ".join(links) or "-")


# -- races --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RaceRow:
    """One recorded race as the report shows it.

    Attributes:
        index: K, its index in the run's schedule (the record's ``race``; older records
            lack it, and K is found from the record's ``id``).
        id: the record's id.
        cars: the car records in starting-slot order.
        gap: the winner's lead over the second car, ``{"seconds": ...}`` or
            ``{"metres": ...}``; None for a lone car.
        overtakes: position swaps in the race.
        steps: env steps raced.
        replay: the race's recorded replay file, None if it has none (older records).
        point: the sweep point's parameters as text, "" in a tournament.
        incidents: the race's contact incidents (:attr:`experiments.race.RaceRecord.incidents`;
            none in records from before the steward).
    """

    index: int
    id: str
    cars: tuple[dict[str, Any], ...]
    gap: dict[str, float] | None
    overtakes: int
    steps: int
    replay: Path | None
    point: str = ""
    incidents: tuple[dict[str, Any], ...] = ()

    @property
    def winner(self) -> dict[str, Any]:
        return min(self.cars, key=lambda car: car["place"])

    @property
    def all_finished(self) -> bool:
        return all(car["finish_time"] is not None for car in self.cars)


def _race_rows(out: Path, records: Sequence[dict[str, Any]], positions: dict[str, int],
               cars: Callable[[dict[str, Any]], list[dict[str, Any]]],
               point: Callable[[dict[str, Any]], str] = lambda record: "") -> list[RaceRow]:
    """The races of ``records`` in schedule order; ``positions`` maps ids to schedule
    indices (for records without ``race``), ``cars`` gives a record's cars by slot."""
    rows = []
    for k, record in enumerate(records):
        replay = out / record["replay"] if record.get("replay") else None
        if replay is not None and not replay.is_file():
            replay = None
        rows.append(RaceRow(index=int(record.get("race", positions.get(record["id"], k))), id=record["id"],
                            cars=tuple(cars(record)), gap=record.get("gap"), overtakes=int(record["overtakes"]),
                            steps=int(record["steps"]), replay=replay, point=point(record),
                            incidents=tuple(record.get("incidents", ()))))
    return sorted(rows, key=lambda race: race.index)


def _gap_text(gap: dict[str, float] | None) -> str:
    if not gap:
        return "-"
    return f"{gap['seconds']:.2f} s" if "seconds" in gap else f"{gap['metres']:.1f} m"


def pick_replays(races: Sequence[RaceRow], count: int) -> list[tuple[RaceRow, str]]:
    """The races whose replays the report embeds, with why each was chosen, at most ``count``.

    Only races with a recorded replay file are candidates. In order: the closest finish
    (the smallest gap in seconds among races every car finished; if there is none, the
    smallest gap in metres), then the race with the most overtakes (if any has one), then
    the first race (by schedule index), then the next races in schedule order; each race
    once, ties to the earlier race. A run without replays (one from before they were
    recorded) gets none.
    """
    candidates = sorted((race for race in races if race.replay is not None), key=lambda race: race.index)
    picks: list[tuple[RaceRow, str]] = []

    def take(race: RaceRow | None, why: str) -> None:
        if race is not None and len(picks) < count and all(race is not r for r, _ in picks):
            picks.append((race, why))

    timed = [race for race in candidates if race.all_finished and race.gap and "seconds" in race.gap]
    spaced = [race for race in candidates if race.gap and "metres" in race.gap]
    if timed:
        closest = min(timed, key=lambda race: race.gap["seconds"])
        take(closest, f"closest finish: {_gap_text(closest.gap)}")
    elif spaced:
        closest = min(spaced, key=lambda race: race.gap["metres"])
        take(closest, f"closest finish: {_gap_text(closest.gap)} apart")
    rest = [race for race in candidates if race.overtakes > 0 and all(race is not r for r, _ in picks)]
    if rest:
        busiest = max(rest, key=lambda race: race.overtakes)  # max keeps the first of equals
        take(busiest, f"most overtakes: {busiest.overtakes}")
    for race in candidates:
        take(race, "first race" if race is candidates[0] else "in schedule order")
    return picks


def replay_every(steps: int) -> int:
    """Every how many steps a race of ``steps`` steps is drawn in the report: every
    :data:`REPLAY_EVERY`-th, or fewer so that the GIF has at most :data:`REPLAY_FRAMES` frames."""
    # the drawn steps are 0, every, 2 every, ... and the last: at most steps // every + 2 of them
    return max(REPLAY_EVERY, math.ceil(steps / (REPLAY_FRAMES - 1)))


def _render_replays(out: Path, picks: Sequence[tuple[RaceRow, str]]) -> list[tuple[RaceRow, str, bytes]]:
    """The picked races drawn as GIFs by :func:`experiments.replay.render_race` (every
    :func:`replay_every` steps, in a temporary folder, read back as bytes); a race whose
    replay went missing is left out."""
    if not picks:
        return []
    from experiments.replay import render_race

    drawn = []
    with tempfile.TemporaryDirectory(prefix="racing-report-") as tmp:
        for race, why in picks:
            path = Path(tmp) / f"race-{race.index:05d}.gif"
            try:
                render_race(out, race.index, path, every=replay_every(race.steps), size=REPLAY_SIZE)
            except FileNotFoundError:
                continue
            drawn.append((race, why, path.read_bytes()))
    return drawn


def _races_section(races: Sequence[RaceRow], embedded: set[int], scheduled: int, sweep: bool) -> str:
    """The table of every recorded race; a race with an embedded replay links to it."""
    columns = [
        _Column("K", lambda race: _Html(f'<a href="#replay-{race.index}">{race.index}</a>')
                if race.index in embedded else str(race.index), kind="num"),
        _Column("id", lambda race: race.id, kind="name"),
        *([_Column("point", lambda race: race.point, kind="name")] if sweep else []),
        _Column("lineup (by start slot)", lambda race: " vs ".join(car["agent"] for car in race.cars), kind="name"),
        _Column("winner", lambda race: race.winner["agent"], kind="name"),
        _Column("winner's time [s]", lambda race: _num(race.winner["finish_time"], "{:.2f}"), kind="num"),
        _Column("x limit", lambda race: _num(race.winner.get("limit_ratio"), "{:.3f}"), kind="num"),
        _Column("gap", lambda race: _gap_text(race.gap), kind="num"),
        _Column("overtakes", lambda race: str(race.overtakes), kind="num"),
        _Column("steps", lambda race: str(race.steps), kind="num"),
    ]
    if not races:
        return _note(f"No race recorded yet (0 of {scheduled} scheduled).")
    return (_note(f"{len(races)} of {scheduled} scheduled races recorded, in schedule order (K: the race's index "
                  "in the schedule)" + ("; a linked K has its replay below." if embedded else "."))
            + _table("races-table", columns, races, row_ids=lambda race: f"race-{race.index}"))


def _incidents_section(races: Sequence[RaceRow], embedded: set[int]) -> str:
    """The table of every contact incident, linked to its race's replay (embedded) or row."""
    rows = [(race, incident) for race in races for incident in race.incidents]
    if not rows:
        return _note("No contact incident in the recorded races.")

    def car(race: RaceRow, index: int | None) -> str:
        return "nobody (racing incident)" if index is None else f"{race.cars[index]['agent']} ({race.cars[index]['car']})"

    def where(row) -> _Html:
        race, incident = row
        target = f"replay-{race.index}" if race.index in embedded else f"race-{race.index}"
        return _Html(f'<a href="#{target}">{race.index}</a>')

    columns = [
        _Column("race K", where, kind="num"),
        _Column("time [s]", lambda row: f"{row[1]['time']:.1f}", kind="num"),
        _Column("cars", lambda row: " / ".join(car(row[0], i) for i in row[1]["cars"]), kind="name"),
        _Column("verdict", lambda row: row[1]["verdict"]),
        _Column("answers", lambda row: car(row[0], row[1]["at_fault"]), kind="name"),
        _Column("closing speed [m/s]", lambda row: f"{row[1]['closing_speed']:.1f}", kind="num"),
    ]
    faults = sum(incident["at_fault"] is not None for _, incident in rows)
    return (_note(f"{len(rows)} contact incidents, {faults} with a car at fault (docs/rules.md); race K links to "
                  "the race's replay where it is embedded, else to its row, and its frames show the verdict "
                  "from the incident's time on.")
            + _table("incidents-table", columns, rows))


def _outcome(race: RaceRow) -> str:
    """Who raced and how it ended, in words."""
    if len(race.cars) == 1:
        car = race.cars[0]
        end = f"finished in {car['finish_time']:.2f} s" if car["finish_time"] is not None else "did not finish"
        return f"{car['agent']} alone, {end}"
    return f"{' vs '.join(car['agent'] for car in race.cars)}, won by {race.winner['agent']}"


def _replays_section(out: Path, races: Sequence[RaceRow], count: int) -> tuple[str, set[int]]:
    """The embedded replays and the schedule indices of the races they show."""
    if not any(race.replay is not None for race in races):
        return _note("No replay was recorded for the races of this run (runs from before replays were recorded "
                     "have none): run again with a newer version to record them."), set()
    if count < 1:
        return _note("Replays were recorded (replays/), but none was asked to be embedded."), set()
    drawn = _render_replays(out, pick_replays(races, count))
    if not drawn:
        return _note("The chosen races' replay files could not be found."), set()
    figures = []
    for race, why, gif in drawn:
        caption = f"Race {race.index} ({race.id}): {why}; {_outcome(race)}; every {replay_every(race.steps)} steps."
        figures.append(f'<figure id="replay-{race.index}"><img src="{_data_uri(gif, "image/gif")}" '
                       f'alt="{_esc(f"replay of race {race.index}")}" width="{REPLAY_SIZE}">'
                       f"<figcaption>{_esc(caption)}</figcaption></figure>")
    intro = _note(f"{len(drawn)} of the races with a recorded replay, drawn every {REPLAY_EVERY} steps (more for "
                  f"races over {(REPLAY_FRAMES - 1) * REPLAY_EVERY} steps): the closest finish, the most overtakes, then "
                  "the first race.")
    return intro + "".join(figures), {race.index for race, _, _ in drawn}


# -- solver health ------------------------------------------------------------------------


def solver_health(cars: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """What an agent's car records say about its solver: ``races``, the mean share of
    converged re-plans (``converged``), the mean iterations per re-plan (``iterations``,
    over the races whose records have ``solver_iterations_mean``), ``fallbacks`` (re-plans
    that fell back to a safe action, summed), ``errors`` (cars that faulted) and the mean
    ``certified`` share; a mean over no races (agents that are no planners) is None."""
    return {"races": len(cars),
            "converged": mean_or_none(car.get("solver_converged_fraction") for car in cars),
            "iterations": mean_or_none(car.get("solver_iterations_mean") for car in cars),
            "fallbacks": sum(int(car.get("solver_failures") or 0) for car in cars),
            "errors": sum(car.get("error") is not None for car in cars),
            "certified": mean_or_none(car.get("certified_share") for car in cars)}


def _health_columns(rows: Sequence[dict[str, Any]]) -> list[_Column]:
    """The solver-health columns for rows with a ``health`` dict (:func:`solver_health`)."""
    columns = [
        _Column("races", lambda row: str(row["health"]["races"]), kind="num"),
        _Column("converged re-plans", lambda row: _num(row["health"]["converged"], "{:.1%}"), kind="num"),
        _Column("iterations / re-plan", lambda row: _num(row["health"]["iterations"], "{:.2f}"), kind="num"),
        _Column("fallbacks", lambda row: str(row["health"]["fallbacks"]), kind="num"),
        _Column("errors", lambda row: str(row["health"]["errors"]), kind="num"),
    ]
    if any(row["health"]["certified"] is not None for row in rows):
        columns.append(_Column("certified", lambda row: _num(row["health"]["certified"], "{:.1%}"), kind="num"))
    return columns


_HEALTH_NOTE = ("Per planner re-plan: the share that met the solver's tolerance (the rest act on the last iterate), "
                "the mean solver iterations, and the fallbacks to a safe action; errors are races the agent faulted "
                "in. A dash: the agent does not plan, or its records do not say (iterations: older runs).")


# -- the page -----------------------------------------------------------------------------


def _ratio(header: str, key: str) -> _Column:
    """``row[key]/row["races"]``, e.g. wins of races."""
    return _Column(header, lambda row: f"{row[key]}/{row['races']}", kind="num")


def _value(header: str, key: str, form: str) -> _Column:
    """``row[key]`` formatted with ``form`` (a dash for none)."""
    return _Column(header, lambda row: _num(row[key], form), kind="num")


def _share_text(share: float | None, interval: tuple[float, float] | None) -> str:
    """A share of rivals beaten with its interval, e.g. ``62% [51-72%]`` (a dash for none,
    e.g. rows from records before the count)."""
    if share is None:
        return "-"
    lo, hi = interval
    return f"{share:.0%} [{lo:.0%}-{hi:.0%}]"


def _ci_columns(header: str) -> list[_Column]:
    """The rate with its 95% interval, and its bar, of rows with ``"ci"`` (:func:`_ci_cells`)."""
    return [_Column(header, lambda row: row["ci"][0], kind="num"), _Column("", lambda row: row["ci"][1])]


_ERRORS = _Column("errors", lambda row: str(row["errors"]), kind="num")
# finish time over the race's lap-time limit (racing_env.limits.race_limit); leaderboards from before it: a dash
_LIMIT = _Column("x limit", lambda row: _num(row.get("mean_limit_ratio"), "{:.3f}"), kind="num")
_LIMIT_NOTE = (" x limit: the mean finish time over the race's lap-time limit (the quasi-steady-state flying laps "
               "of the car on the circuit's racing line, or the centre line where none is shipped; 1.04 is 4% slower).")
_MARGIN_NOTE = "margin: mean finish-time lead over the other cars in the races all finished."


def _run_facts(out: Path, config: RaceSpec, who: Sequence[tuple[str, str]], recorded: int, scheduled: int,
               files: Sequence[str]) -> str:
    """The ``run`` section's list: the race (:class:`experiments.race_spec.RaceSpec`'s
    fields), ``who`` raced it how, the races recorded of those scheduled, and the files."""
    length = f"{config.race_distance:g} m" if config.race_distance is not None else f"{config.laps} lap(s)"
    return _facts([("track", config.track), ("race length", length), *who, ("max steps", config.max_steps),
                   ("jerk weight", f"{config.jerk_weight:g}"),
                   ("incidents", f"contact: {config.on_collision}, off track: {config.on_off_track}"),
                   ("races", f"{recorded} of {scheduled} scheduled races recorded"),
                   ("files", _file_links(out, files))])


def _write_page(out: Path, title: str, *, run: str, leaderboard: str, head_to_head: tuple[str, str], health: str,
                races: Sequence[RaceRow], scheduled: int, replays: int, sweep: bool) -> Path:
    """Put the sections together (the races and replays from ``races``) and write the page
    to ``out/report.html`` atomically; returns its path."""
    replay_body, embedded = _replays_section(out, races, replays)
    sections = [_section("run", "Run", run), _section("leaderboard", "Leaderboard", leaderboard),
                _section("head-to-head", *head_to_head), _section("solver-health", "Solver health", health),
                _section("races", "Races", _races_section(races, embedded, scheduled, sweep)),
                _section("incidents", "Incidents", _incidents_section(races, embedded)),
                _section("replays", "Replays", replay_body)]
    nav = "".join(f'<a href="#{section}">{section.replace("-", " ")}</a>' for section in SECTIONS)
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_esc(title)}</title><style>{_CSS}</style></head>"
            f"<body><main><h1>{_esc(title)}</h1><nav>{nav}</nav>{''.join(sections)}</main></body></html>\n")
    path = out / REPORT
    replace_atomically(lambda partial: partial.write_text(page, encoding="utf-8"), path)
    return path


def write_tournament_report(out: Path, config: RaceSpec, board: dict[str, Any], records: list[dict[str, Any]],
                            *, replays: int = 2) -> Path:
    """Write ``out/report.html`` for a tournament and return its path.

    Args:
        out: the tournament's folder (its files are linked, its ``head_to_head.png`` and
            recorded replays embedded).
        config: the tournament (a :class:`experiments.tournament.TournamentConfig`; the
            report reads its fields and its races in schedule order, ``config.schedule()``).
        board: :func:`experiments.tournament.leaderboard` of ``records``.
        records: the race records (``results.jsonl``), in schedule order.
        replays: at most this many races embedded as GIFs (:func:`pick_replays`).
    """
    out = Path(out)
    time_trial = config.cars == 1
    planned = config.schedule()
    races = _race_rows(out, records, {race["id"]: k for k, race in enumerate(planned)}, lambda record: record["cars"])
    field = config.field  # one field per grid
    lineup = config.lineup
    run = _run_facts(out, config, [
        ("agents", "; ".join(config.agents)),
        *([("lineup", "; ".join(f"{spec} x{lineup.count(spec)}" for spec in config.agents))]
          if lineup is not None else []),
        ("format", "time trial: each agent alone" if time_trial else f"{config.cars} cars per race, "
         + (f"every agent against {config.versus}" if config.versus else
            "the lineup's field per grid" if lineup is not None else
            "a field of all agents per grid" if field else "round robin")),
        ("start", f"{config.scenario}, {config.grids} grid(s), seed {config.seed}, "
         + ("the field shuffled over the slots per grid" if field else "every rotation of the slots")),
    ], len(records), len(planned), TOURNAMENT_FILES)
    rows = [{**row, "rank": k, "ci": _ci_cells(row["win_rate"], *row["win_rate_ci95"])}
            for k, row in enumerate(board["rows"], 1)]
    agent = _Column("agent", lambda row: row["agent"], kind="name")
    rank = _Column("#", lambda row: str(row["rank"]), kind="num")
    if time_trial:
        columns = [rank, agent, _ratio("finished", "finished"),
                   _value("mean finish time [s]", "mean_finish_time_s", "{:.2f}"),
                   _value("best [s]", "best_finish_time_s", "{:.2f}"), _LIMIT,
                   _value("off track [s]", "time_off_track_s", "{:.1f}"), _ERRORS]
        note = "Each agent alone on the track, ranked by laps finished, then mean finish time." + _LIMIT_NOTE
        head_to_head = _note("A time trial races every agent alone: there is no head to head.")
    else:
        columns = [rank, agent, _value("rating", "rating", "{:.2f}"), _ratio("wins/races", "wins"),
                   *_ci_columns("win rate [95% CI]"), _ratio("finished", "finished"),
                   _value("margin [s]", "mean_margin_s", "{:+.2f}"), _LIMIT,
                   _value("contact steps", "collision_steps", "{:d}"),
                   _Column("at fault", lambda row: str(row.get("faults", 0)), kind="num"), _ERRORS]
        note = ("Ranked by rating (Plackett-Luce mu - 3 sigma); win rates with 95% Wilson intervals; "
                + _MARGIN_NOTE + _LIMIT_NOTE + " Contact steps: its cars' steps touching another car; at fault: the "
                "contact incidents the steward found its cars to blame for (docs/rules.md).")
        if config.cars > 2:  # places say more than wins in a field
            columns[4:4] = [_value("mean place", "mean_place", "{:.2f}"),
                            _Column("rivals beaten [95% CI]", lambda row: _share_text(row.get("beaten_share"),
                                                                                   row.get("beaten_share_ci95")),
                                    kind="num"),
                            _Column("passes made/suffered", lambda row: f"{row.get('overtakes', 0)}/{row.get('overtaken', 0)}",
                                    kind="num")]
            note += (" With more than two cars per race: each agent's mean place, the share of the other agents' "
                     "cars its cars beat (with a 95% Wilson interval over those pairs) and its passes made and "
                     "suffered; the rating ranks each agent in a race by its "
                     "cars' mean place.")
        names, wins = board["head_to_head"]["agents"], board["head_to_head"]["wins"]
        matrix = [_Column("row ahead of column", lambda i: names[i], kind="name"),
                  *(_Column(name, lambda i, j=j: "-" if i == j else str(wins[i][j]), kind="num")
                    for j, name in enumerate(names))]
        head_to_head = (_note("Races in which the row agent finished ahead of the column agent"
                              + (" (in a field, pairs of cars: each car of the row agent with each car of the "
                                 "column agent in a race)." if field else "."))
                        + _table("head-to-head-table", matrix, range(len(names)))
                        + _png(out, "head_to_head.png", "head-to-head heat map"))
    health_rows = [{"agent": row["agent"], "health": solver_health(
        [car for race in races for car in race.cars if car["agent"] == row["agent"]])} for row in board["rows"]]
    return _write_page(
        out, f"{'Time trial' if time_trial else 'Tournament'} on {config.track}", run=run,
        leaderboard=_note(note) + _table("leaderboard-table", columns, rows),
        head_to_head=("Head to head", head_to_head),
        health=_note(_HEALTH_NOTE) + _table("solver-health-table", [agent, *_health_columns(health_rows)], health_rows),
        races=races, scheduled=len(planned), replays=replays, sweep=False)


def write_sweep_report(out: Path, config: RaceSpec, rows: list[dict[str, Any]], records: list[dict[str, Any]],
                       *, replays: int = 2) -> Path:
    """Write ``out/report.html`` for a sweep and return its path.

    Args:
        out: the sweep's folder (its files are linked, its ``sweep.png`` and recorded
            replays embedded).
        config: the sweep (a :class:`experiments.sweep.SweepConfig`; the report reads its
            fields, points and races in schedule order, ``config.schedule()``).
        rows: :func:`experiments.sweep.summarize` of ``records`` (per point and agent).
        records: the race records (``results.jsonl``, :func:`experiments.sweep.run_job`).
        replays: at most this many races embedded as GIFs (:func:`pick_replays`).
    """
    out = Path(out)
    time_trial = config.cars == 1
    points = config.points()
    names = [name for name, _ in config.parameters]
    planned = config.schedule()
    races = _race_rows(out, records, {job["id"]: k for k, job in enumerate(planned)},
                       lambda record: sorted(record["agents"], key=lambda car: car.get("slot", 0)),
                       lambda record: ", ".join(f"{name}={points[record['point_index']][name]}" for name in names))
    run = _run_facts(out, config, [
        ("lineup", "; ".join(f"{k}: {spec}" for k, spec in enumerate(config.lineup))
         + (" (time trial: the agent alone)" if time_trial else "")),
        ("parameters", "; ".join(f"{name} = {list(values)}" for name, values in config.parameters)),
        ("start", f"{len(points)} point(s) x {config.grids} grid(s) x "
                  + (f"one field of {config.cars} cars shuffled over the slots" if config.field
                     else f"{len(config.lineup)} rotation(s)") + f", seed {config.seed}"),
    ], len(records), len(planned), SWEEP_FILES)
    rows = [{**row, "ci": _wilson_cells(row["wins"], row["races"])} for row in rows]
    point = [_Column(name, lambda row, name=name: str(points[row["point"]][name])) for name in names]
    agent = _Column("agent", lambda row: f"{row['agent']}: {row['spec']}", kind="name")
    if time_trial:  # alone, a finished lap is a win
        columns = [*point, agent, _ratio("finished", "wins"), *_ci_columns("finished share [95% CI]"),
                   _value("finish time [s]", "mean_finish_time_s", "{:.2f}"),
                   _value("best [s]", "best_finish_time_s", "{:.2f}"), _ERRORS]
        note = "alone on the track, a finished lap is a win."
    else:
        columns = [*point, agent, _ratio("wins/races", "wins"), *_ci_columns("win rate [95% CI]"),
                   _value("mean place", "mean_place", "{:.2f}"), _value("margin [s]", "mean_margin_s", "{:+.2f}"),
                   _ratio("finished", "finished"), _ERRORS]
        note = _MARGIN_NOTE
        if config.cars > 2:  # places say more than wins in a field
            columns[-3:-3] = [_Column("rivals beaten [95% CI]", lambda row: _share_text(
                                  row.get("beaten_share"), (row.get("beaten_ci95_low"), row.get("beaten_ci95_high"))),
                                  kind="num"),
                              _Column("passes made/suffered", lambda row: f"{_num(row.get('overtakes'), '{:d}')}/"
                                      f"{_num(row.get('overtaken'), '{:d}')}", kind="num"),
                              _value("contact steps", "contact_steps", "{:d}")]
            note += (" With more than two cars per race: the share of the other agents' cars each agent's cars beat "
                     "(with a 95% Wilson interval over those pairs), its passes made and suffered and its cars' steps "
                     "in contact" + ("; in a field, races, wins and places count each car of an agent." if config.field
                                     else "."))
    plot = _png(out, "sweep.png", "sweep plot: agent 0's results against the first parameter")
    by_agent: dict[tuple[int, int], list[dict[str, Any]]] = {}  # (point, agent index) -> its cars
    for record in records:
        for index, car in enumerate(record["agents"]):  # a field's cars name their agent (entry)
            by_agent.setdefault((record["point_index"], car.get("entry", index)), []).append(car)
    health_rows = [{**row, "health": solver_health(by_agent.get((row["point"], row["agent"]), []))} for row in rows]
    return _write_page(
        out, f"Sweep: {' vs '.join(config.lineup)}" + (" (time trial)" if time_trial else ""), run=run,
        leaderboard=(_note("Every point (combination of the swept values) and agent, in sweep order; rates with 95% "
                           f"Wilson intervals; {note}") + _table("leaderboard-table", columns, rows)),
        head_to_head=("Results by parameter",
                      _note(f"Agent 0 ({config.lineup[0]}) against the first parameter ({names[0]}).") + plot if plot
                      else _note("No sweep.png in this folder.")),
        health=_note(_HEALTH_NOTE) + _table("solver-health-table", [*point, agent, *_health_columns(health_rows)],
                                            health_rows),
        races=races, scheduled=len(planned), replays=replays, sweep=True)
