"""The slipstream scene (experiments.slipstream_pass): its measures on hand-made records, and
(slow) the feedback planner passing out of the wake on Monza's main straight."""

from __future__ import annotations

import numpy as np
import pytest

from experiments import slipstream_pass as sp


def _record(wake: str, margin: list[float], s: list[float], tow: list[float], place: int = 1) -> dict:
    n = [[0.0, 0.5 * k] for k in range(len(s))]
    return {"follower": "ilqgame-fb", "wake": wake, "gap": 12.0, "margin": margin, "s": s, "n": n, "tow": tow,
            "place": place, "cars": [{"collision_steps": 1}, {"collision_steps": 2}]}


def test_the_scene_measures_where_the_follower_got_ahead_and_its_best_margin_on_the_straight():
    s = [0.0, 300.0, 600.0, 700.0, 800.0]
    margin = [-12.0, -1.0, 2.5, 3.0, -4.0]
    assert sp.first_ahead(s, margin) == 600.0
    assert sp.first_ahead(s, [-1.0] * 5) is None
    assert sp.best_margin(s, margin, sp.STRAIGHT_END) == 2.5  # 700 m and beyond are not the straight
    row = sp.summary_rows([_record("game", margin, s, [0.3, 0.2, 0.0, 0.0, 0.0], place=2)])[0]
    assert row["ahead_s"] == 600.0 and row["straight_margin"] == 2.5 and row["place"] == 2
    assert row["mean_tow"] == pytest.approx((0.3 + 0.2 + 0.0) / 3, rel=1e-15)  # over the steps behind
    assert row["largest_offset"] == 2.0 and row["contact_steps"] == 3
    table = sp.table([_record("none", [-12.0] * 5, s, [0.0] * 5), _record("game", margin, s, [0.3] * 5)])
    lines = table.splitlines()
    assert lines[2].startswith("| ilqgame-fb | game | 12 | 600 | +2.5 |")  # wakes in WAKES order
    assert lines[3].startswith("| ilqgame-fb | none | 12 | - | -12.0 |")


def test_the_scene_refuses_an_unknown_wake(tmp_path):
    with pytest.raises(ValueError, match=r"wake must be one of \('game', 'physics', 'none'\)"):
        sp.run(tmp_path, followers=["ilqr"], gaps=[12.0], wakes=["tow"], progress=False)


def test_the_scene_starts_the_follower_behind_at_the_gap():
    x0 = sp.scene_start(20.0, 68.5)
    assert x0.shape == (2, 6)
    assert x0[1, 0] - x0[0, 0] == 20.0 and np.all(x0[:, 1] == 68.5) and np.all(x0[:, 2:] == 0.0)


@pytest.mark.slow
def test_the_feedback_planner_passes_out_of_the_wake_on_the_straight():
    """12 m behind the racing-line driver, an equal car: with the wake in the physics and its
    game the feedback planner rides the tow (a third of its drag) and pulls out to get ahead
    before the straight's end; with no wake anywhere it stays behind on the straight."""
    import racing_env

    racing_env.configure_for_racing()
    speed = sp.start_speed()
    towed = sp.race_scene("ilqgame-fb", "game", 12.0, speed)
    still = sp.race_scene("ilqgame-fb", "none", 12.0, speed)
    assert not towed["faults"] and not still["faults"]
    ahead = sp.first_ahead(towed["s"], towed["margin"])
    assert ahead is not None and ahead < sp.STRAIGHT_END
    assert max(towed["tow"]) > 0.25
    assert sp.best_margin(still["s"], still["margin"], sp.STRAIGHT_END) < 0.0
    assert max(still["tow"]) == 0.0
