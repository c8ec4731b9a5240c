"""The same suite on SQLite and PostgreSQL: exactly-once uploads, concurrency, crash safety."""

import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import threading

import anyio
import numpy as np
import psutil
import pytest

from bdf.region.evidence import REJECTED, UNTRACKED_WARNING, encode_tile, increments
from bdf.region.map import region_field
from bdf.region.spec import RegionSpec
from service.lanes import Lane
from service.maps import RegionMaps
from service.refresh import PosteriorCache
from service.store import (
    RegionExists,
    RegionNotFound,
    UploadConflict,
    UploadNotFound,
    open_store,
    payload_digest,
)

SPEC = {
    "name": "town",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [300, 200, 60]},
    "tile_size_m": [100, 100, 60],
    "spacing_m": [25, 25, 20],
    "gamma": [1 / 1250, 1 / 1250, 1 / 800],
    "directions": 1,  # one velocity per point (the moments of 8 sectors); new regions: "auto"
}


NO_REJECTS = dict.fromkeys(REJECTED, 0)


def data(seed, n=200, band=False):
    """Synthetic observations; ``band``: points on both sides of the border of tile
    columns 0 and 1, in four rows of tiles' cores."""
    rng = np.random.default_rng(seed)
    if band:
        X = np.stack(
            [rng.uniform(81, 119, n), rng.choice([10.0, 50.0, 150.0, 190.0], n), rng.uniform(0, 60, n)],
            axis=1,
        )
    else:
        X = rng.uniform([0, 0, 0], [300, 200, 60], (n, 3))
    V = np.stack([np.sin(X[:, 0] / 40), np.cos(X[:, 1] / 30), 0.01 * X[:, 2]], axis=1)
    return X, V + 0.1 * rng.standard_normal(X.shape)


def assert_evidence_equal(got, expected, rtol=1e-9):
    assert set(got) == set(expected)
    for key in expected:
        assert len(got[key].classes) == len(expected[key].classes)
        for a, b in zip(got[key].classes, expected[key].classes, strict=True):
            scale = max(np.abs(b.density).max(), 1e-300)
            np.testing.assert_allclose(a.density, b.density, rtol=rtol, atol=rtol * scale)
            np.testing.assert_allclose(a.proj, b.proj, rtol=rtol, atol=rtol * np.abs(b.proj).max())
            np.testing.assert_allclose(a.mass, b.mass, rtol=rtol, atol=rtol * np.abs(b.mass).max())
            np.testing.assert_allclose([a.count, *a.v_sum, *a.v_sq], [b.count, *b.v_sum, *b.v_sq], rtol=rtol)


def test_regions_are_created_listed_and_deleted_with_their_tiles(store, spec):
    with pytest.raises(RegionExists):
        store.create_region(spec)
    info = store.region("town")
    assert (info.spec, info.version, info.tiles, info.observations) == (spec, 0, 0, 0)
    X, V = data(0)
    RegionMaps(store).upload("town", "u1", X, V)
    assert store.region("town").tiles == 6
    store.create_region(spec.model_copy(update={"name": "village"}))
    assert [r.spec.name for r in store.list_regions()] == ["town", "village"]
    store.delete_region("town")
    with pytest.raises(RegionNotFound):
        store.region("town")
    with pytest.raises(RegionNotFound):
        store.delete_region("town")
    again = store.create_region(spec)  # a new region under an old name starts empty
    assert (again.version, again.tiles, again.observations) == (0, 0, 0)
    assert again.region_id != info.region_id
    assert store.upload_result("town", "u1", "x") is None  # the old ledger went with the region


