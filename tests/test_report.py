"""report.html of tournaments and sweeps, from real (short) runs of scripted agents and a
cheap iLQR planner: every section there, every link and image resolving inside the page or
the run folder, nothing from the network, and the tables' numbers those of the leaderboard,
the summary and the race records (recomputed here)."""

from __future__ import annotations

import base64
import io
import math
import re
import shutil
import subprocess
import urllib.parse
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from experiments import sweep, tournament
from experiments.report import write_sweep_report, write_tournament_report
from experiments.sweep import SweepConfig
from experiments.tournament import TournamentConfig, wilson_interval

SECTION_IDS = ("run", "leaderboard", "head-to-head", "solver-health", "races", "incidents", "replays")
SHORT = dict(track="straight", race_distance=120.0, grids=1, max_steps=400)
PLANNER = "ilqr:max_iterations=8,replan_every=5"  # cheap; its re-plans converge in some races more often than in others


class Page(HTMLParser):
    """What the tests read of a page: element ids in order, every ``href``/``src``, the
    tables by id (rows of whitespace-normalised cell texts, the header row first), the
    ``class``/``style`` of the spans inside each table, the images (with the id of the
    element holding them) and the text of each section."""

    def __init__(self, text: str):
        super().__init__(convert_charrefs=True)
        self.ids: list[str] = []
        self.refs: list[tuple[str, str]] = []
        self.tables: dict[str, list[list[str]]] = {}
        self.spans: dict[str, list[tuple[str, str]]] = {}
        self.images: list[tuple[str | None, str]] = []
        self.section_text: dict[str, str] = {}
        self._table = self._row = self._cell = self._figure = self._section = None
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.append(attrs["id"])
        self.refs += [(key, attrs[key]) for key in ("href", "src") if key in attrs]
        if tag == "section":
            self._section = attrs.get("id")
            self.section_text[self._section] = ""
        elif tag == "table":
            self._table = attrs.get("id")
            self.tables[self._table] = []
            self.spans[self._table] = []
        elif tag == "tr" and self._table is not None:
            self._row = []
            self.tables[self._table].append(self._row)
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []
        elif tag == "span" and self._table is not None:
            self.spans[self._table].append((attrs.get("class", ""), attrs.get("style", "")))
        elif tag == "figure":
            self._figure = attrs.get("id")
        elif tag == "img":
            self.images.append((attrs.get("id") or self._figure, attrs["src"]))

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append(" ".join("".join(self._cell).split()))
            self._cell = None
        elif tag == "tr":
            self._row = None
        elif tag == "table":
            self._table = None
        elif tag == "figure":
            self._figure = None
        elif tag == "section":
            self._section = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)
        if self._section is not None:
            self.section_text[self._section] += data

    def rows(self, table: str) -> list[dict[str, str]]:
        """The body rows of a table as ``{header: cell}``."""
        header, *body = self.tables[table]
        return [dict(zip(header, row)) for row in body]


def checked_page(out: Path, path: Path) -> Page:
    """Parse ``path`` (the report of run folder ``out``) and check what every report must
    hold: all sections, unique ids, links to in-page ids or to files of ``out``, images as
    data URIs, and nothing that reaches the network or runs a script."""
    assert path == out / "report.html" and path.is_file()
    text = path.read_text(encoding="utf-8")
    assert "http://" not in text and "https://" not in text and "<script" not in text.lower()
    assert "@import" not in text and "url(" not in text  # no stylesheet or font from elsewhere
    page = Page(text)
    assert [i for i in page.ids if i in SECTION_IDS] == list(SECTION_IDS)
    assert len(page.ids) == len(set(page.ids))
    for attribute, ref in page.refs:
        if ref.startswith("#"):
            assert ref[1:] in page.ids, ref
        elif ref.startswith("data:"):
            assert attribute == "src" and re.fullmatch(r"data:image/(png|gif);base64,[A-Za-z0-9+/]+=*", ref), ref[:60]
        else:
            assert attribute == "href" and not urllib.parse.urlparse(ref).scheme and not ref.startswith("/"), ref
            target = (out / urllib.parse.unquote(ref)).resolve()
            assert target.is_file() and target.parent == out.resolve(), ref
    assert all(src.startswith("data:") for _, src in page.images)
    return page


