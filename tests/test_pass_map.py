"""experiments.pass_map: the zone of a spot on the limit lap (braking, corner, straight) on a
hand-built profile, and the zones of arc lengths on any lap."""

from __future__ import annotations

import numpy as np

from experiments import pass_map


def test_classify_zones_braking_before_corner_before_straight():
    # ax [m/s^2], ay [m/s^2] and the lateral limit [m/s^2] at six points of a limit lap
    ax = np.array([0.0, -1.0, -1.01, -5.0, 2.0, 0.5])
    ay = np.array([0.0, 0.0, 0.0, 20.0, -10.01, 10.0])
    limit = np.array([20.0, 20.0, 20.0, 30.0, 20.0, 20.0])
    zones = pass_map.classify_zones(ax, ay, limit)
    # -1.0 is not under the threshold; braking wins over cornering; |ay| counts either sign;
    # exactly half the limit is not a corner
    assert [pass_map.ZONES[z] for z in zones] == ["straight", "straight", "braking", "braking", "corner", "straight"]
    assert pass_map.BRAKING_AX == -1.0 and pass_map.CORNER_SHARE == 0.5


def test_zone_at_nearest_grid_point_on_any_lap():
    zones = np.array([2, 0, 0, 1, 2])  # grid points at 0, 10, 20, 30, 40 m of a 50 m lap
    s = np.array([0.0, 4.9, 5.1, 26.0, 44.0, 46.0, 60.0, 133.0])
    # 46 m is nearest the lap's end, which is its start (0 m); 60 and 133 m are 10 and 33 m on the lap
    assert pass_map.zone_at(s, zones, ds=10.0, length=50.0).tolist() == [2, 2, 0, 1, 2, 2, 0, 1]


def test_pass_table_counts_made_and_suffered_per_zone():
    passes = [{"passer_agent": "a", "passed_agent": "b", "zone": "braking"},
              {"passer_agent": "a", "passed_agent": "b", "zone": "corner"},
              {"passer_agent": "b", "passed_agent": "a", "zone": "braking"}]
    rows = {r["agent"]: r for r in pass_map.pass_table(passes)}
    assert rows["a"]["made"] == {"braking": 1, "corner": 1, "straight": 0} and rows["a"]["suffered_total"] == 1
    assert rows["b"]["made"] == {"braking": 1, "corner": 0, "straight": 0} and rows["b"]["suffered_total"] == 2