def test_upload_adds_exactly_the_increments_and_stores_them_losslessly(store, spec):
    maps = RegionMaps(store)
    X, V = data(1, n=300)
    w = np.random.default_rng(0).uniform(0.5, 2, len(X))
    result = maps.upload("town", "a", X[:100], V[:100], sample_weight=w[:100])
    assert result == {
        "accepted": 100,
        "rejected": NO_REJECTS,
        "upload_id": "a",
        "kind": "observations",
        "region_version": 1,
        "tiles_updated": len(increments(spec, X[:100], V[:100])),
        "replayed": False,
        "untracked": 100,  # rows without a track id: counted as independent, and said so
        "warnings": [UNTRACKED_WARNING],
    }
    maps.upload("town", "b", X[100:], V[100:], sample_weight=w[100:])
    snap = store.snapshot("town")
    expected = increments(spec, X, V, sample_weight=w)
    assert_evidence_equal(snap.evidence, {k: inc.evidence for k, inc in expected.items()})
    assert {k: t.points for k, t in snap.tiles.items()} == {k: inc.points for k, inc in expected.items()}
    assert snap.region.version == 2 and snap.region.observations == 300
    assert all(t.version in (1, 2) for t in snap.tiles.values())
    first = next(iter(expected.values())).evidence
    assert next(iter(snap.tiles.values())).nbytes == len(encode_tile(first, first))  # and the residual


def test_only_tiles_with_data_are_stored(store, spec):
    X, V = data(2)
    left = X[:, 0] < 50
    RegionMaps(store).upload("town", "u", X[left], V[left])
    assert sorted(store.snapshot("town").tiles) == [(0, 0, 0), (0, 1, 0)]


def test_replay_returns_the_first_result_and_a_new_payload_is_a_conflict(store, spec):
    maps = RegionMaps(store)
    X, V = data(3)
    first = maps.upload("town", "same", X, V)
    before = store.snapshot("town")
    assert maps.upload("town", "same", X, V) == {**first, "replayed": True}
    # the store itself also refuses to apply twice, even if asked directly
    tile_increments = increments(spec, X, V)
    digest = payload_digest("observations", X, V, None, None)
    region_id = store.region("town").region_id
    assert (
        store.apply("town", region_id, "same", digest, tile_increments, observations=len(X))["replayed"]
        is True
    )
    with pytest.raises(UploadConflict):
        maps.upload("town", "same", X + 1.0, V)
    with pytest.raises(UploadConflict):
        maps.upload("town", "same", X, V, replace=True)
    after = store.snapshot("town")
    assert after.region.version == before.region.version == 1
    assert_evidence_equal(after.evidence, before.evidence, rtol=0)


def test_bad_rows_are_counted_and_never_stored(store, spec):
    maps = RegionMaps(store)
    X, V = data(4, n=50)
    X[3, 1], V[7, 2], X[9] = np.nan, np.inf, [500.0, 10.0, 10.0]
    result = maps.upload("town", "bad", X, V)
    assert result["accepted"] == 47
    assert result["rejected"] == {**NO_REJECTS, "non_finite": 2, "outside_region": 1}
    keep = np.ones(50, bool)
    keep[[3, 7, 9]] = False
    expected = increments(spec, X[keep], V[keep])
    assert_evidence_equal(store.snapshot("town").evidence, {k: i.evidence for k, i in expected.items()})
    with pytest.raises(ValueError, match="both be"):
        maps.upload("town", "shape", X[:, :2], V)
    with pytest.raises(ValueError, match="upload id"):
        maps.upload("town", "", X[keep], V[keep])
    with pytest.raises(RegionNotFound):
        maps.upload("nowhere", "x", X[keep], V[keep])
    assert store.region("town").version == 1


def test_fit_replaces_the_map(store, spec):
    maps = RegionMaps(store)
    X1, V1 = data(5)
    X2, V2 = data(6, n=80)
    maps.upload("town", "old", X1, V1)
    result = maps.upload("town", "fit", X2, V2, replace=True)
    assert result["kind"] == "fit" and result["region_version"] == 2
    expected = increments(spec, X2, V2)
    snap = store.snapshot("town")
    assert_evidence_equal(snap.evidence, {k: i.evidence for k, i in expected.items()})
    assert snap.region.observations == 80