def image_bytes(src: str) -> bytes:
    return base64.b64decode(src.split(",", 1)[1])


def number(cell: str) -> float | None:
    """A number shown in a cell (``12.5%`` as 12.5), None for a dash."""
    return None if cell == "-" else float(cell.rstrip("%").removesuffix(" s"))


def assert_shown(cell: str, value: float | None, decimals: int, percent: bool = False) -> None:
    """``cell`` shows ``value`` (a share in % when ``percent``) rounded to ``decimals``, or a dash for None."""
    if value is None:
        assert cell == "-"
        return
    assert cell.endswith("%") == percent
    assert number(cell) == pytest.approx(100 * value if percent else value, abs=0.5 * 10 ** -decimals + 1e-9)


def run(config: TournamentConfig, out: Path) -> tuple[dict, list[dict]]:
    board = tournament.run_tournament(config, out, gif=False, progress=False)
    return board, tournament.load_results(out)


@pytest.fixture(scope="module")
def planner_run(tmp_path_factory):
    """A round robin of the planner and two scripted agents: 6 races with replays."""
    config = TournamentConfig(agents=(PLANNER, "lane-keeping", "constant-speed"), **SHORT)
    out = tmp_path_factory.mktemp("planners")
    board, records = run(config, out)
    return config, out, board, records


@pytest.fixture(scope="module")
def time_trial(tmp_path_factory):
    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), cars=1, **SHORT)
    out = tmp_path_factory.mktemp("time-trial")
    board, records = run(config, out)
    return config, out, board, records


@pytest.fixture(scope="module")
def planner_sweep(tmp_path_factory):
    """The planner against the lane keeper at two collision weights: 4 races with replays."""
    config = SweepConfig(lineup=(PLANNER, "lane-keeping"), parameters=(("agent0.c_collision", (1.0, 10.0)),), **SHORT)
    out = tmp_path_factory.mktemp("sweep")
    summary = sweep.run_sweep(config, out, progress=False)
    return config, out, summary["rows"], sweep.read_results(out)


def expected_health(cars: list[dict]) -> dict:
    """Solver health recomputed from car records."""
    def mean(key):
        values = [car[key] for car in cars if car.get(key) is not None]
        return sum(values) / len(values) if values else None

    return {"races": len(cars), "converged": mean("solver_converged_fraction"),
            "iterations": mean("solver_iterations_mean"), "fallbacks": sum(car["solver_failures"] for car in cars),
            "errors": sum(car["error"] is not None for car in cars), "certified": mean("certified_share")}


def assert_health_row(shown: dict[str, str], expected: dict) -> None:
    assert int(shown["races"]) == expected["races"]
    assert_shown(shown["converged re-plans"], expected["converged"], 1, percent=True)
    assert_shown(shown["iterations / re-plan"], expected["iterations"], 2)
    assert int(shown["fallbacks"]) == expected["fallbacks"]
    assert int(shown["errors"]) == expected["errors"]
    if "certified" in shown:
        assert_shown(shown["certified"], expected["certified"], 1, percent=True)
    else:
        assert expected["certified"] is None


def assert_ci(cell: str, bar: tuple[str, str], rate: float | None, lo: float, hi: float) -> None:
    """A ``0.50 [0.20, 0.80]`` cell and its bar (the shaded interval on [0, 1]) show
    ``rate`` (None: no races) and its 95% interval ``[lo, hi]``."""
    shown_rate, shown_lo, shown_hi = re.fullmatch(r"(\S+) \[(\S+), (\S+)\]", cell).groups()
    assert_shown(shown_rate, rate, 2)
    assert_shown(shown_lo, lo, 2)
    assert_shown(shown_hi, hi, 2)
    left, width = map(float, re.fullmatch(r"left:([\d.]+)%;width:([\d.]+)%", bar[1]).groups())
    assert bar[0] == "ci"
    assert left == pytest.approx(100 * lo, abs=0.051) and width == pytest.approx(100 * (hi - lo), abs=0.051)


