"""Tracks as users send them: the service weighs a track's correlated rows itself
(:func:`bdf.ingest.track_weights`), on every write path, keeping the store's guarantees."""

import io

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bdf import ingest
from bdf.region.evidence import UNTRACKED_WARNING, accepted_increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.spec import RegionSpec

# 1 km x 400 m x 200 m, hinges every 50 m (kernel width 50 m horizontally, 40 m vertically)
LINE = {
    "name": "line",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [1000, 400, 200]},
    "tile_size_m": [250, 400, 200],
    "spacing_m": [50, 50, 40],
    "gamma": [1 / 2500, 1 / 2500, 1 / 1600],
}


def flight(hz: float, y: float = 200.0, speed: float = 20.0, t0: float = 0.0):
    """A straight, level flight east at ``speed`` m/s along ``y`` for 960 m, sampled at
    ``hz``: positions, velocities (a gentle flow along the track) and times."""
    t = t0 + np.arange(round(960 / speed * hz) + 1) / hz
    X = np.stack([10 + speed * (t - t0), np.full_like(t, y), np.full_like(t, 100.0)], axis=1)
    V = np.stack([speed + 2 * np.sin(X[:, 0] / 120), 0.5 * np.cos(X[:, 0] / 90), 0 * t], axis=1)
    return X, V, t


def region_map(spec, X, V, track=None, time=None, weight=None) -> RegionMap:
    increments, _ = accepted_increments(spec, X, V, sample_weight=weight, track=track, time=time)
    evidence = region_total(spec, {k: i.evidence for k, i in increments.items()})
    return RegionMap(spec, compute_posterior(spec, evidence))


def assert_same_map(a: RegionMap, b: RegionMap, rtol: float, ends_m: float = 0.0) -> None:
    """Mean within ``rtol`` of the largest, std within ``rtol``, over the flight's box but
    ``ends_m`` from its ends."""
    x = np.linspace(10 + ends_m, 970 - ends_m, 25)
    Xq = np.stack(np.meshgrid(x, [150, 200, 250], [80, 100, 120]), -1).reshape(-1, 3)
    (ma, sa, _), (mb, sb, _) = a.predict(Xq), b.predict(Xq)
    scale = np.abs(ma).max(axis=0)
    assert np.all(np.abs(ma - mb) <= rtol * scale), f"mean: {np.abs(ma - mb).max(axis=0)} vs {rtol * scale}"
    np.testing.assert_allclose(sa, sb, rtol=rtol, err_msg="std")


def test_a_track_sampled_1_4_or_16_times_a_second_gives_the_same_map():
    # fixed hyperparameters: the evidence of noise-free data is flat, and its optimum moves
    # by a percent with anything; the statistics are what the rule makes equal (on one
    # field: a mode's prior mean, its class's mean near each hinge, moves with the ends' weights)
    spec = RegionSpec.model_validate({**LINE, "alpha": 1.0, "beta": 4.0, "model_directions": 1})
    maps = []
    for hz in (1, 4, 16):
        X, V, t = flight(hz)
        maps.append(region_map(spec, X, V, np.zeros(len(t), np.int64), t))
        # a row stands for speed / hz metres of its track: 20 m / 50 m at 1 Hz
        w = ingest.track_weights(np.zeros(len(t), int), t, V, spec.gamma)
        assert np.median(w) == pytest.approx(np.median(np.linalg.norm(V, axis=1)) / hz / 50, rel=1e-2)
    # a track's end samples stand for their whole interval, not half (a cut end cannot be
    # told from a true one): the maps differ near the ends, by half a sample of track
    assert_same_map(maps[0], maps[1], 1e-3, ends_m=200)
    assert_same_map(maps[0], maps[2], 1e-3, ends_m=200)
    # the raw rows, counted as independent, are a different (overconfident) map
    X, V, t = flight(16)
    raw = region_map(spec, X, V)
    assert np.median(raw.predict(X[::50])[1] / maps[2].predict(X[::50])[1]) < 0.9


def test_two_flights_weigh_twice_one_and_16_times_the_samples_weigh_the_same():
    gamma = LINE["gamma"]
    _, V, t = flight(1)
    one = ingest.track_weights(np.zeros(len(t), int), t, V, gamma).sum()
    two = ingest.track_weights(
        np.r_[np.zeros(len(t), int), np.ones(len(t), int)], np.r_[t, t], np.r_[V, V], gamma
    )
    assert two.sum() == pytest.approx(2 * one, rel=1e-12)
    _, V16, t16 = flight(16)
    dense = ingest.track_weights(np.zeros(len(t16), int), t16, V16, gamma).sum()
    assert dense == pytest.approx(one, rel=2e-2)  # the same flight, up to its ends' sampling
    # one track id for both flights at the same times: they share each time's weight
    same = ingest.track_weights(np.zeros(2 * len(t), int), np.r_[t, t], np.r_[V, V], gamma)
    assert same.sum() == pytest.approx(one, rel=1e-12)


