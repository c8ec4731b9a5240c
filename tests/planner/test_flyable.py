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


def test_a_corner_whose_arc_leaves_the_tube_is_pushed_out_until_the_flown_path_keeps_in_it():
    """An L-shaped tube 40 m wide and a planned path in it that turns at its inner corner:
    the drone's fillet (30 m) cuts the corner, out of the tube. Given the tube, the corner is
    pushed out and the flown path keeps in it everywhere, within the envelope, from the same
    start to the same goal; a path that keeps in the tube anyway is unchanged by it."""
    from planner.costmap import CostMap, CostWeights

    axes = (np.arange(0.0, 305.0, 5.0), np.arange(0.0, 305.0, 5.0), np.arange(0.0, 61.0, 20.0))
    x, y = np.meshgrid(axes[0], axes[1], indexing="ij")
    tube = ((x <= 40) & (y <= 200)) | ((y >= 160) & (y <= 200))
    std = np.where(tube, 0.1, 1.0)[:, :, None, None] * np.ones((1, 1, len(axes[2]), 3))
    costmap = CostMap(axes, np.zeros_like(std), std, CostWeights(max_std_mps=0.3))
    drone = Vehicle(5.0, 30.0, 20.0, 20.0, 1.0, 59.0)
    P = np.array([[20.0, 10.0, 30.0], [37.0, 163.0, 30.0], [290.0, 180.0, 30.0]])
    assert costmap.segments_in_tube(P[:-1], P[1:]).all()
    plain = flyable(P, drone)
    assert not costmap.segments_in_tube(plain[:-1], plain[1:]).all()
    kept = flyable(P, drone, in_tube=costmap.segments_in_tube)
    assert costmap.segments_in_tube(kept[:-1], kept[1:]).all()
    assert envelope(kept, drone)["flyable"]
    np.testing.assert_allclose(kept[[0, -1]], P[[0, -1]], atol=1e-9)
    # the arc passes within its inset of the planned corner, outside the plain one's
    inset = 30.0 * (1 / np.cos(abs(np.arctan2(17, 153) - np.arctan2(253, 17)) / 2) - 1)
    assert np.min(np.linalg.norm(kept[:, :2] - P[1, :2], axis=1)) < 0.6 * inset
    assert np.min(np.linalg.norm(plain[:, :2] - P[1, :2], axis=1)) == pytest.approx(inset, rel=0.01)
    wide = np.array([[20.0, 10.0, 30.0], [20.0, 180.0, 30.0], [290.0, 180.0, 30.0]])
    unchanged = flyable(wide, drone, in_tube=costmap.segments_in_tube)
    np.testing.assert_array_equal(unchanged, flyable(wide, drone))


def test_corners_too_close_for_their_fillets_merge_outside_a_bend_or_the_nearer_one_goes():
    """Two left turns of 45 degrees 141 m apart (fillets of 500 m need 207 m each) become one
    right angle where their outer segments meet: its arc's middle lies R (sqrt 2 - 1) inside
    that corner. Of two turns the opposite way (one of 3 degrees beside one of 32), the slight
    one goes: the path still turns at the sharp one, where the planner looked."""
    craft = Vehicle(50.0, 500.0, 5.0, 5.0, 0.0, 5000.0)
    bend = np.array(
        [[0.0, 0.0, 1000.0], [1000.0, 0.0, 1000.0], [1100.0, 100.0, 1000.0], [1100.0, 1100.0, 1000.0]]
    )
    F = flyable(bend, craft)
    assert envelope(F, craft)["flyable"]
    inset = np.min(np.linalg.norm(F[:, :2] - [1100.0, 0.0], axis=1))
    assert inset == pytest.approx(500.0 * (np.sqrt(2) - 1), rel=1e-3)
    drone = Vehicle(5.0, 30.0, 20.0, 20.0, 1.0, 59.0)
    s_bend = np.array(
        [[192.8, 153.3, 12.0], [233.5, 142.6, 16.0], [238.6, 137.2, 18.0], [259.0, 117.6, 25.0]]
    )
    F = flyable(s_bend, drone)
    assert envelope(F, drone)["flyable"]
    sharp = 30.0 * (1 / np.cos(np.radians(32.0) / 2) - 1)  # the sharp corner's inset, 1.2 m (the join: 3.4 m)
    assert np.min(np.linalg.norm(F[:, :2] - s_bend[1, :2], axis=1)) < 2 * sharp