def assert_wilson(cell: str, bar: tuple[str, str], wins: int, races: int) -> None:
    """As :func:`assert_ci`, for ``wins`` of ``races`` with their 95% Wilson interval."""
    assert_ci(cell, bar, wins / races if races else None, *wilson_interval(wins, races))


def ci_bars(page: Page, table: str) -> list[tuple[str, str]]:
    return [span for span in page.spans[table] if span[0] == "ci"]


def test_tournament_report_sections_links_and_leaderboard(planner_run):
    config, out, board, records = planner_run
    page = checked_page(out, write_tournament_report(out, config, board, records))
    run_text = page.section_text["run"]
    assert f"{len(records)} of {len(tournament.schedule(config))} scheduled races" in run_text
    assert "straight" in run_text and "120 m" in run_text and all(agent in run_text for agent in config.agents)
    linked = {ref for key, ref in page.refs if key == "href" and not ref.startswith("#")}
    assert {"results.jsonl", "summary.csv", "leaderboard.json", "tournament.json", "head_to_head.png"} <= linked
    assert "race.gif" not in linked and not (out / "race.gif").exists()  # ran without a GIF: no link to one
    rows = page.rows("leaderboard-table")
    assert [row["agent"] for row in rows] == [row["agent"] for row in board["rows"]]
    bars = ci_bars(page, "leaderboard-table")
    assert len(bars) == len(rows)
    for rank, (shown, row, bar) in enumerate(zip(rows, board["rows"], bars), 1):
        assert shown["#"] == str(rank)
        assert shown["wins/races"] == f"{row['wins']}/{row['races']}"
        assert shown["finished"] == f"{row['finished']}/{row['races']}"
        assert int(shown["errors"]) == row["errors"]
        assert_shown(shown["rating"], row["rating"], 2)
        assert_shown(shown["margin [s]"], row["mean_margin_s"], 2)
        if row["mean_margin_s"] is not None:
            assert shown["margin [s]"][0] in "+-"
        assert_ci(shown["win rate [95% CI]"], bar, row["win_rate"], *row["win_rate_ci95"])  # the board's numbers
    plots = [src for _, src in page.images if src.startswith("data:image/png")]
    assert [image_bytes(src) for src in plots] == [(out / "head_to_head.png").read_bytes()]


def test_incidents_table_lists_every_incident_with_a_link_to_its_race(planner_run, tmp_path):
    """Every incident of the records, in race order, with its verdict, the car that answers
    (nobody for a racing incident) and a link to its race's replay or row."""
    config, out, board, records = planner_run
    records = [dict(record, incidents=list(record.get("incidents", []))) for record in records]
    records[0]["incidents"].append({"step": 12, "time": 1.2, "cars": [0, 1], "verdict": "rear-end", "at_fault": 1,
                                    "closing_speed": 4.25})
    records[-1]["incidents"].append({"step": 30, "time": 3.0, "cars": [0, 1], "verdict": "racing-incident",
                                     "at_fault": None, "closing_speed": 0.5})
    page = checked_page(out, write_tournament_report(out, config, board, records))
    rows = page.rows("incidents-table")
    expected = [(k, incident) for k, record in enumerate(records) for incident in record["incidents"]]
    assert len(rows) == len(expected)
    for shown, (k, incident) in zip(rows, expected):
        cars = records[k]["cars"]
        assert shown["time [s]"] == f"{incident['time']:.1f}"
        assert shown["verdict"] == incident["verdict"]
        fault = incident["at_fault"]
        assert shown["answers"] == ("nobody (racing incident)" if fault is None else
                                    f"{cars[fault]['agent']} ({cars[fault]['car']})")
        assert shown["closing speed [m/s]"] == f"{incident['closing_speed']:.1f}"
        index = records[k].get("race", k)
        assert shown["race K"] == str(index)
        # the link resolves (checked_page): to the embedded replay, or else to the race's row
        assert ("href", f"#replay-{index}") in page.refs or ("href", f"#race-{index}") in page.refs


