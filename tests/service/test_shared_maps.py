"""A version's map is computed once and shared through the store (service.refresh): by the
processes on one store, by a restart, and after its computing process died."""

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from service.app import create_app
from service.maps import RegionMaps
from service.settings import Settings
from service.store import open_store
from tests.service.test_store import SPEC, data

NAME = SPEC["name"]
ROOT = Path(__file__).resolve().parents[2]
FIXED = {**SPEC, "alpha": 1e-3, "beta": 0.05}  # no settling pass: one computation per version


def never(*args, **kw):
    raise AssertionError("a map was computed where one is stored")


def test_a_restart_answers_from_the_stored_map_without_computing(store_url):
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        X, V = data(1)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        r = c.post(f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "a"})
        assert r.is_success
        assert c.post(f"/v1/regions/{NAME}/hyperparameters").status_code == 200  # settled and stored
        first = c.post(f"/v1/regions/{NAME}/query", json={"points": [[150, 100, 30]]}).json()

    # the restart: a deadline of 1 s, and a posterior that may not be computed
    app = create_app(Settings(store_url=store_url, request_timeout_s=1.0))
    app.state.service.maps.refresher.posterior = never
    with TestClient(app) as c:
        r = c.post(f"/v1/regions/{NAME}/query?min_version=1", json={"points": [[150, 100, 30]]})
        assert r.status_code == 200, r.text
        stats = app.state.service.maps.stats
        assert (stats.count, stats.loaded, stats.failed) == (0, 1, 0)
    assert r.json()["region_version"] == 1
    np.testing.assert_array_equal(r.json()["mean"], first["mean"])
    np.testing.assert_array_equal(r.json()["std"], first["std"])


def test_processes_on_one_store_compute_each_version_once(store_url):
    """Two processes' refreshers (the workers or replicas of one store) asked for the same
    version at once: one computes it, the other loads it; each later version likewise."""
    store_a, store_b = open_store(store_url), open_store(store_url)
    store_a.create_region(RegionSpec.model_validate(FIXED))
    a, b = RegionMaps(store_a), RegionMaps(store_b)
    computing = threading.Event()
    posterior = a.refresher.posterior

    def slow(*args, **kw):  # long enough for the other to find the lease held
        computing.set()
        threading.Event().wait(0.5)
        return posterior(*args, **kw)

    a.refresher.posterior = b.refresher.posterior = slow
    Q = np.random.default_rng(5).uniform([0, 0, 0], [300, 200, 60], (50, 3))
    for version in (1, 2, 3):
        a.upload(NAME, f"u{version}", *data(version))
        answers = [None, None]

        def ask(i, maps, answers=answers, version=version):
            answers[i] = maps.predict(NAME, Q, min_version=version)

        threads = [threading.Thread(target=ask, args=(i, m)) for i, m in enumerate((a, b))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert [p.version for p in answers] == [version, version]
        np.testing.assert_array_equal(answers[0].mean, answers[1].mean)
        assert a.stats.count + b.stats.count == version  # each version computed once
        assert a.stats.loaded + b.stats.loaded == version
    assert computing.is_set()
    for maps in (a, b):
        maps.close()
    store_b.close()
    store_a.close()


def test_a_killed_holders_version_is_computed_by_another_process_once_its_lease_expires(
    store_url, store, spec
):
    """A process takes the region's lease (2 s) to compute a version and is killed (SIGKILL)
    while it computes: the next process's refresh waits for it, takes the lease over once
    it expired, computes the version, stores it and frees the lease."""
    X, V = data(1)
    store.apply(NAME, store.region(NAME).region_id, "a", "d", increments(spec, X, V), observations=len(X))
    info = store.region(NAME)  # version 1, and no refresh of it here yet
    script = f"""
import threading
from service.maps import RegionMaps
from service.store import open_store
maps = RegionMaps(open_store({store_url!r}), lease_s=2.0)
maps.refresher.posterior = lambda *a, **k: threading.Event().wait()  # computes forever
maps.refresh({NAME!r})
"""
    holder = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while (lease := store.take_lease(info.region_id, "probe", info.version, 0.0)).holder == "probe":
            store.release_lease(info.region_id, "probe")  # not taken yet: free it again
            assert holder.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        assert lease.version == info.version and str(holder.pid) in lease.holder
        holder.kill()
        holder.wait(30)
        maps, done = RegionMaps(store), []
        taker = threading.Thread(target=lambda: done.append(maps.refresh(NAME)), daemon=True)
        taker.start()  # it waits for the holder's map, then takes its lease over
        taker.join(60)
        assert done, "the dead holder's lease was never taken over"
        state = done[0]
    finally:
        holder.kill()
    assert state.version == 1 and maps.stats.count >= 1 and maps.stats.loaded == 0
    assert store.stored_map(info.region_id).version == 1
    assert store.take_lease(info.region_id, "next", 2, 1.0).holder == "next"  # freed
    maps.close()


@pytest.mark.parametrize("settled", [False, True])
def test_the_store_keeps_the_newest_map_and_never_an_older_over_it(store, spec, settled):
    region_id = store.region(NAME).region_id
    assert store.stored_map(region_id) is None and store.load_map(region_id) is None
    assert store.save_map(region_id, 2, settled, 1.5, b"two")
    assert not store.save_map(region_id, 1, True, 1.0, b"one")  # older
    assert store.save_map(region_id, 2, True, 2.0, b"two, settled") != settled  # settled over unsettled only
    stored, blob = store.load_map(region_id)
    assert stored.version == 2 and stored.settled and blob == (b"two" if settled else b"two, settled")
    assert store.save_map(region_id, 3, False, 1.0, b"three")  # newer over settled
    assert store.load_map(region_id)[1] == b"three"
    store.delete_region(NAME)
    store.create_region(spec)
    assert store.stored_map(store.region(NAME).region_id) is None
