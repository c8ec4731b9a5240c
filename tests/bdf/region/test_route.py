import dataclasses
import itertools

import numpy as np
import pytest

from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.route import (
    MAX_ROUTE_POINTS,
    VEHICLES,
    Vehicle,
    assess,
    envelope,
    resample,
    samples,
    turn_radii,
    vehicle,
)
from bdf.region.spec import RegionSpec
from bdf.sectors import CROSSING_DEG
from tests.bdf.region.conftest import SMALL

CRAFT = Vehicle(
    cruise_mps=50.0,
    min_turn_radius_m=500.0,
    max_climb_deg=6.0,
    max_descent_deg=4.0,
    floor_m=100.0,
    ceiling_m=2000.0,
)


def arc_route(radius: float, climb_deg: float, step_m: float = 5.0) -> np.ndarray:
    """1 km east, a quarter turn to the north of ``radius`` (points every ``step_m`` on the
    circle), 1 km north; climbing at ``climb_deg`` all the way from 500 m."""
    straight = np.arange(0.0, 1000.0, step_m)
    first = np.stack([straight, np.zeros_like(straight)], axis=1)
    theta = np.arange(0.0, np.pi / 2, step_m / radius)
    turn = np.stack([1000.0 + radius * np.sin(theta), radius * (1 - np.cos(theta))], axis=1)
    last = np.stack([np.full(201, 1000.0 + radius), radius + np.linspace(0.0, 1000.0, 201)], axis=1)
    xy = np.vstack([first, turn, last])
    h = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return np.column_stack([xy, 500.0 + np.tan(np.radians(climb_deg)) * h])


def test_the_turn_radius_of_an_arc_is_its_radius_and_a_corner_has_none():
    P = arc_route(600.0, 0.0)
    radii = turn_radii(P)
    assert np.min(radii) == pytest.approx(600.0, rel=0.01)
    assert np.isinf(radii[:50]).all()  # the first straight
    corner = np.array([[0.0, 0.0, 500.0], [2000.0, 0.0, 500.0], [2000.0, 2000.0, 500.0]])
    assert turn_radii(corner).min() < 60.0  # a right angle: the window's order, not km


def test_a_route_within_the_envelope_passes_and_a_tighter_envelope_fails_it():
    """Sampled every 10 m: the arc's 600 m against 500 m, the 5-degree climb against 6;
    each limit made tighter than what the route flies (or the floor raised)
    fails that check alone."""
    P = arc_route(600.0, 5.0)
    got = envelope(P, CRAFT)
    assert got["flyable"] and got["min_turn_radius_m"] == pytest.approx(600.0, rel=0.01)
    assert got["max_climb_deg"] == pytest.approx(5.0, abs=1e-3) and got["max_descent_deg"] == 0.0
    assert (got["min_alt_m"], got["max_alt_m"]) == pytest.approx((500.0, P[-1, 2]))
    for change, check in (
        ({"min_turn_radius_m": 660.0}, "turn_ok"),
        ({"max_climb_deg": 4.5}, "climb_ok"),
        ({"floor_m": 600.0}, "altitude_ok"),
        ({"ceiling_m": 600.0}, "altitude_ok"),
    ):
        verdict = envelope(P, dataclasses.replace(CRAFT, **change))
        assert not verdict["flyable"] and not verdict[check], change
        assert sum(not verdict[k] for k in ("turn_ok", "climb_ok", "descent_ok", "altitude_ok")) == 1
    down = P[::-1]  # flown backwards: a 5-degree descent against 4
    assert envelope(down, CRAFT)["max_descent_deg"] == pytest.approx(5.0, abs=1e-3)
    assert not envelope(down, CRAFT)["descent_ok"]


def test_vehicles_and_bad_routes_are_clear_value_errors():
    assert vehicle("evtol") is VEHICLES["evtol"] and vehicle(CRAFT) is CRAFT
    assert vehicle(dataclasses.asdict(CRAFT)) == CRAFT
    with pytest.raises(ValueError, match="unknown vehicle 'blimp'"):
        vehicle("blimp")
    with pytest.raises(ValueError, match="min_turn_radius_m must be positive"):
        Vehicle(50.0, 0.0, 5.0, 5.0, 0.0, 100.0)
    with pytest.raises(ValueError, match=r"floor_m 100\.0 must be below ceiling_m 50\.0"):
        Vehicle(50.0, 10.0, 5.0, 5.0, 100.0, 50.0)
    for P, message in (
        ([[0.0, 0.0, 0.0]], "needs 2 to"),
        ([[0.0, 0.0, 0.0], [1.0, np.nan, 0.0]], "NaN or infinite"),
        ([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], "two consecutive points"),
        (np.zeros((MAX_ROUTE_POINTS + 1, 3)), "needs 2 to"),
    ):
        with pytest.raises(ValueError, match=message):
            envelope(P, CRAFT)