def assert_map_is_the_field(maps, spec, X, V, version):
    """The served map at ``version``, settled, equals one field over the region's lattice
    fitted on (X, V) at once ("auto": its evidence maximum), everywhere (empty places
    included)."""
    field = region_field(spec).fit(X, V)
    Q = np.random.default_rng(9).uniform([0, 0, 0], [300, 200, 60], (400, 3))
    assert maps.refresh("town").version == version
    got = maps.predict("town", Q, min_version=version)
    assert got.evidence_gap == 0
    mean, std = field.predict(Q, return_std=True)
    climate = np.sqrt((V**2).mean(0))
    np.testing.assert_allclose(got.mean, mean, rtol=0, atol=1e-6 * climate.min())
    np.testing.assert_allclose(got.std, std, rtol=1e-6)
    assert got.version == version
    axes = [np.linspace(0, 300, 4), np.linspace(0, 200, 3), np.array([5.0, 55.0])]
    grid = maps.predict_grid("town", axes, min_version=version)
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    mean, std = field.predict(mesh, return_std=True)
    np.testing.assert_allclose(grid.mean.reshape(-1, 3), mean, rtol=0, atol=1e-6 * climate.min())
    np.testing.assert_allclose(grid.std.reshape(-1, 3), std, rtol=1e-6)
    hyper = maps.store.region("town").hyper  # the record of what this version's map found
    assert hyper["evidence_version"] == version
    np.testing.assert_allclose(hyper["alpha"], field.alpha_, rtol=1e-6)
    np.testing.assert_allclose(hyper["beta"], field.beta_, rtol=1e-6)
    return got


def test_the_served_map_is_one_field_through_uploads_replays_and_refits(store, spec):
    maps = RegionMaps(store, cache_mb=64)
    Q = np.random.default_rng(9).uniform([0, 0, 0], [300, 200, 60], (400, 3))
    empty = maps.predict("town", Q)
    assert not empty.known.any() and np.all(empty.mean == 0) and empty.version == 0
    X, V = data(7, n=400)
    left = X[:, 0] < 150  # the right half of the region stays empty
    maps.upload("town", "a", X[left], V[left])
    got = assert_map_is_the_field(maps, spec, X[left], V[left], 1)
    assert got.known[Q[:, 0] < 100].all() and not got.known[Q[:, 0] > 280].any()
    misses, snapshots = maps.cache.misses, []
    read = store.snapshot
    store.snapshot = lambda *a, **k: snapshots.append(a) or read(*a, **k)
    again = maps.predict("town", Q)
    assert maps.cache.misses == misses and snapshots == []  # warm: no recomputation, no read
    np.testing.assert_array_equal(again.mean, got.mean)
    store.snapshot = read
    X2, V2 = data(8, n=100)
    maps.upload("town", "b", X2, V2)
    assert maps.upload("town", "b", X2, V2)["replayed"]
    both_X, both_V = np.vstack([X[left], X2]), np.vstack([V[left], V2])
    assert_map_is_the_field(maps, spec, both_X, both_V, 2)  # "auto" found again, on both
    info = maps.fit_hyperparameters("town")  # the synchronous form: the map of version 2
    assert info.version == 2 and info.hyper["evidence_version"] == 2
    maps.upload("town", "fit", X, V, replace=True)  # a fit replaces the data, and finds them
    assert store.region("town").hyper["evidence_version"] == 3
    assert_map_is_the_field(maps, spec, X, V, 3)
    with pytest.raises(ValueError, match="outside region"):
        maps.predict("town", [[400.0, 0.0, 0.0]])


def test_queries_answer_from_the_previous_version_until_the_new_one_is_ready(store, spec):
    maps = RegionMaps(store, cache_mb=64)
    X, V = data(3, n=300)
    maps.upload("town", "a", X, V)
    first = maps.predict("town", X[:5], min_version=1)
    gate = threading.Event()
    posterior = maps.refresher.posterior
    maps.refresher.posterior = lambda *a, **k: gate.wait(30) and posterior(*a, **k)  # the refresh is slow
    maps.upload("town", "b", *data(4, n=50))
    stale = maps.predict("town", X[:5])  # answers at once, from version 1, and says so
    assert stale.version == 1 and np.array_equal(stale.mean, first.mean)
    assert stale.behind == 1 and stale.behind_s >= 0
    gate.set()
    fresh = maps.predict("town", X[:5], min_version=2)
    assert fresh.version == 2 and not np.allclose(fresh.mean, first.mean) and fresh.behind == 0


def test_a_fit_that_cannot_be_solved_stores_nothing(store, spec):
    maps = RegionMaps(store, cache_mb=64)
    X, V = data(5, n=100)
    bad = RegionSpec.model_validate({**SPEC, "name": "bad", "alpha": 1e-300, "beta": 1e300})
    store.create_region(bad)
    with pytest.raises(ValueError, match="increase alpha or decrease beta"):
        maps.upload("bad", "f", X, V, replace=True)
    info = store.region("bad")
    assert (info.version, info.tiles, info.observations) == (0, 0, 0)