def test_head_to_head_cells_are_the_boards(planner_run):
    config, out, board, records = planner_run
    page = checked_page(out, write_tournament_report(out, config, board, records))
    names, wins = board["head_to_head"]["agents"], board["head_to_head"]["wins"]
    header, *body = page.tables["head-to-head-table"]
    assert header[1:] == names and [row[0] for row in body] == names
    for i, row in enumerate(body):
        assert row[1 + i] == "-"
        assert [int(cell) for j, cell in enumerate(row[1:]) if j != i] == [w for j, w in enumerate(wins[i]) if j != i]
    assert sum(map(sum, wins)) == len(records)  # two cars a race: one pair ordered per race


def test_solver_health_is_the_mean_of_the_race_records(planner_run):
    config, out, board, records = planner_run
    page = checked_page(out, write_tournament_report(out, config, board, records))
    rows = page.rows("solver-health-table")
    assert [row["agent"] for row in rows] == [row["agent"] for row in board["rows"]]
    for shown in rows:
        cars = [car for record in records for car in record["cars"] if car["agent"] == shown["agent"]]
        assert_health_row(shown, expected_health(cars))
    planner = next(row for row in rows if row["agent"] == PLANNER)
    assert planner["converged re-plans"] != "-" and planner["iterations / re-plan"] != "-"
    assert all(row["converged re-plans"] == "-" for row in rows if row["agent"] != PLANNER)  # scripted: no solver


def test_races_table_lists_every_race_in_schedule_order(planner_run):
    config, out, board, records = planner_run
    page = checked_page(out, write_tournament_report(out, config, board, records))
    position = {race["id"]: k for k, race in enumerate(tournament.schedule(config))}
    shown = page.rows("races-table")
    expected = sorted(records, key=lambda record: position[record["id"]])
    assert [row["id"] for row in shown] == [record["id"] for record in expected]
    for row, record in zip(shown, expected):
        assert int(row["K"]) == record["race"] == position[record["id"]]
        assert row["lineup (by start slot)"] == " vs ".join(car["agent"] for car in record["cars"])
        assert row["winner"] == record["order"][0]
        assert int(row["overtakes"]) == record["overtakes"] and int(row["steps"]) == record["steps"]
        gap = record["gap"]
        assert row["gap"] == (f"{gap['seconds']:.2f} s" if "seconds" in gap else f"{gap['metres']:.1f} m")


def closest_then_busiest_then_first(records: list[dict], out: Path, cars: str) -> list[int]:
    """The races a report should embed (schedule indices), worked out from the records:
    the closest finish, the most overtakes (if any), then the first races, each once and
    only races with a replay file."""
    candidates = sorted((r for r in records if (out / r["replay"]).is_file()), key=lambda r: r["race"])
    timed = [r for r in candidates if r["gap"] and "seconds" in r["gap"]
             and all(car["finish_time"] is not None for car in r[cars])]
    picks = [min(timed, key=lambda r: (r["gap"]["seconds"], r["race"]))["race"]] if timed else []
    overtaking = [r for r in candidates if r["overtakes"] > 0 and r["race"] not in picks]
    if overtaking:
        picks.append(min(overtaking, key=lambda r: (-r["overtakes"], r["race"]))["race"])
    return picks + [r["race"] for r in candidates if r["race"] not in picks]


def test_replays_embed_the_closest_finish_the_most_overtakes_and_the_first_race(planner_run):
    config, out, board, records = planner_run
    assert all((out / record["replay"]).is_file() for record in records)
    page = checked_page(out, write_tournament_report(out, config, board, records, replays=3))
    figures = [(figure, src) for figure, src in page.images if figure and figure.startswith("replay-")]
    expected = closest_then_busiest_then_first(records, out, "cars")[:3]
    assert [figure for figure, _ in figures] == [f"replay-{k}" for k in expected]
    for _, src in figures:
        gif = Image.open(io.BytesIO(image_bytes(src)))
        assert gif.format == "GIF" and gif.n_frames > 1  # animated
    # the races table links exactly the embedded races to their replays
    linked = sorted(ref for _, ref in page.refs if ref.startswith("#replay-"))
    assert linked == sorted(f"#replay-{k}" for k in expected)


