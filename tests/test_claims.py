"""Paired claims on hand-made duel records: the differences are exact by construction."""

import numpy as np
import pytest

from experiments.claims import agent_mean, bootstrap_interval, car_races, compare, duel_difference, head_to_head


def _car(agent: str, place: int, start: int, faults: int = 0, blocks: int = 0) -> dict:
    return {"agent": agent, "place": place, "start_place": start, "finish_time": 60.0 + place, "faults": faults,
            "collision_steps": 3 * faults, "time_off_track": 0.0, "overtakes": 0, "blocks": blocks,
            "defending_moves": blocks}


def _duel(grid: int, first: dict, second: dict) -> dict:
    return {"id": f"{first['agent']}|{second['agent']}@grid{grid}", "grid": grid, "cars": [first, second]}


def _records() -> list[dict]:
    """Leader beats the opponent on every grid from slot 2 and blocks twice; Nash wins half and
    blocks never; leader answers for one incident per race, Nash for none."""
    records = []
    for grid in range(4):
        records.append(_duel(grid, _car("leader", 1, 2, faults=1, blocks=2), _car("opp", 2, 1)))
        records.append(_duel(grid, _car("nash", 1 if grid % 2 else 2, 2), _car("opp", 2 if grid % 2 else 1, 1)))
        records.append(_duel(grid, _car("leader", 2, 1), _car("nash", 1, 2)))
    return records


def test_a_paired_difference_is_the_mean_of_the_matched_races_and_says_its_verdict():
    rows = car_races(_records(), "trefoil")
    wins = compare(rows, "leader", "nash", "win")
    assert wins.pairs == 4  # against opp, same grid and slot; their own duels are left out
    assert wins.difference == pytest.approx(0.5, abs=1e-12)
    # four pairs with differences 1, 0, 1, 0: a resample of all zeros has chance 1/16 > 2.5%
    assert wins.low == 0.0 and wins.verdict == "not separated"
    blocks = compare(rows, "leader", "nash", "blocks")
    assert (blocks.difference, blocks.low, blocks.high) == (2.0, 2.0, 2.0)
    assert blocks.verdict == "reproduced"
    safer = compare(rows, "nash", "leader", "at-fault incidents")
    assert safer.difference == -1.0 and safer.verdict == "refuted"
    assert compare(rows, "leader", "nobody", "win").verdict == "not measurable"


def test_a_duel_difference_compares_the_two_cars_of_each_race():
    rows = car_races(_records(), "trefoil")
    # leader (slot 1) against nash (slot 2) on four grids: nash wins every one
    wins = duel_difference(rows, "nash", "leader", "win")
    assert wins.pairs == 4 and (wins.difference, wins.low, wins.high) == (1.0, 1.0, 1.0)
    assert wins.verdict == "reproduced" and duel_difference(rows, "leader", "nash", "win").verdict == "refuted"
    # leader against opp: one incident a race for leader, none for opp; nash's duels with opp are not paired
    faults = duel_difference(rows, "leader", "opp", "at-fault incidents")
    assert faults.pairs == 4 and faults.difference == 1.0
    assert duel_difference(rows, "nash", "nobody", "win").pairs == 0


def test_means_head_to_head_and_intervals():
    rows = car_races(_records(), "trefoil")
    mean = agent_mean(rows, "nash", "win")
    assert (mean.value, mean.n) == (pytest.approx(6 / 8), 8)
    assert mean.low < 0.75 < mean.high
    table = head_to_head(rows, ["leader", "nash", "opp"])
    assert table[0, 1] == 0.0 and table[1, 0] == 1.0 and table[0, 2] == 1.0 and table[1, 2] == 0.5
    assert np.isnan(table[0, 0])
    low, high = bootstrap_interval(np.array([0.0, 1.0] * 50))
    assert 0.35 < low < 0.5 < high < 0.65  # 0.5 +- 1.96 * 0.05


def test_only_duels_are_compared():
    race = _duel(0, _car("a", 1, 1), _car("b", 2, 2))
    race["cars"].append(_car("c", 3, 3))
    with pytest.raises(ValueError, match="duels"):
        car_races([race], "trefoil")


def test_the_stackelberg_study_reports_every_claim_from_its_folders(tmp_path):
    """The study's report reads each circuit's results.jsonl and writes every claim's row."""
    import json

    from experiments import stackelberg_study as study

    folder = tmp_path / "trefoil"
    folder.mkdir()
    records = []
    for grid in range(2):
        for other in ("ilqr", "ilqgame-ol"):
            for agent in ("ilqgame-leader", "ilqgame-fb", "ilqgame-follower"):
                records.append(_duel(grid, _car(agent, 1, 1, blocks=1 if agent == "ilqgame-leader" else 0),
                                     _car(other, 2, 2)))
    folder.joinpath("results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    rows = study.load(tmp_path, circuits=(("trefoil", "trefoil", None),))
    assert len(rows) == 2 * len(records)
    page = study.report(rows)
    for claim in study.CLAIMS:
        assert claim.text in page
    line = next(row for row in page.splitlines() if row.startswith("| leading blocks more than Nash play"))
    assert "| +1.000 | [+1.000, +1.000] | 4 | reproduced |" in line