@pytest.mark.slow  # a child process
@pytest.mark.parametrize("directions", [1, 4])
def test_posteriors_computed_in_a_child_process_answer_as_those_computed_here(store, spec, directions):
    """The service computes posteriors in a child process (seconds of CPU on a city's
    lattice, part of it under the GIL): what comes back, without its factors, answers as
    here (to rounding: BLAS may sum in another order there); errors too."""
    name = f"town{directions}"
    store.create_region(RegionSpec.model_validate({**SPEC, "name": name, "directions": directions}))
    here, there = RegionMaps(store), RegionMaps(store, isolate=True)
    X, V = data(3, n=300)
    V[::3, 0] *= -1  # opposing flows for the directional map
    # the fit comes from a lane's thread, of lower priority: the child it starts is not
    fit = lambda: there.upload(name, "fit", X, V, replace=True)  # noqa: E731
    anyio.run(lambda: Lane("heavy", 1, 0).run(fit))  # the fit's posterior, computed there
    (child,) = there.refresher._pool._processes
    assert psutil.Process(child).nice() == psutil.Process().nice()
    there.upload(name, "more", *data(4, n=100))  # a refresh, there
    Q = np.random.default_rng(5).uniform([0, 0, 0], [300, 200, 60], (200, 3))
    there.refresh(name)  # both settled, each its own: the map stored there is dropped first
    store.drop_map(store.region(name).region_id, 2)
    here.refresh(name)
    a, b = here.predict(name, Q), there.predict(name, Q, min_version=2)
    assert a.version == b.version == 2 and len(there.refresher._pool._processes) == 1
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-12, atol=1e-12 * np.abs(a.mean).max())
    np.testing.assert_allclose(b.std, a.std, rtol=1e-12)
    axes = [np.linspace(0, 300, 7), np.linspace(0, 200, 5), np.linspace(0, 60, 4)]
    grids = here.predict_grid(name, axes), there.predict_grid(name, axes, min_version=2)
    np.testing.assert_allclose(grids[1].std, grids[0].std, rtol=1e-12)
    bad = RegionSpec.model_validate({**SPEC, "name": f"bad{directions}", "alpha": 1e-300, "beta": 1e300})
    store.create_region(bad)
    with pytest.raises(ValueError, match="increase alpha or decrease beta"):
        there.upload(bad.name, "f", X, V, replace=True)
    # a child killed (out of memory, say) is replaced at the next posterior
    (child,) = there.refresher._pool._processes
    os.kill(child, signal.SIGKILL)
    there.upload(name, "again", *data(6, n=100))
    assert there.predict(name, Q, min_version=3).version == 3
    assert list(there.refresher._pool._processes) != [child]
    there.close()