def test_a_race_whose_replay_file_is_gone_is_not_chosen(planner_run, tmp_path):
    config, original, board, records = planner_run
    out = tmp_path / "run"
    shutil.copytree(original, out)
    first_choice = closest_then_busiest_then_first(records, out, "cars")[0]
    (out / next(record["replay"] for record in records if record["race"] == first_choice)).unlink()
    page = checked_page(out, write_tournament_report(out, config, board, records, replays=2))
    shown = [figure for figure, _ in page.images if figure and figure.startswith("replay-")]
    assert f"replay-{first_choice}" not in shown
    assert shown == [f"replay-{k}" for k in closest_then_busiest_then_first(records, out, "cars")[:2]]


def test_old_records_without_race_replay_or_iterations_still_report(planner_run, tmp_path):
    """Records from before replays: no ``race``, no ``replay``, no ``solver_iterations_mean``
    (here in the first race only: the mean is over the races that have it)."""
    config, original, board, records = planner_run
    out = tmp_path / "old"
    out.mkdir()
    for name in ("results.jsonl", "tournament.json"):
        shutil.copy(original / name, out / name)
    old = [{k: v for k, v in record.items() if k not in ("race", "replay")} for record in records]
    old[0]["cars"] = [{k: v for k, v in car.items() if k != "solver_iterations_mean"} for car in old[0]["cars"]]
    assert any(car["agent"] == PLANNER for car in old[0]["cars"])  # the planner's first race loses its iterations
    page = checked_page(out, write_tournament_report(out, config, board, old))
    assert not [figure for figure, _ in page.images if figure]
    assert "no replay was recorded" in page.section_text["replays"].lower()
    assert "newer version" in page.section_text["replays"]
    position = {race["id"]: k for k, race in enumerate(tournament.schedule(config))}
    assert [int(row["K"]) for row in page.rows("races-table")] == sorted(position[r["id"]] for r in old)
    planner = next(row for row in page.rows("solver-health-table") if row["agent"] == PLANNER)
    cars = [car for record in old for car in record["cars"] if car["agent"] == PLANNER]
    assert sum("solver_iterations_mean" in car for car in cars) == len(cars) - 1
    assert_health_row(planner, expected_health(cars))
    linked = {ref for key, ref in page.refs if key == "href" and not ref.startswith("#")}
    assert linked == {"results.jsonl", "tournament.json"}  # only the files this folder has


def test_a_report_before_any_race(planner_run, tmp_path):
    config, _, _, _ = planner_run
    page = checked_page(tmp_path, write_tournament_report(tmp_path, config, tournament.leaderboard(config, []), []))
    assert f"0 of {len(tournament.schedule(config))} scheduled races" in page.section_text["run"]
    rows = page.rows("leaderboard-table")
    assert sorted(row["agent"] for row in rows) == sorted(config.agents)
    assert all(row["wins/races"] == "0/0" and row["win rate [95% CI]"] == "- [0.00, 1.00]" for row in rows)
    assert "races-table" not in page.tables


def test_time_trial_report_ranks_by_finish_time(time_trial):
    config, out, board, records = time_trial
    page = checked_page(out, write_tournament_report(out, config, board, records, replays=2))
    rows = page.rows("leaderboard-table")
    assert [row["agent"] for row in rows] == [row["agent"] for row in board["rows"]]
    finished = [row for row in board["rows"] if row["finished"]]
    assert len(finished) >= 2
    times = [row["mean_finish_time_s"] for row in finished]
    assert times == sorted(times)  # the board's order, which the table keeps
    for shown, row in zip(rows, board["rows"]):
        assert shown["finished"] == f"{row['finished']}/{row['races']}"
        assert_shown(shown["mean finish time [s]"], row["mean_finish_time_s"], 2)
        assert_shown(shown["best [s]"], row["best_finish_time_s"], 2)
        assert "rating" not in shown
    assert "head-to-head-table" not in page.tables and "time trial" in page.section_text["head-to-head"]
    assert not (out / "head_to_head.png").exists() and not [src for figure, src in page.images if figure is None]
    for row, record in zip(page.rows("races-table"), records):
        assert row["gap"] == "-" and record["gap"] is None
        assert_shown(row["winner's time [s]"], record["cars"][0]["finish_time"], 2)
    # alone there is no finish to be close and no one to overtake: the first races
    shown = [figure for figure, _ in page.images if figure]
    assert shown == [f"replay-{k}" for k in closest_then_busiest_then_first(records, out, "cars")[:2]]
    assert shown == [f"replay-{record['race']}" for record in records[:2]]


