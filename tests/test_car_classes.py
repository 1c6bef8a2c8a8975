

def test_the_race_jerk_weight_is_scaled_for_a_class_jerk_limits(cars):
    """The racing jerk weight is tuned at the paper car's 30 m/s^3: a car with other jerk
    limits plans with r (30 / j_max)^2, the same cost for the same share of its limits."""
    from racing_env.config import RaceConfig
    from racing_env.costs import RACING_JERK_WEIGHT, racing_weights

    assert racing_weights(vehicle=cars["paper"]) == racing_weights()
    av21 = racing_weights(vehicle=cars["av21"])
    assert av21.r_jx == pytest.approx(RACING_JERK_WEIGHT * (30.0 / float(cars["av21"].jx_max)) ** 2, rel=1e-12)
    assert float(cars["av21"].jx_max) ** 2 * av21.r_jx == pytest.approx(30.0**2 * RACING_JERK_WEIGHT, rel=1e-12)
    field = RaceConfig(num_agents=2, vehicles=[cars["paper"], cars["av21"]]).game_weights()
    assert [w.r_jy for w in field] == [RACING_JERK_WEIGHT, av21.r_jy]
