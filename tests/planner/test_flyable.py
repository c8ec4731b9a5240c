import dataclasses

import numpy as np
import pytest

from bdf.region.route import VEHICLES, Vehicle, envelope, turn_radii
from planner.flyable import flyable


def random_polyline(rng, n=8) -> np.ndarray:
    """Corners of up to 180 degrees, segments of 0.3-4 km, altitudes 1,000-2,500 m apart by
    far more than a vehicle can climb between corners."""
    xy = np.cumsum(rng.uniform(-3000.0, 3000.0, (n, 2)), axis=0)
    return np.column_stack([xy, rng.uniform(1000.0, 2500.0, n)])


@pytest.mark.parametrize("name", sorted(VEHICLES))
def test_every_flyable_path_holds_the_envelope_sampled_every_10_m(name):
    """200 random polylines: every path flies within the vehicle's envelope (radius, climb,
    descent, altitudes, read every 10 m to 2 %), from the start (its altitude kept) to the
    goal (its altitude reached wherever the path is long enough to climb there). With the
    radius 10 % larger every path that turns at its limit fails, and with the climb and descent 10 %
    smaller every path that climbs or descends at its limit somewhere (most turn, and most
    climb at their limit)."""
    craft = VEHICLES[name]
    tighter = dataclasses.replace(craft, min_turn_radius_m=1.1 * craft.min_turn_radius_m)
    steeper = dataclasses.replace(
        craft, max_climb_deg=0.9 * craft.max_climb_deg, max_descent_deg=0.9 * craft.max_descent_deg
    )
    rng = np.random.default_rng(7)
    turning = at_limit = 0
    for _ in range(200):
        P = random_polyline(rng)
        F = flyable(P, craft)
        verdict = envelope(F, craft)
        assert verdict["flyable"], verdict
        np.testing.assert_allclose(F[[0, -1], :2], P[[0, -1], :2], atol=1e-6)
        assert F[0, 2] == P[0, 2]
        climbable = (
            np.tan(np.radians(min(craft.max_climb_deg, craft.max_descent_deg)))
            * np.linalg.norm(np.diff(F[:, :2], axis=0), axis=1).sum()
        )
        if abs(P[-1, 2] - P[0, 2]) < climbable / 2:
            assert F[-1, 2] == pytest.approx(P[-1, 2], abs=1e-6)
        radius = verdict["min_turn_radius_m"]
        turns = radius is not None and radius < 1.01 * craft.min_turn_radius_m  # turns at its limit
        limit = max(
            verdict["max_climb_deg"] / craft.max_climb_deg, verdict["max_descent_deg"] / craft.max_descent_deg
        )
        if turns:
            assert not envelope(F, tighter)["turn_ok"]
        check = envelope(F, steeper)
        if limit > 0.99:
            assert not (check["climb_ok"] and check["descent_ok"])
        turning, at_limit = turning + turns, at_limit + (limit > 0.99)
    assert turning > 150 and at_limit > 150


def test_a_right_angle_becomes_an_arc_of_the_least_radius_and_a_corner_too_tight_is_dropped():
    craft = Vehicle(50.0, 500.0, 5.0, 5.0, 0.0, 5000.0)
    P = np.array([[0.0, 0.0, 1000.0], [3000.0, 0.0, 1000.0], [3000.0, 3000.0, 1000.0]])
    F = flyable(P, craft)
    assert np.min(turn_radii(F)) == pytest.approx(500.0, rel=0.005)
    # the arc's middle is R (sqrt 2 - 1) inside the corner
    assert np.min(np.linalg.norm(F[:, :2] - [3000.0, 0.0], axis=1)) == pytest.approx(
        500.0 * (np.sqrt(2) - 1), rel=1e-3
    )
    zigzag = np.array(
        [[0.0, 0.0, 1000.0], [400.0, 0.0, 1000.0], [400.0, 300.0, 1000.0], [3000.0, 300.0, 1000.0]]
    )
    F = flyable(zigzag, craft)  # 300 m between two right angles: no room for two fillets of 500 m
    assert envelope(F, craft)["flyable"]
    assert np.min(turn_radii(F)) >= 500.0 * 0.995  # the first corner dropped: one wide turn
    length = np.linalg.norm(np.diff(F[:, :2], axis=0), axis=1).sum()
    assert length < np.linalg.norm(np.diff(zigzag[:, :2], axis=0), axis=1).sum()