@pytest.mark.parametrize("track", ["trefoil", "Monza"])
def test_tournament_reports_on_the_trefoil_and_a_real_circuit(track, tmp_path):
    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), track=track, race_distance=150.0, grids=1,
                              max_steps=400)
    board, records = run(config, tmp_path)
    page = checked_page(tmp_path, write_tournament_report(tmp_path, config, board, records))
    assert track in page.section_text["run"]
    assert [row["agent"] for row in page.rows("leaderboard-table")] == [row["agent"] for row in board["rows"]]
    assert len(page.rows("races-table")) == len(records) == 2
    assert {figure for figure, _ in page.images if figure} <= {f"replay-{record['race']}" for record in records}
    assert len([figure for figure, _ in page.images if figure]) == 2


def test_strings_from_the_run_are_escaped(tmp_path):
    """A track file under a folder named with ``<``, ``&`` and quotes shows as text, never as markup."""
    folder = tmp_path / 'a<b&c"d\'e>'
    folder.mkdir()
    angle = np.linspace(0.0, 2 * np.pi, 126, endpoint=False)
    rows = [f"{100 * math.cos(a):.3f},{100 * math.sin(a):.3f},6.0,6.0" for a in angle]  # a circle, 200 m across
    (folder / "ring.csv").write_text("# x_m,y_m,w_tr_right_m,w_tr_left_m\n" + "\n".join(rows) + "\n")
    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), track=str(folder / "ring.csv"),
                              race_distance=100.0, grids=1, max_steps=300)
    out = tmp_path / "out"
    board, records = run(config, out)
    text = write_tournament_report(out, config, board, records, replays=0).read_text()
    assert str(folder) not in text and "<b&" not in text
    page = checked_page(out, out / "report.html")
    assert str(folder / "ring.csv") in page.section_text["run"]  # shown as written, once unescaped
    assert "none was asked to be embedded" in page.section_text["replays"]


def test_sweep_report(planner_sweep):
    config, out, rows, records = planner_sweep
    page = checked_page(out, write_sweep_report(out, config, rows, records))
    assert f"{len(records)} of {len(sweep.schedule(config))} scheduled races" in page.section_text["run"]
    assert "agent0.c_collision" in page.section_text["run"]
    linked = {ref for key, ref in page.refs if key == "href" and not ref.startswith("#")}
    assert {"results.jsonl", "summary.csv", "summary.json", "sweep.json", "sweep.png"} <= linked
    shown = page.rows("leaderboard-table")
    bars = ci_bars(page, "leaderboard-table")
    assert len(shown) == len(rows) == len(bars) == 4  # points x agents
    points = config.points()
    for cells, row, bar in zip(shown, rows, bars):
        assert float(cells["agent0.c_collision"]) == points[row["point"]]["agent0.c_collision"]
        assert cells["agent"] == f"{row['agent']}: {row['spec']}"
        assert cells["wins/races"] == f"{row['wins']}/{row['races']}"
        assert cells["finished"] == f"{row['finished']}/{row['races']}"
        assert_wilson(cells["win rate [95% CI]"], bar, row["wins"], row["races"])
        assert_shown(cells["mean place"], row["mean_place"], 2)
        assert_shown(cells["margin [s]"], row["mean_margin_s"], 2)
    health = page.rows("solver-health-table")
    assert len(health) == len(rows)
    for cells, row in zip(health, rows):
        cars = [record["agents"][row["agent"]] for record in records if record["point_index"] == row["point"]]
        assert_health_row(cells, expected_health(cars))
    assert any(cells["iterations / re-plan"] != "-" for cells in health)
    plots = [src for figure, src in page.images if figure is None]
    assert [image_bytes(src) for src in plots] == [(out / "sweep.png").read_bytes()]
    races = page.rows("races-table")
    assert [int(row["K"]) for row in races] == [record["race"] for record in records] == list(range(len(records)))
    for row, record in zip(races, records):
        assert row["point"] == f"agent0.c_collision={record['point']['agent0.c_collision']}"
        lineup = sorted(record["agents"], key=lambda car: car["slot"])
        assert row["lineup (by start slot)"] == " vs ".join(car["agent"] for car in lineup)
        assert row["winner"] == next(car["agent"] for car in record["agents"] if car["place"] == 1)
    figures = [figure for figure, _ in page.images if figure]
    assert figures == [f"replay-{k}" for k in closest_then_busiest_then_first(records, out, "agents")[:2]]