def test_the_rule_is_local_to_a_track_and_its_neighbours():
    gamma = np.array(LINE["gamma"])
    t = np.array([0.0, 0.25, 0.5, 1.5, 10.0, 100.0])
    V = np.tile([20.0, 0.0, 0.0], (6, 1))
    w = ingest.track_weights(np.zeros(6, int), t, V, gamma)
    # nearer neighbour 0.25 s away: 5 m of 50; 1 s or more (or alone): 1 s, 20 m of 50
    np.testing.assert_allclose(w, [0.1, 0.1, 0.1, 0.4, 0.4, 0.4])
    np.testing.assert_allclose(ingest.track_weights([3], [5.0], V[:1], gamma), [0.4])
    # a region of tracks sampled every 10 s says so: then those rows are one observation each
    sparse = ingest.track_weights(np.zeros(6, int), t, V, gamma, max_interval_s=10.0)
    np.testing.assert_allclose(sparse, [0.1, 0.1, 0.1, 0.4, 1.0, 1.0])
    # rows in any order; a hover counts at the slow speed (5 m/s), not as nothing
    order = np.random.default_rng(0).permutation(6)
    w = ingest.track_weights(np.zeros(6, int), t, V, gamma)
    np.testing.assert_allclose(ingest.track_weights(np.zeros(6, int), t[order], V[order], gamma), w[order])
    hover = ingest.track_weights(np.zeros(3, int), [0.0, 1.0, 2.0], np.zeros((3, 3)), gamma)
    np.testing.assert_allclose(hover, 5.0 / 50)
    # a track cut anywhere (sampled regularly, or at 1 s and slower with gaps): each part
    # weighs as it did in the whole
    _, V, t = flight(1)
    t = t + np.cumsum(np.where(np.arange(len(t)) % 7 == 3, 5.0, 0.0))  # gaps of 6 s
    whole = ingest.track_weights(np.zeros(len(t), int), t, V, gamma)
    for cut in range(1, len(t)):
        parts = [slice(0, cut), slice(cut, None)]
        np.testing.assert_array_equal(
            np.concatenate(
                [ingest.track_weights(np.zeros(len(t[p]), int), t[p], V[p], gamma) for p in parts]
            ),
            whole,
        )
    with pytest.raises(ValueError, match="finite time"):
        ingest.track_weights([0, 0], [0.0, np.nan], V[:2], gamma)


def test_track_codes_take_strings_integers_and_none():
    np.testing.assert_array_equal(ingest.track_codes(["b", "a", "b", None, ""]), [1, 0, 1, -1, -1])
    np.testing.assert_array_equal(ingest.track_codes(np.array([7, 3, 7])), [1, 0, 1])
    np.testing.assert_array_equal(ingest.track_codes(np.array([7.0, np.nan, 7.0])), [0, -1, 0])


def test_untracked_rows_are_counted_and_sample_weight_multiplies_the_track_weight():
    spec = RegionSpec.model_validate(LINE)
    X, V, t = flight(1)
    track = np.zeros(len(t), np.int64)
    track[:5] = -1  # five rows without a track
    _, summary = accepted_increments(spec, X, V, track=track, time=t)
    assert summary["untracked"] == 5 and summary["warnings"] == [UNTRACKED_WARNING]
    _, summary = accepted_increments(spec, X, V, track=np.zeros(len(t), np.int64), time=t)
    assert summary["untracked"] == 0 and "warnings" not in summary
    # a row of a track without its time is not finite
    t_bad = t.copy()
    t_bad[3] = np.nan
    _, summary = accepted_increments(spec, X, V, track=np.zeros(len(t), np.int64), time=t_bad)
    assert summary["rejected"]["non_finite"] == 1
    halves = region_map(spec, X, V, np.zeros(len(t), np.int64), t, np.full(len(t), 0.5))
    weights = 0.5 * ingest.track_weights(np.zeros(len(t), int), t, V, spec.gamma)
    assert_same_map(halves, region_map(spec, X, V, weight=weights), 1e-12)


