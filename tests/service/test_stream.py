"""Maps under a stream of uploads: "auto" is the evidence maximum of the data in force,
whatever uploads brought them; refreshes keep up (one per region, of the newest version)
and say how far behind an answer is."""

import threading

import numpy as np
import pytest

from bdf.hyperparameters import LOG_TOLERANCE
from bdf.region.map import region_field
from bdf.region.spec import RegionSpec
from service.maps import RegionMaps
from tests.service.test_store import SPEC

pytestmark = pytest.mark.slow  # maps built from many uploads


def lanes(n: int, seed: int = 0):
    """Traffic over the town: four lanes flying east, west, north and south (so a map of 8
    heading sectors has several modes), with track-like weights."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([0, 0, 0], [300, 200, 60], (n, 3))
    lane = rng.integers(0, 4, n)
    heading = np.radians(np.array([90.0, 270.0, 0.0, 180.0])[lane])
    speed = 20.0 + 0.05 * X[:, 2] + 3.0 * np.sin(X[:, 0] / 50.0)
    V = np.stack([speed * np.sin(heading), speed * np.cos(heading), 0.02 * (X[:, 2] - 30.0)], axis=1)
    V += rng.standard_normal(V.shape) * np.array([1.0, 1.0, 0.3])
    weight = rng.uniform(0.2, 1.0, n)
    return X, V, weight


def wait_until(condition, polls: int = 6000) -> None:
    """Poll ``condition`` every 10 ms until it holds (a background refresh reached a point)."""
    for _ in range(polls):
        if condition():
            return
        threading.Event().wait(0.01)
    raise AssertionError("the background refresh did not get there")


@pytest.mark.parametrize("directions", [1, 8])
def test_a_map_built_by_many_uploads_is_the_single_fit(store, directions):
    """The same data as 1, 10 and 100 uploads of random sizes in shuffled orders: once the
    newest version is served, hyperparameters, means and stds are those of one fit of all
    the data (the search's tolerance; 1e-6 of the climatology std; 1e-6 relative; shares to
    1e-6). 1: the paper's model of one field (one class answered from 8 sectors is the map
    of 8)."""
    X, V, w = lanes(3000)
    model = {"directions": directions, "model_directions": directions}
    one = RegionSpec.model_validate({**SPEC, **model})
    field = region_field(one).fit(X, V, sample_weight=w)
    Q = np.random.default_rng(7).uniform([0, 0, 0], [300, 200, 60], (500, 3))
    want = field.predict_modes(Q)
    climate = np.sqrt((V**2).mean(0))
    for uploads in (1, 10, 100):
        name = f"town{uploads}"
        spec = RegionSpec.model_validate({**SPEC, "name": name, **model})
        store.create_region(spec)
        maps = RegionMaps(store, cache_mb=64)
        rng = np.random.default_rng(uploads)
        order = rng.permutation(len(X))
        cuts = np.sort(rng.choice(np.arange(1, len(X)), uploads - 1, replace=False))
        for k, rows in enumerate(np.split(order, cuts)):
            maps.upload(name, f"u{k}", X[rows], V[rows], sample_weight=w[rows])
        info = store.region(name)
        assert info.version == uploads
        post = maps.refresh(name).posterior  # settled
        got = maps.predict(name, Q, min_version=uploads, modes=True)
        assert got.version == uploads and got.behind == 0 and got.evidence_gap == 0
        np.testing.assert_allclose(
            np.log(post.alpha / post.beta), np.log(field.alpha_ / field.beta_), atol=10 * LOG_TOLERANCE
        )
        np.testing.assert_allclose(post.beta, field.beta_, rtol=1e-6)
        np.testing.assert_allclose(got.modes.mean, want.mean, rtol=0, atol=1e-6 * climate.min())
        np.testing.assert_allclose(got.modes.std, want.std, rtol=1e-6)
        np.testing.assert_allclose(got.modes.share, want.share, rtol=0, atol=1e-6)
        recorded = store.region(name).hyper  # the region view's record: this version's
        assert recorded["evidence_version"] == uploads
        np.testing.assert_allclose(recorded["alpha"], field.alpha_, rtol=1e-6)
        maps.close()


def test_refreshes_run_one_at_a_time_per_region_and_skip_to_the_newest_version(store):
    """While a refresh runs, 20 uploads arrive: the next refresh computes the newest version
    (the 19 between are skipped, never queued), readers are answered at once from the map
    they have and told how far behind it is, and a reader of the newest version waits."""
    spec = RegionSpec.model_validate(SPEC)
    store.create_region(spec)
    maps = RegionMaps(store, cache_mb=64)
    X, V, _ = lanes(2100, seed=3)
    maps.upload("town", "first", X[:100], V[:100])
    assert maps.predict("town", X[:3], min_version=1).version == 1
    gate, computed, running, most = threading.Event(), [], [0], [0]
    posterior, lock = maps.refresher.posterior, threading.Lock()

    def slow(spec, evidence, *args, **kwargs):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        gate.wait(30)
        try:
            out = posterior(spec, evidence, *args, **kwargs)
            computed.append(evidence.count)
            return out
        finally:
            with lock:
                running[0] -= 1

    maps.refresher.posterior = slow
    for k in range(20):
        maps.upload("town", f"u{k}", X[100 + 100 * k : 200 + 100 * k], V[100 + 100 * k : 200 + 100 * k])
    stale = maps.predict("town", X[:3])
    assert stale.version == 1 and stale.behind == 20 and stale.behind_s >= 0
    answered = []
    newest = threading.Thread(
        target=lambda: answered.append(maps.predict("town", X[:3], min_version=21).version)
    )
    newest.start()
    gate.set()
    newest.join(60)
    maps.close()
    assert answered == [21]  # the reader got the newest version
    # one computation of an early version (the refresh under way when the burst began) and
    # of the newest (and its settling pass, which may end after the reader's answer), none
    # of the versions between, one at a time
    counts = computed
    assert counts[-1] == 2100.0 and len(set(counts)) <= 2 and len(counts) <= 3 and most[0] == 1
    assert maps.stats.skipped >= 18
    assert maps.predict("town", X[:3]).version == 21


def test_a_background_refresh_is_within_a_nat_at_once_and_settles_when_no_version_waits(store):
    """After a small upload the background refresh answers at once with hyperparameters
    within a nat of the evidence maximum (the answer says how far, the record says not
    settled); with no newer version waiting it computes the version again, settled on the
    maximum (the single fit's), and that map replaces the first; the record says so."""
    spec = RegionSpec.model_validate(SPEC)
    store.create_region(spec)
    maps = RegionMaps(store, cache_mb=64)
    X, V, w = lanes(3000, seed=5)
    maps.upload("town", "base", X[:2950], V[:2950], sample_weight=w[:2950])
    maps.refresh("town")
    calls, gate = [], threading.Event()
    posterior = maps.refresher.posterior

    def gated(spec, evidence, start, stored=True, settle=True, job=0):
        calls.append(settle)
        if settle:
            gate.wait(30)
        return posterior(spec, evidence, start, stored=stored, settle=settle, job=job)

    maps.refresher.posterior = gated
    maps.upload("town", "more", X[2950:], V[2950:], sample_weight=w[2950:])
    quick = maps.predict("town", X[:5], min_version=2)
    assert quick.version == 2 and 0 < quick.evidence_gap < 1.0
    wait_until(lambda: True in calls)  # the settling pass has begun: the first map's record is written
    recorded = store.region("town").hyper
    assert recorded["evidence_version"] == 2 and not recorded["settled"]
    assert recorded["evidence_gap"] == pytest.approx(quick.evidence_gap)
    gate.set()
    info = maps.fit_hyperparameters("town")  # waits for the settled map
    settled = maps.predict("town", X[:5])
    maps.close()
    assert calls == [False, True]
    assert settled.version == 2 and settled.evidence_gap == 0
    assert info.hyper["settled"] and info.hyper["evidence_version"] == 2 and info.hyper["evidence_gap"] == 0
    single = region_field(spec).fit(X, V, sample_weight=w)
    np.testing.assert_allclose(info.hyper["alpha"], single.alpha_, rtol=1e-6)
    np.testing.assert_allclose(settled.mean, single.predict(X[:5]), rtol=0, atol=1e-6 * np.abs(V).max())
    assert maps.stats.settled == 1


@pytest.mark.parametrize("isolate", [False, True])
def test_a_version_waits_only_for_the_refresh_under_way_and_abandons_a_settling_pass(store, isolate):
    """A version written while a refresh computes the one before is served by the next
    refresh: answers meanwhile say one version and one refresh behind. A version written
    while the background settles the one before abandons that settling pass (at its next
    factorisation, in the posterior process too): the newer version is computed next, then
    settled on the single fit's maximum."""
    spec = RegionSpec.model_validate(SPEC)
    store.create_region(spec)
    maps = RegionMaps(store, cache_mb=64, isolate=isolate)
    X, V, w = lanes(3050, seed=6)
    maps.upload("town", "base", X[:2900], V[:2900], sample_weight=w[:2900])
    maps.refresh("town")
    gates = [threading.Event() for _ in range(8)]
    calls, ended = [], []
    posterior = maps.refresher.posterior

    def gated(spec, evidence, start=None, stored=True, settle=True, job=0):
        k = len(calls)
        calls.append((settle, job))
        gates[k].wait(60)
        try:
            out = posterior(spec, evidence, start, stored=stored, settle=settle, job=job)
        except Exception as exc:
            ended.append(type(exc).__name__)
            raise
        ended.append("computed")
        return out

    def rows(a, b):
        return X[a:b], V[a:b]

    maps.refresher.posterior = gated
    maps.upload("town", "v2", *rows(2900, 2950), sample_weight=w[2900:2950])
    wait_until(lambda: len(calls) >= 1)  # version 2 refreshing: version 3 waits for it and the next
    maps.upload("town", "v3", *rows(2950, 3000), sample_weight=w[2950:3000])
    gates[0].set()
    wait_until(lambda: len(calls) >= 2)
    behind = maps.predict("town", X[:5])
    assert (behind.version, behind.behind, behind.refreshes_behind) == (2, 1, 1)
    gates[1].set()
    wait_until(lambda: len(calls) >= 3)  # version 3 served, its settling pass under way
    assert calls[2][0] and calls[2][1] > 0
    fresh = maps.predict("town", X[:5])
    assert (fresh.version, fresh.behind, fresh.refreshes_behind) == (3, 0, 0) and fresh.evidence_gap > 0
    maps.upload("town", "v4", *rows(3000, 3050), sample_weight=w[3000:3050])
    waiting = maps.predict("town", X[:5])
    assert (waiting.version, waiting.behind, waiting.refreshes_behind) == (3, 1, 0)
    for gate in gates:
        gate.set()
    info = maps.fit_hyperparameters("town")
    settled = maps.predict("town", X[:5])
    maps.close()
    assert [settle for settle, _ in calls] == [False, False, True, False, True]
    assert ended == ["computed", "computed", "Abandoned", "computed", "computed"]
    assert maps.stats.abandoned == 1
    assert settled.version == 4 and settled.evidence_gap == 0 and info.hyper["evidence_version"] == 4
    single = region_field(spec).fit(X, V, sample_weight=w)
    np.testing.assert_allclose(info.hyper["alpha"], single.alpha_, rtol=1e-6)
    np.testing.assert_allclose(settled.mean, single.predict(X[:5]), rtol=0, atol=1e-6 * np.abs(V).max())