@pytest.mark.parametrize("directions", [1, 4])
def test_a_grid_served_slab_by_slab_is_the_maps_grid_at_once(store, spec, directions, monkeypatch):
    """The service computes a grid in slabs of x (a deadline check between them): joined,
    they are the map's grid computed whole, modes included, and ``known`` is the points'."""
    name = f"town{directions}"
    store.create_region(RegionSpec.model_validate({**SPEC, "name": name, "directions": directions}))
    maps = RegionMaps(store)
    X, V = data(3, n=300, band=True)  # known only near the band
    V[::3, 0] *= -1  # opposing flows for the directional map
    maps.upload(name, "fit", X, V, replace=True)
    axes = [np.linspace(0, 300, 7), np.linspace(0, 200, 5), np.linspace(0, 60, 4)]
    monkeypatch.setattr(RegionMaps, "GRID_SLAB", 2 * 5 * 4)  # slabs of two x values, the last of one
    whole = maps._state(name, store.region(name), 1).map
    modes = whole.predict_grid_modes(axes)
    for asked, want in ((None, whole.predict_grid(axes)), (modes, whole.predict_grid(axes, modes))):
        sliced = maps.predict_grid(name, axes, modes=asked is not None)
        for got, expected in zip((sliced.mean, sliced.std, sliced.known), want, strict=True):
            np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
        if asked is not None:
            np.testing.assert_allclose(sliced.modes.mean, modes.mean, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(sliced.modes.weight, modes.weight, rtol=1e-12, atol=1e-15)
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    points = whole.predict(mesh)
    np.testing.assert_allclose(sliced.std.reshape(-1, 3), points[1], rtol=1e-9)
    np.testing.assert_array_equal(sliced.known.ravel(), points[2])
    assert sliced.known.any() and not sliced.known.all()


def test_posterior_cache_is_bounded_by_memory(store, spec):
    maps = RegionMaps(store)
    states = []
    for i in range(4):
        maps.upload("town", f"u{i}", *data(10 + i, n=100))
        states.append(maps.refresh("town"))
    size = max(s.nbytes for s in states)
    cache = PosteriorCache(max_mb=2.5 * size / 2**20)
    for s in states:
        cache.put((s.region_id, s.version), s)
    assert len(cache) == 2 and cache.nbytes <= 2.5 * size
    assert cache.get((states[0].region_id, 1)) is None  # the oldest went first
    assert cache.get((states[3].region_id, 4)) is states[3]


# -- many processes -------------------------------------------------------------------------


def _writer(url, seed, n_uploads):
    store = open_store(url)
    maps = RegionMaps(store)
    for i in range(n_uploads):
        X, V = data(1000 * seed + i, n=20, band=True)
        maps.upload("town", f"w{seed}-{i}", X, V)
    store.close()


def _reader(url, stop, out):
    """Every snapshot must show whole uploads only: each point counts in exactly one tile."""
    store = open_store(url)
    reads = torn = 0
    while not stop.is_set() or reads == 0:
        snap = store.snapshot("town", keys=())
        tile_points = sum(t.points for t in snap.tiles.values())
        torn += (
            tile_points != snap.region.observations or snap.region.observations != 20 * snap.region.version
        )
        reads += 1
    out.put((reads, torn))
    store.close()


@pytest.mark.slow  # threads of writers and readers
@pytest.mark.parametrize("directions", [1, 4])  # a directional region: evidence per class
def test_concurrent_writers_equal_one_batch_and_readers_never_see_half_an_upload(store_url, directions):
    spec = RegionSpec.model_validate({**SPEC, "directions": directions, "slow_mps": 0.1})
    open_store(store_url).create_region(spec)
    ctx = multiprocessing.get_context("spawn")
    stop, out = ctx.Event(), ctx.Queue()
    reader = ctx.Process(target=_reader, args=(store_url, stop, out))
    reader.start()
    writers = [ctx.Process(target=_writer, args=(store_url, seed, 50)) for seed in range(4)]
    for p in writers:
        p.start()
    for p in writers:
        p.join(timeout=300)
        assert p.exitcode == 0
    stop.set()
    reads, torn = out.get(timeout=60)
    reader.join(timeout=60)
    assert reads > 0 and torn == 0

    batches = [data(1000 * seed + i, n=20, band=True) for seed in range(4) for i in range(50)]
    X, V = np.vstack([b[0] for b in batches]), np.vstack([b[1] for b in batches])
    store = open_store(store_url)
    snap = store.snapshot("town")
    assert snap.region.version == 200 and snap.region.observations == 4000
    expected = increments(spec, X, V)
    assert_evidence_equal(snap.evidence, {k: i.evidence for k, i in expected.items()}, rtol=1e-9)
    store.close()


CRASHER = textwrap.dedent(
    """
    import os, sys, time
    import numpy as np
    from service.maps import RegionMaps
    from service.store import open_store
    from tests.service.test_store import data

    store = open_store(sys.argv[1])

    def stall(key):
        print("half written", flush=True)
        time.sleep(120)

    store.after_tile_write = stall
    X, V = data(42, n=2000)
    X *= [2, 2, 1]
    RegionMaps(store).upload(sys.argv[2], "crash", X, V)
    """
)


def test_a_process_opening_a_store_in_use_waits_for_no_transaction(store_url):
    """A worker, replica or restart opens the store while others write: its setup takes no
    lock that waits for their transactions (an ALTER TABLE on every open did, and deadlocked
    with writers holding a region's row)."""
    if not store_url.startswith("postgresql"):
        pytest.skip("a SQLite store sets nothing up on a database in use")
    import psycopg

    base, schema = store_url.split("?schema=")
    first = open_store(store_url)
    first.create_region(RegionSpec.model_validate(SPEC))
    with psycopg.connect(base) as writer:  # mid-transaction on the tables, as a writer is
        writer.execute(f"SET search_path = {schema}")
        for table in ("regions", "tiles", "maps", "leases"):
            writer.execute(f"SELECT count(*) FROM {table}")
        second = open_store(store_url, timeout_s=2.0)
        second.ping()
        assert second.region("town").version == 0
        second.close()
    first.close()


@pytest.mark.slow  # a writer process killed
def test_a_writer_killed_mid_upload_leaves_all_or_nothing(store_url):
    # 6 x 4 tiles: an upload everywhere writes more than one batch of tile rows
    spec = RegionSpec.model_validate(
        {**SPEC, "name": "city", "bounds_m": {"min": [0, 0, 0], "max": [600, 400, 60]}}
    )
    store = open_store(store_url)
    store.create_region(spec)
    maps = RegionMaps(store)
    X0, V0 = data(41, n=500)
    X0 *= [2, 2, 1]
    maps.upload("city", "base", X0, V0)
    before = store.snapshot("city")

    X, V = data(42, n=2000)
    X *= [2, 2, 1]
    proc = subprocess.Popen(
        [sys.executable, "-c", CRASHER, store_url, "city"],
        stdout=subprocess.PIPE,
        text=True,
        cwd=os.getcwd(),
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    assert proc.stdout.readline().strip() == "half written"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)

    after = store.snapshot("city")
    assert after.region.version == 1 and after.region.observations == 500
    assert_evidence_equal(after.evidence, before.evidence, rtol=0)
    assert store.upload_result("city", "crash", payload_digest("observations", X, V, None, None)) is None
    # the client retries: now it applies, once
    assert maps.upload("city", "crash", X, V)["replayed"] is False
    expected = increments(spec, np.vstack([X0, X]), np.vstack([V0, V]))
    assert_evidence_equal(store.snapshot("city").evidence, {k: i.evidence for k, i in expected.items()})
    store.close()


@pytest.mark.parametrize("directions", [1, 4])
def test_a_retraction_leaves_exactly_the_map_without_that_upload(store, spec, directions):
    """A broken sensor's upload, retracted: the stored statistics (1e-9), the tiles and the
    map (1e-6) equal those of the same region built without it, once per upload id."""
    body = {**SPEC, "name": "town", "directions": directions}
    if directions > 1:
        store.delete_region("town")
        store.create_region(RegionSpec.model_validate(body))
    maps = RegionMaps(store)
    (Xa, Va), (Xc, Vc) = data(20, n=150), data(22, n=150)
    Xb, Vb = data(21, n=120)
    Xb[:60, 0] = np.linspace(210, 299, 60)  # tile column 2 has only the broken upload's rows
    Xa[:, 0], Xc[:, 0] = Xa[:, 0] * 0.66, Xc[:, 0] * 0.66
    weight, noise = np.linspace(0.5, 2, 120), np.full(120, 3.0)
    maps.upload("town", "a", Xa, Va)
    maps.upload("town", "b", Xb, Vb + 20, sample_weight=weight, input_noise_std=noise)
    maps.upload("town", "c", Xc, Vc)
    assert (2, 0, 0) in store.snapshot("town").tiles
    result = maps.retract("town", "b", Xb, Vb + 20, sample_weight=weight, input_noise_std=noise)
    assert (result["kind"], result["accepted"], result["region_version"]) == ("retraction", 120, 4)
    assert maps.retract("town", "b", Xb, Vb + 20, sample_weight=weight, input_noise_std=noise) == {
        **result,
        "replayed": True,
    }
    assert maps.upload("town", "b", Xb, Vb + 20, sample_weight=weight, input_noise_std=noise)["replayed"]
    after = store.snapshot("town")
    assert after.region.version == 4 and after.region.observations == 300
    # the same region built without the broken upload ("auto": its evidence maximum)
    clean = RegionSpec.model_validate({**body, "name": "clean"})
    store.create_region(clean)
    maps.upload("clean", "a", Xa, Va)
    maps.upload("clean", "c", Xc, Vc)
    expected = store.snapshot("clean")
    assert set(after.tiles) == set(expected.tiles) and (2, 0, 0) not in after.tiles
    assert_evidence_equal(after.evidence, expected.evidence, rtol=1e-9)
    assert [t.points for t in after.tiles.values()] == [t.points for t in expected.tiles.values()]
    Q = np.random.default_rng(9).uniform([0, 0, 0], [300, 200, 60], (300, 3))
    maps.fit_hyperparameters("town"), maps.fit_hyperparameters("clean")  # the settled maps
    got, want = maps.predict("town", Q, min_version=4), maps.predict("clean", Q, min_version=2)
    # the same evidence to rounding, its maximum found from other starts: the acceptance's 1e-6
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-6 * np.abs(want.mean).max())
    np.testing.assert_allclose(got.std, want.std, rtol=1e-6)
    np.testing.assert_array_equal(got.known, want.known)