@pytest.fixture(params=[1, 4], ids=["one class", "4 sectors"])
def region_map(request, small) -> RegionMap:
    spec = RegionSpec.model_validate({**SMALL, "directions": request.param, "slow_mps": 2.0})
    _, X, V = small
    evidence = region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
    return RegionMap(spec, compute_posterior(spec, evidence))


def test_assess_equals_a_direct_integration_of_the_maps_predictions(region_map):
    """Each metric, per segment and in total, against the map's predictions read point by
    point at the midpoints of 10 m pieces (the mode of each segment's heading), and the
    totals against the segments'."""
    P = np.array([[10.0, 10.0, 10.0], [140.0, 30.0, 20.0], [150.0, 180.0, 40.0], [290.0, 190.0, 50.0]])
    got = assess(region_map, P, max_std_mps=1.0, craft=CRAFT)
    spec, seg = region_map.spec, got["segments"]
    for i, (a, b) in enumerate(itertools.pairwise(P)):
        n = int(np.ceil(np.linalg.norm(b - a) / 10.0))
        X = a + ((np.arange(n) + 0.5) / n)[:, None] * (b - a)
        heading = np.degrees(np.arctan2(*(b - a)[:2]))
        mean, std, _ = region_map.predict(X, heading_deg=np.full(n, heading))
        s = std.max(axis=1)
        v = (b - a) / np.linalg.norm(b - a) * CRAFT.cruise_mps
        assert seg["max_std_mps"][i] == pytest.approx(s.max(), rel=1e-12)
        assert seg["mean_std_mps"][i] == pytest.approx(s.mean(), rel=1e-12)
        assert seg["in_tube_fraction"][i] == pytest.approx(np.mean(s <= 1.0), rel=1e-12)
        assert seg["integrated_risk_m"][i] == pytest.approx(s.sum() * np.linalg.norm(b - a) / n, rel=1e-12)
        assert seg["flow_mismatch_mps"][i] == pytest.approx(
            np.linalg.norm(v - mean, axis=1).mean(), rel=1e-12
        )
        turn = np.degrees(np.arctan2(mean[:, 0], mean[:, 1])) - heading
        offset = np.abs((turn + 180.0) % 360.0 - 180.0)
        assert seg["flow_heading_offset_deg"][i] == pytest.approx(offset.mean(), rel=1e-12)
        assert seg["traffic_speed_mps"][i] == pytest.approx(np.hypot(*mean[:, :2].T).mean(), rel=1e-12)
        if spec.directions > 1:
            modes = region_map.predict_modes(X)
            off = np.abs((spec.sectors.centres_deg - heading + 180.0) % 360.0 - 180.0)
            expected = (modes.share[:, : spec.directions] * (off >= CROSSING_DEG)).sum(axis=1).mean()
            assert seg["conflict_exposure"][i] == pytest.approx(expected, rel=1e-12)
            assert 0 < expected < 1
        else:
            assert seg["conflict_exposure"][i] == 0.0
    lengths = np.array(seg["length_m"])
    total = got["total"]
    assert total["length_m"] == pytest.approx(lengths.sum(), rel=1e-14)
    assert total["duration_s"] == pytest.approx(lengths.sum() / CRAFT.cruise_mps, rel=1e-14)
    for key in (
        "mean_std_mps",
        "in_tube_fraction",
        "conflict_exposure",
        "flow_mismatch_mps",
        "flow_heading_offset_deg",
        "traffic_speed_mps",
    ):
        assert total[key] == pytest.approx(np.dot(seg[key], lengths) / lengths.sum(), rel=1e-12), key
    assert total["integrated_risk_m"] == pytest.approx(sum(seg["integrated_risk_m"]), rel=1e-12)
    assert total["max_std_mps"] == max(seg["max_std_mps"])
    assert got["envelope"] == envelope(P, CRAFT)
    assert not got["envelope"]["flyable"]  # corners of a few metres


