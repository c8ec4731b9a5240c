"""POST /v1/regions/{name}/routes/assess: the library's metrics of a route, over HTTP."""

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.route import MAX_ROUTE_POINTS, VEHICLES, Vehicle, assess
from bdf.region.spec import RegionSpec
from service.app import create_app
from service.settings import Settings
from service.wire import GEOJSON
from tests.service.test_store import SPEC, data

NAME = SPEC["name"]
JSON = {"Content-Type": "application/json"}
#: across the region and back up: four segments of different headings and climbs
ROUTE = np.array(
    [[10.0, 20.0, 5.0], [150.0, 40.0, 25.0], [160.0, 180.0, 40.0], [290.0, 190.0, 50.0], [200.0, 60.0, 30.0]]
)


@pytest.fixture(params=[1, 8], ids=["one class", "8 sectors"])
def served(request, tmp_path):
    """A region with data on a service and, beside it, the library's map of the same data."""
    spec = RegionSpec.model_validate({**SPEC, "directions": request.param, "slow_mps": 0.5})
    X, V = data(3, n=1500)
    V = 30.0 * V  # an aircraft's speeds: above slow_mps, in every sector
    app = create_app(Settings(store_url=f"sqlite:///{tmp_path / 'data'}"))
    with TestClient(app) as client:
        assert client.post("/v1/regions", json=spec.model_dump(mode="json")).status_code == 201
        body = {"points": X.tolist(), "velocities": V.tolist()}
        upload = client.post(f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "u"})
        assert upload.status_code == 200, upload.text
        evidence = region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
        yield client, RegionMap(spec, compute_posterior(spec, evidence))


def assert_equal_metrics(got: dict, want: dict) -> None:
    for part in ("segments", "total"):
        for key, value in want[part].items():
            np.testing.assert_allclose(got[part][key], value, rtol=1e-9, atol=1e-12, err_msg=f"{part} {key}")
    assert got["envelope"] == pytest.approx(want["envelope"], rel=1e-9)


def test_assess_answers_the_librarys_metrics_in_json_and_geojson(served):
    """JSON in ENU (with times and headings, and a vehicle of its own), and GeoJSON in WGS84
    (a FeatureCollection of one LineString, its properties the other fields): to 1e-9 of
    :func:`bdf.region.route.assess` on the library's map of the same data."""
    client, region_map = served
    url = f"/v1/regions/{NAME}/routes/assess?min_version=1"
    times = np.array([0.0, 5.0, 9.0, 16.0, 30.0])
    heading = [80.0, 10.0, 75.0, 215.0]
    craft = {**VEHICLES["fixed-wing"].__dict__, "floor_m": 0.0}
    body = {
        "points": ROUTE.tolist(),
        "times_s": times.tolist(),
        "heading_deg": heading,
        "max_std_mps": 2.0,
        "vehicle": craft,
    }
    got = client.post(url, json=body)
    assert got.status_code == 200, got.text
    assert got.headers["X-Region-Version"] == "1" and got.json()["region_version"] == 1
    want = assess(
        region_map, ROUTE, max_std_mps=2.0, craft=Vehicle(**craft), times_s=times, heading_deg=heading
    )
    assert_equal_metrics(got.json(), want)
    assert len(got.json()["segments"]["length_m"]) == 4
    spec = region_map.spec
    lat, lon, alt = spec.frame().to_geodetic(ROUTE).T
    feature = {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": np.column_stack([lon, lat, alt]).tolist()},
        "properties": {"max_std_mps": 2.0, "vehicle": "evtol", "name": "a fleet's own route"},
    }
    doc = {"type": "FeatureCollection", "features": [feature]}
    got = client.post(url, content=json.dumps(doc), headers={"Content-Type": GEOJSON})
    assert got.status_code == 200, got.text
    enu = spec.frame().to_enu(lat, lon, alt)
    assert np.abs(enu - ROUTE).max() < 1e-6
    assert_equal_metrics(got.json(), assess(region_map, enu, max_std_mps=2.0, craft=VEHICLES["evtol"]))


def test_bad_routes_are_422_with_the_reason(served):
    client, _ = served
    url = f"/v1/regions/{NAME}/routes/assess"

    def post(points, **fields):
        return client.post(url, json={"points": points, "max_std_mps": 2.0, **fields})

    cases = [
        (post([[10.0, 10.0, 10.0]]), "at least 2 points"),
        (
            client.post(
                url, content=b'{"points": [[1, 1, 1], [1e400, 1, 1]], "max_std_mps": 2}', headers=JSON
            ),
            "finite",
        ),
        (post([[10.0, 10.0, 10.0], [400.0, 10.0, 10.0]]), "outside region 'town'"),
        (
            post(np.tile([[10.0, 10.0, 10.0], [20.0, 10.0, 10.0]], (MAX_ROUTE_POINTS, 1)).tolist()),
            "rows in one request",
        ),
        (post([[10.0, 10.0, 10.0], [10.0, 10.0, 10.0]]), "two consecutive points that are the same"),
        (post(ROUTE.tolist(), times_s=[0.0, 1.0]), "times_s must be 5 finite, increasing seconds"),
        (post(ROUTE.tolist(), heading_deg=[0.0]), "heading_deg must be 4 finite degrees"),
        (post(ROUTE.tolist(), vehicle="blimp"), "vehicle"),
        (client.post(url, content=b'{"type": "Point"}', headers={"Content-Type": GEOJSON}), "LineString"),
        (client.post(url, content=b"x,y", headers={"Content-Type": "text/csv"}), "application/json"),
    ]
    for response, reason in cases:
        assert 400 <= response.status_code < 500 and response.status_code != 404, response.text
        assert response.headers["content-type"].startswith("application/problem+json")
        assert reason in response.json()["detail"], (reason, response.json()["detail"])
    assert cases[3][0].status_code == 422
