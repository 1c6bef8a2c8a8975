"""The outlook study's page (experiments.outlook): its numbers are the records', a changed
number or a changed record fails `racing study check`, and the claims' verdicts follow their
intervals. The run folder is the small study kept in tests/data/outlook-small (raced once
with `racing study run`, its replays left out)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from experiments.claims import CarRace
from experiments.cli import main
from experiments.outlook import Claim, Run, check_page, circuit_classes, duel_rows, judge, page
from experiments.standings import won_race

SMALL = Path(__file__).parent / "data" / "outlook-small"
RUN, PAGE = SMALL / "run", SMALL / "page.md"
ROOT = Path(__file__).parents[1]
OUTLOOK_PAGE, OUTLOOK_RUN = ROOT / "docs" / "experiments" / "outlook.md", ROOT / "docs" / "studies" / "outlook-run"


def test_the_kept_page_is_its_run_folders_page():
    assert check_page(PAGE, RUN) == []
    assert main(["study", "check", str(PAGE), "--run", str(RUN)]) == 0


# slow (13 s of the default run's budget): the default run checks the small study's page
# through the same code (test_the_kept_page_is_its_run_folders_page)
@pytest.mark.slow
def test_the_outlook_page_is_its_committed_runs_page():
    """docs/experiments/outlook.md against the records of the study's run kept beside its file
    (its replays left out: the pass maps are figures, not compared)."""
    assert check_page(OUTLOOK_PAGE, OUTLOOK_RUN) == []


def test_the_pages_numbers_are_the_records():
    """Numbers of the page computed here straight from results.jsonl: each head-to-head cell
    (wins over races) and each agent's number of duels."""
    records = [json.loads(line) for line in (RUN / "results.jsonl").read_text().splitlines()]
    duels = [r for r in records if r["part"].startswith("duel-")]
    text = PAGE.read_text()
    matrix = text.split("## Head to head")[1].split("##")[0]
    cells, header = {}, None
    for line in matrix.splitlines():
        row = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|  |"):
            header = row[1:]
        elif line.startswith("| "):
            cells[row[0]] = row[1:]
    checked = 0
    for a in header:
        for b in header:
            races = [r for r in duels if {c["agent"].split(":")[0] for c in r["agents"]} == {a, b} and a != b]
            if not races:
                continue
            wins = sum(won_race(c, 2) for r in races for c in r["agents"] if c["agent"].split(":")[0] == a)
            assert cells[a][header.index(b)] == f"{wins / len(races):.2f} ({len(races)})"
            checked += 1
    assert checked >= 8
    both = text.split("**Both cars**")[1].split("**")[0]
    agents = 0
    for line in both.splitlines():
        if line.startswith("| ") and not line.startswith("| agent"):
            agent, races = [c.strip() for c in line.strip("|").split("|")][:2]
            assert int(races) == sum(1 for r in duels for c in r["agents"] if c["agent"].split(":")[0] == agent)
            agents += 1
    assert agents == 4


def test_a_changed_number_on_the_page_fails_the_check(tmp_path, capsys):
    lines = PAGE.read_text().splitlines()
    row = next(k for k, line in enumerate(lines) if line.startswith("| ilqgame-fb |"))
    changed = lines[row].replace("0.", "9.", 1)
    assert changed != lines[row]
    page_path = tmp_path / "page.md"
    page_path.write_text("\n".join(lines[:row] + [changed] + lines[row + 1:]) + "\n")
    differences = check_page(page_path, RUN)
    assert len(differences) == 1 and differences[0].startswith(f"line {row + 1}:")
    assert main(["study", "check", str(page_path), "--run", str(RUN)]) == 1
    assert "1 line(s) differ" in capsys.readouterr().err