def tracks(seed: int, flights: int = 12):
    """Raw 1 Hz tracks across the region ``town`` (300 x 200 x 60 m): straight lines at
    4-12 m/s in random directions, a flow of their own plus noise; rows, track ids, times."""
    rng = np.random.default_rng(seed)
    X, V, track, t = [], [], [], []
    for f in range(flights):
        start = rng.uniform([20, 20, 10], [280, 180, 50])
        heading = rng.uniform(0, 2 * np.pi)
        speed = rng.uniform(4, 12)
        v = speed * np.array([np.sin(heading), np.cos(heading), 0.0])
        times = rng.uniform(0, 100) + np.arange(40.0)
        pos = start + (times - times[0])[:, None] * v
        inside = np.all((pos > 1) & (pos < [299, 199, 59]), axis=1)
        X.append(pos[inside])
        V.append(v + 0.3 * rng.standard_normal((inside.sum(), 3)))
        track.append(np.full(inside.sum(), f))
        t.append(times[inside])
    return np.concatenate(X), np.concatenate(V), np.concatenate(track), np.concatenate(t)


def test_tracks_cut_across_uploads_in_any_order_give_the_map_of_one_upload(store, spec):
    """1, 10 and 100 uploads of the same rows cut by time (flights cut across them), applied
    in shuffled orders: the same stored statistics (1e-9) and map (1e-6) as one upload, and
    retracting one upload leaves the region built without it."""
    from service.maps import RegionMaps
    from tests.service.test_store import assert_evidence_equal

    X, V, track, t = tracks(0)
    maps = RegionMaps(store)
    order = np.argsort(t, kind="stable")
    Q = np.random.default_rng(1).uniform([0, 0, 0], [300, 200, 60], (200, 3))
    answers = {}
    for uploads in (1, 10, 100):
        name = f"u{uploads}"
        store.create_region(spec.model_copy(update={"name": name}))
        chunks = np.array_split(order, uploads)
        for k in np.random.default_rng(uploads).permutation(uploads):
            rows = chunks[k]
            result = maps.upload(name, f"c{k}", X[rows], V[rows], track=track[rows], time=t[rows])
            assert result["untracked"] == 0 and "warnings" not in result
        assert store.region(name).observations == len(X)
        maps.fit_hyperparameters(name)  # the settled map: "auto" at the evidence maximum itself
        answers[uploads] = maps.predict(name, Q, min_version=uploads)
        if uploads > 1:
            assert_evidence_equal(store.snapshot(name).evidence, store.snapshot("u1").evidence, rtol=1e-9)
    for uploads in (10, 100):
        got, want = answers[uploads], answers[1]
        np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-6 * np.abs(want.mean).max())
        np.testing.assert_allclose(got.std, want.std, rtol=1e-6)
    # the rows weighed as a track weigh far less than as independent rows
    one = store.snapshot("u1").evidence
    assert sum(ev.classes[0].count for ev in one.values()) < 0.5 * len(X)
    # retract upload 3 of 10: the region built from the other 9
    chunks = np.array_split(order, 10)
    rows = chunks[3]
    maps.retract("u10", "c3", X[rows], V[rows], track=track[rows], time=t[rows])
    store.create_region(spec.model_copy(update={"name": "without"}))
    for k in (0, 1, 2, 4, 5, 6, 7, 8, 9):
        rows = chunks[k]
        maps.upload("without", f"c{k}", X[rows], V[rows], track=track[rows], time=t[rows])
    assert_evidence_equal(store.snapshot("u10").evidence, store.snapshot("without").evidence, rtol=1e-9)