def test_a_retraction_needs_the_uploads_own_rows_and_an_upload_still_in_the_map(store, spec):
    maps = RegionMaps(store)
    X, V = data(23, n=60)
    maps.upload("town", "a", X, V)
    before = store.snapshot("town")
    with pytest.raises(UploadConflict, match="not those of upload"):
        maps.retract("town", "a", X, V + 1)
    with pytest.raises(UploadNotFound, match="no upload 'zz'"):
        maps.retract("town", "zz", X, V)
    maps.upload("town", "f", X[:30], V[:30], replace=True)
    with pytest.raises(UploadConflict, match="replaced by the fit at version 2"):
        maps.retract("town", "a", X, V)
    with pytest.raises(UploadConflict, match="is a fit"):
        maps.retract("town", "f", X[:30], V[:30])
    after = store.snapshot("town")
    assert after.region.version == before.region.version + 1 == 2  # only the fit changed it
    assert after.region.observations == 30


def test_tiles_checksummed_before_crc32_still_read_and_damage_still_shows(store, spec):
    """Tiles written with a sha256 checksum (before CRC-32) are read as they were; a flipped
    byte fails either kind."""
    import hashlib

    from service.store.base import checks_out, checksum

    RegionMaps(store).upload("town", "a", *data(1, n=100))
    blob = b"\x00\x01statistics" * 100
    assert checks_out(blob, checksum(blob)) and checksum(blob).startswith("crc32:")
    assert checks_out(blob, hashlib.sha256(blob).hexdigest())
    damaged = blob[:-1] + b"\x00"
    assert not checks_out(damaged, checksum(blob)) and not checks_out(
        damaged, hashlib.sha256(blob).hexdigest()
    )
    before = store.snapshot("town").evidence
    info = store.region("town")
    with store._write() as q:
        for key, stats in q("SELECT key, stats FROM tiles WHERE region_id = ?", (info.region_id,)):
            sha = hashlib.sha256(bytes(stats)).hexdigest()
            q("UPDATE tiles SET checksum = ? WHERE region_id = ? AND key = ?", (sha, info.region_id, key))
    assert_evidence_equal(store.snapshot("town").evidence, before, rtol=0)