def test_times_and_headings_change_the_velocity_and_the_mode_flown(region_map):
    P = np.array([[10.0, 100.0, 30.0], [290.0, 100.0, 30.0]])
    east = assess(region_map, P, max_std_mps=1.0, craft=CRAFT)
    slow = assess(region_map, P, max_std_mps=1.0, craft=CRAFT, times_s=[0.0, 280.0])  # 1 m/s
    assert slow["total"]["duration_s"] == 280.0
    assert slow["total"]["flow_mismatch_mps"] != east["total"]["flow_mismatch_mps"]
    north = assess(region_map, P, max_std_mps=1.0, craft=CRAFT, heading_deg=[0.0])
    if region_map.spec.directions > 1:
        assert north["total"]["max_std_mps"] != east["total"]["max_std_mps"]
        # at 1 m/s, below slow_mps: the slow class is the mode flown, and no sector conflicts
        assert slow["total"]["max_std_mps"] != east["total"]["max_std_mps"]
    else:
        assert north["total"]["max_std_mps"] == east["total"]["max_std_mps"]
    for kwargs, message in (
        ({"times_s": [0.0, 0.0]}, "times_s must be 2 finite, increasing"),
        ({"times_s": [0.0]}, "times_s must be 2"),
        ({"heading_deg": [0.0, 1.0]}, "heading_deg must be 1 finite"),
        ({"max_std_mps": 0.0}, "max_std_mps must be at least 0.001"),
        ({"max_std_mps": 1e-310}, "max_std_mps must be at least 0.001"),
        ({"times_s": [0.0, 1e-310]}, "segment 0 is flown at inf m/s, faster than 1000"),
        ({"times_s": [-1.7e308, 1.7e308]}, "times_s must be 2 finite, increasing"),
    ):
        with pytest.raises(ValueError, match=message):
            assess(region_map, P, **{"max_std_mps": 1.0, "craft": CRAFT, **kwargs})
    with pytest.raises(ValueError, match=r"route points \[1\] are outside region 'small'"):
        assess(region_map, [[10.0, 10.0, 10.0], [400.0, 10.0, 10.0]], max_std_mps=1.0, craft=CRAFT)
    assert len(resample(P, 10.0)) == 29


def test_a_route_read_in_chunks_equals_one_read_and_checks_between_them(region_map, monkeypatch):
    """Memory bounded by a chunk: 7-sample chunks give what one chunk gives (the sums in
    another order: 1e-12), with a checkpoint before each chunk of the map and the envelope."""
    import bdf.region.route as route

    P = np.array([[10.0, 10.0, 10.0], [140.0, 30.0, 20.0], [150.0, 180.0, 40.0], [290.0, 190.0, 50.0]])
    whole = assess(region_map, P, max_std_mps=1.0, craft=CRAFT)
    calls = []
    monkeypatch.setattr(route, "CHUNK_SAMPLES", 7)
    chunked = assess(region_map, P, max_std_mps=1.0, craft=CRAFT, checkpoint=lambda: calls.append(1))
    on_map, on_envelope = route.samples(P, CRAFT)
    assert len(calls) == -(-on_map // 7) + -(-on_envelope // 7)
    assert chunked["envelope"] == whole["envelope"]
    for part in ("segments", "total"):
        for key, value in whole[part].items():
            assert np.allclose(chunked[part][key], value, rtol=1e-12, atol=0), key


def test_the_envelope_of_a_vehicle_turning_on_a_coin_is_sampled_every_metre():
    """A turn radius of 1 cm would sample a 20 km route every 0.8 mm (24 M samples): the
    envelope never samples finer than a metre, and judges the corner flyable."""
    P = np.array([[0.0, 0.0, 500.0], [10_000.0, 0.0, 500.0], [10_000.0, 10_000.0, 500.0]])
    coin = dataclasses.replace(CRAFT, min_turn_radius_m=0.01)
    assert samples(P, coin) == (2000, 20_001)
    got = envelope(P, coin)
    assert got["turn_ok"] and got["min_turn_radius_m"] == pytest.approx(3 / np.sqrt(2), rel=0.01)
    # the right angle read over 3 m chords: the circle through (-3, 0), (0, 0), (0, 3)
    assert samples(P, CRAFT) == (2000, 2001)  # 500 m: 50 m chords, every 10 m