@pytest.mark.slow  # a live server
def test_tracks_over_http_in_every_format_and_rows_without_them_warned_of(live_server):
    import httpx

    from service.formats import arrow_bytes
    from tests.service.test_api import enu_columns, library, settle
    from tests.service.test_store import SPEC

    server = live_server()
    spec = RegionSpec.model_validate(SPEC)
    X, V, track, t = tracks(4)
    order = np.argsort(t, kind="stable")  # by time: flights cut across the three uploads
    X, V, track, t = X[order], V[order], track[order], t[order]
    names = np.array([f"N{k:03d}" for k in track])
    a, b = len(X) // 3, 2 * len(X) // 3
    with httpx.Client(base_url=server.url, timeout=60) as client:
        assert client.post("/v1/regions", json=SPEC).status_code == 201
        assert client.post("/v1/regions", json={**SPEC, "name": "raw"}).status_code == 201
        body = {
            "points": X[:a].tolist(),
            "velocities": V[:a].tolist(),
            "track": names[:a].tolist(),
            "t": t[:a].tolist(),
        }
        answers = [client.post("/v1/regions/town/observations", json=body, headers={"Idempotency-Key": "j"})]
        columns = {**enu_columns(X[a:b], V[a:b]), "track": track[a:b], "t": t[a:b]}  # integer ids
        answers.append(
            client.post(
                "/v1/regions/town/observations",
                content=arrow_bytes(columns),
                headers={"Idempotency-Key": "a", "Content-Type": "application/vnd.apache.arrow.stream"},
            )
        )
        buf = io.BytesIO()
        pq.write_table(pa.table({**enu_columns(X[b:], V[b:]), "track": names[b:], "t": t[b:]}), buf)
        answers.append(
            client.post(
                "/v1/regions/town/observations",
                content=buf.getvalue(),
                headers={"Idempotency-Key": "p", "Content-Type": "application/vnd.apache.parquet"},
            )
        )
        for r in answers:
            assert r.status_code == 200, r.text
            assert (r.json()["untracked"], r.json()["warnings"]) == (0, [])
        settle(client, "town")
        Q = np.random.default_rng(5).uniform([0, 0, 0], [300, 200, 60], (150, 3))
        got = client.post("/v1/regions/town/query", json={"points": Q.tolist()}).json()
        # one field fitted on all rows, each weighed by its whole track: the same map
        weight = ingest.track_weights(track, t, V, spec.gamma)
        mean, std, _ = library(spec, X, V, Q, sample_weight=weight)
        np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6 * np.abs(mean).max())
        np.testing.assert_allclose(got["std"], std, rtol=1e-6)
        # the same rows without their tracks: accepted, counted, warned of
        r = client.post(
            "/v1/regions/raw/observations",
            json={"points": X.tolist(), "velocities": V.tolist()},
            headers={"Idempotency-Key": "r"},
        )
        assert (r.json()["accepted"], r.json()["untracked"]) == (len(X), len(X))
        assert r.json()["warnings"] == [UNTRACKED_WARNING]
        settle(client, "raw")
        for name in ("town", "raw"):
            view = client.get(f"/v1/regions/{name}").json()
            assert view["plausibility"]["worst_ratio"] > 0 and view["hyperparameters"]["at_bound"] in (
                True,
                False,
            )
        # refused as a whole, nothing stored: a track without its times, a track of floats
        bad = {**body, "t": None}
        r = client.post("/v1/regions/town/observations", json=bad, headers={"Idempotency-Key": "b1"})
        assert r.status_code == 422 and "track and t go together" in r.json()["detail"]
        floats = arrow_bytes({**enu_columns(X[:5], V[:5]), "track": np.ones(5), "t": t[:5]})
        r = client.post(
            "/v1/regions/town/observations",
            content=floats,
            headers={"Idempotency-Key": "b2", "Content-Type": "application/vnd.apache.arrow.stream"},
        )
        assert r.status_code == 422 and "'track'" in r.json()["detail"]
        assert client.get("/v1/regions/town").json()["version"] == 3


def test_the_speed_bound_is_the_fastest_traffic_near_each_altitude():
    """The tiles' speed histograms, summed over the region: 1.1 x the 99.9th percentile of
    the horizontal speeds of the rows within 1 km (by their 100 m altitude bin's centre; the
    upper edge of its 2 m/s speed bin); the envelope's speed where no row is near."""
    from bdf.region.evidence import increments
    from bdf.region.map import speed_bound

    spec = RegionSpec.model_validate(
        {**LINE, "bounds_m": {"min": [0, 0, 0], "max": [1000, 400, 5000]}, "tile_size_m": [250, 200, 1000]}
    )
    rng = np.random.default_rng(2)
    X = rng.uniform([0, 0, 0], [1000, 400, 2000], (3000, 3))  # nothing above 2 km
    V = np.stack([rng.uniform(0, 50 + 0.05 * X[:, 2]), rng.normal(0, 5, 3000), np.zeros(3000)], 1)
    total = region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
    bound = speed_bound(spec, total.speeds)
    layer_z = (np.floor(X[:, 2] / 100.0) + 0.5) * 100.0
    speed = np.hypot(V[:, 0], V[:, 1])
    alts = np.arange(-500.0, 5500.0, 125.0)
    want = np.full(len(alts), spec.envelope.max_horizontal_speed_mps)
    for k, at in enumerate(alts):
        near = np.abs(layer_z - at) <= 1000
        if near.any():
            q = np.sort(speed[near])[int(np.ceil(0.999 * near.sum())) - 1]
            want[k] = 1.1 * (np.floor(q / 2.0) + 1) * 2.0
    np.testing.assert_allclose(bound(alts), want)
    assert want[-1] == spec.envelope.max_horizontal_speed_mps and want[0] < 200