def test_a_region_read_sees_every_commit_of_any_connection(tmp_path):
    """SQLite keeps a thread's region read while the database is unchanged: another
    connection's commit (another process's store) and this store's own writes, in any
    thread, are seen at the next read; a deletion too."""
    name = SPEC["name"]
    from service.store.sqlite import SqliteStore

    here, there = SqliteStore(tmp_path), SqliteStore(tmp_path)
    spec = RegionSpec.model_validate(SPEC)
    here.create_region(spec)
    assert here.region(name).version == 0 and here.region(name) is here.region(name)  # kept
    X, V = data(1)
    region_id = there.region(name).region_id
    there.apply(name, region_id, "a", "d", increments(spec, X, V), observations=len(X))
    assert here.region(name).version == 1  # another connection's commit
    here.apply(name, region_id, "b", "e", increments(spec, X, V), observations=len(X))
    assert here.region(name).version == 2  # its own, from this thread
    seen = []
    thread = threading.Thread(target=lambda: seen.append(here.region(name).version))
    thread.start()
    thread.join()
    here.record_hyperparameters(name, region_id, {"alpha": [1.0] * 3}, 2)  # a write, no new version
    assert seen == [2] and here.region(name).hyper["alpha"] == [1.0] * 3
    there.delete_region(name)
    with pytest.raises(RegionNotFound):
        here.region(name)
    here.close()
    there.close()