def test_time_trial_sweep_report(tmp_path):
    config = SweepConfig(lineup=("lane-keeping",), parameters=(("max_steps", (30, 400)),), track="straight",
                         race_distance=120.0, grids=1)
    rows = sweep.run_sweep(config, tmp_path, progress=False)["rows"]
    records = sweep.read_results(tmp_path)
    page = checked_page(tmp_path, write_sweep_report(tmp_path, config, rows, records, replays=1))
    shown = page.rows("leaderboard-table")
    assert [cells["max_steps"] for cells in shown] == ["30", "400"]
    assert [cells["finished"] for cells in shown] == [f"{row['wins']}/{row['races']}" for row in rows] == ["0/1", "1/1"]
    for cells, row, bar in zip(shown, rows, ci_bars(page, "leaderboard-table")):
        assert_wilson(cells["finished share [95% CI]"], bar, row["wins"], row["races"])
        assert_shown(cells["finish time [s]"], row["mean_finish_time_s"], 2)
    assert [figure for figure, _ in page.images if figure] == ["replay-0"]


@pytest.mark.slow
def test_report_renders_in_chromium_with_a_readable_leaderboard(tmp_path):
    """The page as a browser draws it: a screenshot by headless Chromium, read back by OCR."""
    chromium, tesseract = shutil.which("chromium"), shutil.which("tesseract")
    if chromium is None or tesseract is None:
        pytest.skip(f"needs chromium and tesseract on PATH (chromium: {chromium}, tesseract: {tesseract})")
    config = TournamentConfig(agents=("lane-keeping", "constant-speed"), track="trefoil", race_distance=150.0,
                              grids=1, max_steps=400)
    board, records = run(config, tmp_path / "run")
    report = write_tournament_report(tmp_path / "run", config, board, records)
    shot = tmp_path / "report.png"
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1280,1600", f"--screenshot={shot}",
                    report.as_uri()], check=True, capture_output=True, timeout=120)
    image = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert image.shape == (1600, 1280)
    assert image.std() > 10 and (image < 100).mean() > 0.005  # drawn: dark text on the light page, not blank
    ocr = subprocess.run([tesseract, str(shot), "stdout"], check=True, capture_output=True, text=True,
                         timeout=120).stdout

    def normal(text: str) -> str:
        return re.sub(r"[^a-z0-9]", "", text.lower())

    text = normal(ocr)
    assert "leaderboard" in text
    for row in board["rows"]:
        assert normal(row["agent"]) in text
        lo, hi = row["win_rate_ci95"]
        assert normal(f"{row['win_rate']:.2f} [{lo:.2f}, {hi:.2f}]") in text


def test_a_long_race_is_drawn_in_at_most_the_frame_cap():
    from experiments.report import REPLAY_EVERY, REPLAY_FRAMES, replay_every

    for steps in (0, 90, 596, 597, 600, 3000, 12_345):
        every = replay_every(steps)
        frames = len(range(0, steps + 1, every)) + (steps % every > 0)  # the steps Replay.frames draws
        assert every >= REPLAY_EVERY and frames <= REPLAY_FRAMES
        assert (every == REPLAY_EVERY) == (steps <= (REPLAY_FRAMES - 1) * REPLAY_EVERY)
