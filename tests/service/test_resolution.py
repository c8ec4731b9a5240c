"""A region of ``directions: "auto"`` in the service: its fit chooses and stores the heading
sectors with its tiles; writes split into the sectors before are computed again."""

import numpy as np
import pytest

from bdf.region.evidence import accepted_increments, checked_rows
from bdf.region.resolution import choose_directions
from bdf.region.spec import RegionSpec
from service.maps import RegionMaps
from service.store import ResolutionChanged
from tests.bdf.region.test_resolution import CROSSING, crossing_flows

TRACKS_M = np.arange(-3500, 3501, 1000)


@pytest.fixture
def crossing(store):
    """The crossing flows' region, its model at 8 sectors until a fit chooses."""
    spec = RegionSpec.model_validate({**CROSSING, "model_directions": 8})
    store.create_region(spec)
    return spec


def test_a_fit_chooses_the_sectors_stores_them_with_its_tiles_and_uploads_then_use_them(store, crossing):
    maps = RegionMaps(store)
    X, V, track, t = crossing_flows(TRACKS_M, seed=0)
    early = maps.upload("crossing", "early", X[:500], V[:500], track=track[:500], time=t[:500])
    assert store.region("crossing").spec.model_directions == 8
    fit = maps.upload("crossing", "fit", X, V, track=track, time=t, replace=True)
    assert fit["kind"] == "fit" and fit["region_version"] == early["region_version"] + 1
    info = store.region("crossing")
    expected = choose_directions(crossing, checked_rows(X, V, track=track, time=t)).spec
    # the service's fit sums in its own threads: scores equal to the last few bits
    scores = ("directions_scores",)
    assert info.spec.model_dump(exclude=set(scores)) == expected.model_dump(exclude=set(scores))
    got, want = ([s.model_dump() for s in spec.directions_scores] for spec in (info.spec, expected))
    assert got == [{k: pytest.approx(v, rel=1e-9, abs=1e-12) for k, v in row.items()} for row in want]
    assert info.spec.model_directions >= 12 and info.spec.directions == "auto"
    assert [s.chosen for s in info.spec.directions_scores].count(True) == 1
    # the stored tiles hold the chosen sectors' classes, and the map answers every class
    snapshot = store.snapshot("crossing")
    classes = info.spec.model_sectors.classes
    assert {len(ev.classes) for ev in snapshot.evidence.values()} == {classes}
    pred = maps.predict("crossing", X[:10], info, modes=True)
    assert pred.version == fit["region_version"] and pred.modes.share.shape == (10, classes)
    # a later upload is split into them, and a replayed fit changes nothing
    Xl, Vl, tl, ttl = crossing_flows([0.0], seed=2)
    later = maps.upload("crossing", "later", Xl, Vl, track=tl, time=ttl)
    assert later["region_version"] == fit["region_version"] + 1
    assert maps.upload("crossing", "fit", X, V, track=track, time=t, replace=True)["replayed"]
    assert store.region("crossing").spec == info.spec


def test_a_write_split_into_the_sectors_before_a_fit_chose_stores_nothing_and_is_computed_again(
    store, crossing
):
    maps = RegionMaps(store)
    X, V, track, t = crossing_flows(TRACKS_M, seed=0)
    before = store.region("crossing")
    stale, summary = accepted_increments(crossing, X[:300], V[:300], track=track[:300], time=t[:300])
    maps.upload("crossing", "fit", X, V, track=track, time=t, replace=True)
    info = store.region("crossing")
    assert info.spec.model_directions != before.spec.model_directions == 8
    with pytest.raises(ResolutionChanged, match=f"{info.spec.model_directions} heading sectors"):
        store.apply("crossing", info.region_id, "stale", "d", stale, observations=summary["accepted"])
    assert store.region("crossing").version == info.version  # nothing stored
    assert store.upload_result("crossing", "stale", "d") is None

    # an upload that read the spec before the fit committed is computed again with the new one
    reads = iter([before, None])
    real = store.region

    def region(name):
        info = next(reads, None)
        return real(name) if info is None else info

    store.region = region
    try:
        result = maps.upload("crossing", "raced", X[:300], V[:300], track=track[:300], time=t[:300])
    finally:
        store.region = real
    assert result["region_version"] == info.version + 1 and not result["replayed"]
    classes = info.spec.model_sectors.classes
    assert {len(ev.classes) for ev in store.snapshot("crossing").evidence.values()} == {classes}


@pytest.mark.slow
def test_over_http_a_fit_job_chooses_in_the_posterior_process_and_the_region_view_says_what_and_why(
    live_server,
):
    from clients.sdk import BDFClient

    X, V, track, t = crossing_flows(TRACKS_M, seed=0)
    server = live_server()
    with BDFClient(server.url) as bdf:
        bdf.create_region(CROSSING)
        job = bdf.fit("crossing", X, V, track=track, t=t, key="fit", wait=False)
        seen = []
        while job["state"] not in ("succeeded", "failed"):
            seen.append(job["progress"])
            job = bdf.job(job["id"])
        assert job["state"] == "succeeded", job
        assert seen == sorted(seen) and job["progress"] == 1.0
        spec = RegionSpec.model_validate(bdf.region("crossing").spec)
        expected = choose_directions(
            RegionSpec.model_validate(CROSSING), checked_rows(X, V, track=track, time=t)
        )
        assert spec == expected.spec and spec.directions == "auto"
        # the mode of a heading, from the chosen sectors' map
        Xt, Vt, _, _ = crossing_flows([0.0], seed=1)
        heading = np.degrees(np.arctan2(Vt[:, 0], Vt[:, 1]))
        pred = bdf.query("crossing", Xt, heading_deg=heading)
        assert np.sqrt(np.mean((pred.mean - Vt) ** 2)) < 5.0