def test_a_changed_record_fails_the_check(tmp_path):
    run = tmp_path / "run"
    shutil.copytree(RUN, run)
    records = [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines()]
    duel = next(r for r in records if r["part"].startswith("duel-") and all(c["finish_time"] for c in r["agents"]))
    duel["agents"][0]["finish_time"] += 0.5  # a margin and a lap time change
    (run / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    assert check_page(PAGE, run) != []


def test_the_page_says_how_many_races_its_run_log_did_not_time(tmp_path):
    run = tmp_path / "run"
    shutil.copytree(RUN, run)
    log = json.loads((run / "run.json").read_text())
    log["invocations"][0]["races"] -= 5  # five races of an invocation killed before it logged them
    (run / "run.json").write_text(json.dumps(log))
    text = page(Run.read(run), run_name="run", study_file="study.toml")
    assert "for 33 races" in text and "(5 more races were run by invocations killed before" in text


def test_the_reading_is_kept_by_the_report_and_left_out_by_the_check(tmp_path):
    page_path = tmp_path / "page.md"
    shutil.copy(PAGE, page_path)
    lines = PAGE.read_text().splitlines()
    at = lines.index("## Agents in their duels")
    reading = ["<!-- reading -->", "## Reading", "", "Prose with a number the run does not hold: 12.5.", "<!-- /reading -->"]
    page_path.write_text("\n".join(lines[:at] + reading + [""] + lines[at:]) + "\n")
    assert check_page(page_path, RUN) == []
    assert main(["study", "report", str(RUN), "--page", str(page_path), "--study", "tests/data/outlook-small/study.toml"]) == 0
    written = page_path.read_text().splitlines()
    assert written[at: at + len(reading) + 1] == reading + [""] and written[at + len(reading) + 1] == lines[at]
    assert check_page(page_path, RUN) == []
    # a number outside the reading still fails, counted in the page's lines without the reading
    row = next(k for k, line in enumerate(written) if line.startswith("| ilqgame-fb |"))
    written[row] = written[row].replace("0.", "9.", 1)
    page_path.write_text("\n".join(written) + "\n")
    (difference,) = check_page(page_path, RUN)
    assert difference.startswith(f"line {row + 1 - len(reading) - 1}:")
    page_path.write_text("\n".join(lines[:at] + reading[:-1] + lines[at:]) + "\n")
    with pytest.raises(ValueError, match="never closes"):
        check_page(page_path, RUN)


def test_a_page_not_written_by_the_report_is_refused(tmp_path):
    other = tmp_path / "page.md"
    other.write_text("# a page\n")
    with pytest.raises(ValueError, match="not written by racing study report"):
        check_page(other, RUN)
    with pytest.raises(ValueError, match="not a study's run folder"):
        Run.read(tmp_path)


def _rows(wins_of_a: list[int], measure_a: list[float], measure_b: list[float]) -> list[CarRace]:
    """Duels of a against b (a's wins), and races of a and of b against c on the same keys."""
    rows = [CarRace("a", "b", "t", k, 1, {"win": float(w)}) for k, w in enumerate(wins_of_a)]
    rows += [CarRace("a", "c", "t", k, 1, {"m": v}) for k, v in enumerate(measure_a)]
    rows += [CarRace("b", "c", "t", k, 1, {"m": v}) for k, v in enumerate(measure_b)]
    return rows


def test_verdicts_follow_the_intervals():
    head = Claim("test", "a beats b", "a", "b")
    assert judge(head, _rows([1] * 18 + [0] * 2, [], [])).endswith("of 20: reproduced")  # Wilson [0.70, 0.97]
    assert judge(head, _rows([1] * 2 + [0] * 18, [], [])).endswith("of 20: refuted")
    assert judge(head, _rows([1, 0] * 10, [], [])).endswith("of 20: not separated")
    assert judge(head, _rows([], [], [])) == "not raced"
    from experiments import outlook

    outlook.FORMS["m"] = "{:.2f}"
    try:
        paired = Claim("test", "a is higher on m", "a", "b", "m")
        assert judge(paired, _rows([], [2.0] * 10, [1.0] * 10)) == "+1.00 [+1.00, +1.00] of 10 pairs: reproduced"
        assert judge(paired, _rows([], list(np.arange(10.0)), list(np.arange(10.0))[::-1])).endswith("not separated")
    finally:
        del outlook.FORMS["m"]


def test_circuit_classes_split_the_circuits_at_their_medians():
    classes = circuit_classes(["Monza", "Norisring", "Spa", "Budapest"])
    assert classes["Monza"]["speed"] == "fast" and classes["Budapest"]["speed"] == "slow"
    assert {c["speed"] for c in classes.values()} == {"fast", "slow"}
    assert {c["corners"] for c in classes.values()} == {"many", "few"}


def test_duel_rows_pair_each_car_with_its_opponent():
    run = Run.read(RUN)
    rows = duel_rows(run)
    assert len(rows) == 2 * len(run.part_records("duel-"))
    for row, point in rows:
        assert row.track == f"{point['track']}/{point['car']}" and row.agent != row.opponent
    assert page(run, "run", "study.toml").count("## ") >= 4


def test_the_figures_are_drawn_from_the_run(tmp_path):
    from experiments.outlook import FIGURE_MARGINS, FIGURE_WIN_RATES, draw_figures

    paths = draw_figures(Run.read(RUN), tmp_path / "figures")
    assert [p.name for p in paths] == [FIGURE_WIN_RATES, FIGURE_MARGINS]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_the_pass_maps_place_every_pass_the_records_count(tmp_path):
    """A duel study of scripted cars (the faster one starting behind on one of the two grids):
    the passes read from its replays are as many as its records count, each on its circuit,
    and each car class gets its map."""
    from experiments.outlook import FIGURE_PASSES, draw_pass_maps, duel_passes
    from experiments.study import load_study, run_study

    path = tmp_path / "duels.toml"
    path.write_text('name = "passes"\nquestion = "Where do passes happen?"\n[[part]]\nname = "duel-lk-cs"\n'
                    'lineup = ["lane-keeping", "constant-speed:target_speed=12"]\ntrack = "straight"\n'
                    'race_distance = 250.0\ngrids = 1\n[part.parameters]\ncar = ["paper"]\n')
    run_study(load_study(path), tmp_path / "run", progress=False)
    records = Run.read(tmp_path / "run").records
    counted = sum(car["overtakes"] for record in records for car in record["agents"])
    passes = duel_passes(tmp_path / "run")
    assert counted >= 1 and len(passes) == counted
    assert all(p["track"] == "straight" and p["car"] == "paper" and 0 <= p["lap_s"] <= 300 for p in passes)
    (figure,) = draw_pass_maps(passes, ["straight"], tmp_path / "figures")
    assert figure.name == FIGURE_PASSES.format(car="paper") and figure.stat().st_size > 5_000
