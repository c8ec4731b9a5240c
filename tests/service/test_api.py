"""The HTTP API through a real uvicorn server on 127.0.0.1 (``bdf serve`` in a subprocess)."""

import inspect
import io
import json
import socket
import threading
import time

import httpx
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fastapi.routing import APIRoute

from bdf.posterior import known
from bdf.region.map import region_field
from bdf.region.spec import RegionSpec
from service.app import create_app, ops, router
from service.formats import arrow_body, arrow_bytes, npz_bytes
from service.settings import Settings
from service.wire import ARROW, GEOJSON, NPZ, PARQUET
from tests.service.test_store import NO_REJECTS, SPEC, data

pytestmark = pytest.mark.slow  # the HTTP API end to end

NAME = SPEC["name"]


def library(spec: RegionSpec, X, V, Xq, **fit):
    """One field over the region's lattice fitted on all the data at once ("auto": its
    evidence maximum): mean, std and known."""
    field = region_field(spec).fit(X, V, **fit)
    mean, std = field.predict(Xq, return_std=True)
    return mean, std, known(field.posterior_.data_weight(Xq))


def settle(client, name: str) -> None:
    """Wait for the region's settled map: "auto" at the evidence maximum itself (a refresh's
    first map after an upload may stop a nat short of it), which the library's fit equals."""
    r = client.post(f"/v1/regions/{name}/hyperparameters")
    assert r.status_code == 200, r.text


def arrow_table(columns: dict) -> bytes:
    return arrow_bytes({k: np.asarray(v, float) for k, v in columns.items()})


def parquet_table(columns: dict) -> bytes:
    buf = io.BytesIO()
    pq.write_table(pa.table({k: np.asarray(v, float) for k, v in columns.items()}), buf)
    return buf.getvalue()


def enu_columns(X, V):
    return dict(x=X[:, 0], y=X[:, 1], z=X[:, 2], ve=V[:, 0], vn=V[:, 1], vu=V[:, 2])


@pytest.fixture
def server(live_server, store_url):
    """A server on each store backend (SQLite, and PostgreSQL where configured)."""
    return live_server(env={"BDF_STORE_URL": store_url})


@pytest.fixture
def client(server):
    with httpx.Client(base_url=server.url, timeout=60) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        yield c


def test_chunked_uploads_in_three_formats_replay_and_query_equal_the_library(client, server):
    X, V = data(0, n=900)
    spec = RegionSpec.model_validate(SPEC)
    chunks = [
        (
            "application/json",
            json.dumps({"points": X[:300].tolist(), "velocities": V[:300].tolist()}).encode(),
        ),
        (ARROW, arrow_table(enu_columns(X[300:600], V[300:600]))),
        (PARQUET, parquet_table(enu_columns(X[600:], V[600:]))),
    ]
    versions = []
    for i, (media, body) in enumerate(chunks):
        r = client.post(
            f"/v1/regions/{NAME}/observations",
            content=body,
            headers={"Content-Type": media, "Idempotency-Key": f"chunk-{i}"},
        )
        assert r.status_code == 200, r.text
        assert r.json()["accepted"] == 300 and not r.json()["replayed"]
        versions.append(r.json()["region_version"])
    assert versions == [1, 2, 3]
    # a replayed chunk returns the first answer and changes nothing
    media, body = chunks[1]
    r = client.post(
        f"/v1/regions/{NAME}/observations",
        content=body,
        headers={"Content-Type": media, "Idempotency-Key": "chunk-1"},
    )
    assert r.json()["replayed"] and r.json()["region_version"] == 2
    info = client.get(f"/v1/regions/{NAME}").json()
    assert (info["version"], info["observations"], info["tiles"]) == (3, 900, 6)
    # the same key for other data is a conflict
    r = client.post(
        f"/v1/regions/{NAME}/observations",
        content=chunks[0][1],
        headers={"Content-Type": "application/json", "Idempotency-Key": "chunk-1"},
    )
    assert r.status_code == 409 and r.headers["content-type"] == "application/problem+json"

    Xq = np.random.default_rng(5).uniform([0, 0, 0], [300, 200, 60], (500, 3))
    settle(client, NAME)
    mean, std, known = library(spec, X, V, Xq)
    r = client.post(f"/v1/regions/{NAME}/query", json={"points": Xq.tolist()}, params={"min_version": 3})
    got = r.json()
    np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["std"], std, rtol=1e-6)
    assert got["known"] == known.tolist() and got["region_version"] == 3
    # Arrow in and out
    r = client.post(
        f"/v1/regions/{NAME}/query",
        content=arrow_table(dict(x=Xq[:, 0], y=Xq[:, 1], z=Xq[:, 2])),
        headers={"Content-Type": ARROW, "Accept": ARROW},
    )
    table = pa.ipc.open_stream(r.content).read_all()
    np.testing.assert_allclose(
        np.stack([table[c].to_numpy() for c in ("ve", "vn", "vu")], 1), mean, rtol=0, atol=1e-6
    )
    np.testing.assert_allclose(
        np.stack([table[c].to_numpy() for c in ("std_e", "std_n", "std_u")], 1), std, rtol=1e-6
    )

    # grid (npz) on the same lattice the library evaluates
    r = client.get(
        f"/v1/regions/{NAME}/grid",
        params={"bbox": "0,0,0,300,200,60", "step": "20,25,30"},
        headers={"Accept": NPZ},
    )
    assert r.status_code == 200 and r.headers["content-type"] == NPZ
    grid = np.load(io.BytesIO(r.content))
    axes = [np.arange(0, 301, 20.0), np.arange(0, 201, 25.0), np.arange(0, 61, 30.0)]
    for got_axis, axis in zip((grid["x"], grid["y"], grid["z"]), axes, strict=True):
        np.testing.assert_array_equal(got_axis, axis)
    mesh = np.stack([m.ravel() for m in np.meshgrid(*axes, indexing="ij")], 1)
    g_mean, g_std, _ = library(spec, X, V, mesh)
    shape = tuple(len(a) for a in axes)
    np.testing.assert_allclose(grid["mean"], g_mean.reshape(*shape, 3), rtol=0, atol=1e-6)
    np.testing.assert_allclose(grid["std"], g_std.reshape(*shape, 3), rtol=1e-6)
    # and exactly the same map's answer at those points (the library's own fit may settle
    # its "auto" hyperparameters a hair apart: the search stops within its tolerance)
    points = client.post(f"/v1/regions/{NAME}/query", json={"points": mesh.tolist()}).json()
    np.testing.assert_allclose(grid["mean"], np.reshape(points["mean"], (*shape, 3)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(grid["std"], np.reshape(points["std"], (*shape, 3)), rtol=1e-9)

    # tubes: exactly the voxels whose three stds are below the bound
    bound = float(np.quantile(g_std.max(1), 0.3))
    params = {"bbox": "0,0,0,300,200,60", "step": "20,25,30", "max_std_mps": bound}
    r = client.get(f"/v1/regions/{NAME}/tubes", params=params, headers={"Accept": NPZ})
    tube = np.load(io.BytesIO(r.content))
    expected = g_std.max(1) < bound
    assert 0 < expected.sum() < len(expected)
    np.testing.assert_array_equal(tube["mask"].ravel(), expected)
    np.testing.assert_allclose(tube["points"], mesh[expected])
    np.testing.assert_allclose(tube["mean"], g_mean[expected], rtol=0, atol=1e-6)
    r = client.get(f"/v1/regions/{NAME}/tubes", params=params)
    assert r.headers["content-type"] == GEOJSON
    features = r.json()["features"]
    assert len(features) == expected.sum()
    lat, lon, alt = spec.frame().to_geodetic(mesh[expected][:1])[0]
    np.testing.assert_allclose(features[0]["geometry"]["coordinates"], [lon, lat, alt], rtol=1e-12)
    # an empty tube says why, and the least bound that holds a voxel
    least = float(g_std.max(1).min())
    r = client.get(f"/v1/regions/{NAME}/tubes", params={**params, "max_std_mps": least / 2})
    assert (
        r.json()["features"] == []
        and f"least std among the grid's known voxels is {least:.3g}" in (r.json()["properties"]["note"])
    )
    # one named component: a superset of the all-component tube
    r = client.get(f"/v1/regions/{NAME}/tubes", params={**params, "component": "u"}, headers={"Accept": NPZ})
    np.testing.assert_array_equal(np.load(io.BytesIO(r.content))["mask"].ravel(), g_std[:, 2] < bound)

    tiles = client.get(f"/v1/regions/{NAME}/tiles").json()
    assert tiles["region_version"] == 3 and sum(t["points"] for t in tiles["tiles"]) == 900


def test_local_noise_regions_store_their_moments_and_serve_local_std(client):
    """Tiles keep local-noise moments in their stored blobs: chunked uploads, queries and
    grids equal the library's local-noise map, whose std differs from the global noise's."""
    body = {**SPEC, "name": "calm", "noise_spacing_m": [10, 10, 10], "noise_prior": 0.5}
    spec = RegionSpec.model_validate(body)
    assert client.post("/v1/regions", json=body).json()["spec"]["noise_spacing_m"] == [10, 10, 10]
    X, V = data(4, n=400)
    for i, part in enumerate(np.array_split(np.arange(len(X)), 2)):
        r = client.post(
            "/v1/regions/calm/observations",
            json={"points": X[part].tolist(), "velocities": V[part].tolist()},
            headers={"Idempotency-Key": f"calm-{i}"},
        )
        assert r.json()["accepted"] == len(part), r.text
    Xq = np.clip(X[:50] + 1.0, spec.lower, spec.upper)
    settle(client, "calm")
    got = client.post(
        "/v1/regions/calm/query", json={"points": Xq.tolist()}, params={"min_version": 2}
    ).json()
    mean, std, _ = library(spec, X, V, Xq)
    np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["std"], std, rtol=1e-6)
    _, global_std, _ = library(RegionSpec.model_validate({**SPEC, "name": "calm"}), X, V, Xq)
    assert np.abs(std / global_std - 1).max() > 0.1
    grid = client.get("/v1/regions/calm/grid", params={"step": "50,50,20"}, headers={"Accept": NPZ})
    with np.load(io.BytesIO(grid.content)) as npz:
        mesh = np.stack([m.ravel() for m in np.meshgrid(npz["x"], npz["y"], npz["z"], indexing="ij")], 1)
        _, grid_std, _ = library(spec, X, V, mesh)
        np.testing.assert_allclose(npz["std"].reshape(-1, 3), grid_std, rtol=1e-4)


def test_directional_regions_serve_the_mixture_of_the_library(client):
    """A region with heading sectors stores evidence per class in its tiles: chunked
    uploads, a replay, queries and grids equal the library's directional field at the
    hyperparameters in force (one row per class)."""
    body = {**SPEC, "name": "lanes", "directions": 4}
    spec = RegionSpec.model_validate(body)
    assert client.post("/v1/regions", json=body).json()["spec"]["directions"] == 4
    X, V = data(5, n=600)
    V[: len(V) // 2, :2] *= -8.0  # opposing traffic on half the points
    for i, part in enumerate(np.array_split(np.arange(len(X)), 2)):
        for _ in range(2):  # the second is a replay
            r = client.post(
                "/v1/regions/lanes/observations",
                json={"points": X[part].tolist(), "velocities": V[part].tolist()},
                headers={"Idempotency-Key": f"lanes-{i}"},
            )
            assert r.json()["accepted"] == len(part), r.text
    Xq = np.clip(X[:50] + 1.0, spec.lower, spec.upper)
    settle(client, "lanes")
    got = client.post(
        "/v1/regions/lanes/query", json={"points": Xq.tolist()}, params={"min_version": 2}
    ).json()
    region = client.get("/v1/regions/lanes").json()  # what the map of version 2 found
    assert region["version"] == 2 and np.shape(region["hyperparameters"]["alpha"]) == (6, 3)
    assert region["hyperparameters"]["evidence_version"] == 2
    mean, std, _ = library(spec, X, V, Xq)
    np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["std"], std, rtol=1e-6)
    one = region_field(spec.model_copy(update={"directions": 1, "model_directions": 1})).fit(X, V)
    assert np.abs(np.asarray(got["std"]) / one.predict(Xq, return_std=True)[1] - 1).max() > 0.1
    # the modes and the mode of a heading, in JSON and Arrow
    field = region_field(spec).fit(X, V)
    ref = field.predict_modes(Xq)
    heading = np.linspace(0, 350, len(Xq))
    got = client.post(
        "/v1/regions/lanes/query",
        json={"points": Xq.tolist(), "modes": True, "heading_deg": heading.tolist()},
    ).json()
    assert got["modes"]["heading_deg"] == [0.0, 90.0, 180.0, 270.0, None]
    np.testing.assert_allclose(got["modes"]["share"], ref.share, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.sum(got["modes"]["share"], axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["modes"]["share_std"], ref.share_std, rtol=1e-6)
    np.testing.assert_allclose(got["modes"]["mean"], ref.mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["modes"]["std"], ref.std, rtol=1e-6)
    # where a class has no data of its own within the kernel's reach, its mode is its prior
    np.testing.assert_array_equal(got["modes"]["prior_only"], ref.prior_only)
    assert 0 < np.sum(got["modes"]["prior_only"]) < ref.prior_only.size
    cond_mean, cond_std = field.predict(Xq, return_std=True, heading_deg=heading)
    np.testing.assert_allclose(got["mean"], cond_mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["std"], cond_std, rtol=1e-6)
    r = client.post(
        "/v1/regions/lanes/query",
        content=arrow_table({**dict(zip("xyz", Xq.T, strict=True)), "heading_deg": heading}),
        params={"modes": "true"},
        headers={"Content-Type": ARROW, "Accept": ARROW},
    )
    table = pa.ipc.open_stream(r.content).read_all()
    np.testing.assert_allclose(table.column("ve").to_numpy(), cond_mean[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(table.column("share2").to_numpy(), ref.share[:, 2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(table.column("mode4_std_u").to_numpy(), ref.std[:, 4, 2], rtol=1e-6)
    np.testing.assert_array_equal(
        table.column("prior_only4").to_numpy(zero_copy_only=False), ref.prior_only[:, 4]
    )
    # bad headings are the client's error, and nothing changes
    for bad in ([1.0, 2.0], "north"):
        r = client.post("/v1/regions/lanes/query", json={"points": Xq.tolist(), "heading_deg": bad})
        assert r.status_code == 422 and r.headers["content-type"] == "application/problem+json", r.text
    assert client.get("/v1/regions/lanes").json()["version"] == 2
    grid = client.get("/v1/regions/lanes/grid", params={"step": "50,50,20"}, headers={"Accept": NPZ})
    with np.load(io.BytesIO(grid.content)) as npz:
        mesh = np.stack([m.ravel() for m in np.meshgrid(npz["x"], npz["y"], npz["z"], indexing="ij")], 1)
        grid_mean, grid_std, _ = library(spec, X, V, mesh)
        np.testing.assert_allclose(npz["mean"].reshape(-1, 3), grid_mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(npz["std"].reshape(-1, 3), grid_std, rtol=1e-6)
    grid = client.get(
        "/v1/regions/lanes/grid", params={"step": "50,50,20", "modes": "true"}, headers={"Accept": NPZ}
    )
    with np.load(io.BytesIO(grid.content)) as npz:
        ref = field.predict_modes(mesh)
        np.testing.assert_allclose(npz["share"].reshape(-1, 5), ref.share, rtol=0, atol=1e-9)
        np.testing.assert_allclose(npz["mode_mean"].reshape(-1, 5, 3), ref.mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(npz["mode_std"].reshape(-1, 5, 3), ref.std, rtol=1e-6)
        noise = npz["mode_heading_noise"].reshape(-1, 5, 3)
        np.testing.assert_allclose(noise, ref.heading_noise, rtol=1e-6)
        assert (noise[:, :4] > 0).all() and (noise[:, 4] == 0).all()  # sectors' noise; none for slow
        np.testing.assert_array_equal(npz["heading_deg"][:4], [0, 90, 180, 270])
    r = client.get("/v1/regions/lanes/grid", params={"step": "50,50,20", "modes": "true"})
    assert r.status_code == 422 and "npz" in r.json()["detail"]
    # the directional tube: the mode flown (95 degrees: sectors 90 and 180 pooled), where its
    # share (pooled alike) is at least min_share
    params = {"step": "50,50,20", "max_std_mps": 5.0, "heading_deg": 95.0, "min_share": 0.2}
    tube = client.get("/v1/regions/lanes/tubes", params=params, headers={"Accept": NPZ})
    flown_mean, flown_std = ref.answer(spec.sectors, 95.0)
    flown_share = ref.heading_share(spec.sectors, 95.0)
    w = 1.0 - 5.0 / 90.0
    np.testing.assert_allclose(flown_share, w * ref.share[:, 1] + (1 - w) * ref.share[:, 2], rtol=1e-12)
    with np.load(io.BytesIO(tube.content)) as npz:
        mask = npz["mask"].ravel()
        expected = (flown_share >= 0.2) & (flown_std < 5.0).all(-1) & known(ref.weight)
        np.testing.assert_array_equal(mask, expected)
        assert 0 < mask.sum() < len(mask)
        np.testing.assert_allclose(npz["mean"], flown_mean[mask], rtol=0, atol=1e-6)


def test_a_new_region_chooses_its_sectors_and_answers_their_moments_until_then_from_16(client):
    """A spec that names no count is of ``directions: "auto"``: its uploads are split into
    16 sectors until a fit chooses, and it answers the mixture's moments (its modes if asked)."""
    body = {k: v for k, v in SPEC.items() if k != "directions"} | {"name": "new"}
    created = client.post("/v1/regions", json=body).json()["spec"]
    assert (created["directions"], created["model_directions"]) == ("auto", 16)
    spec = RegionSpec.model_validate(created)
    X, V = data(7, n=400)
    V[::2, :2] *= -1.0  # opposing traffic on half the points
    r = client.post(
        "/v1/regions/new/observations",
        json={"points": X.tolist(), "velocities": V.tolist()},
        headers={"Idempotency-Key": "new-0"},
    )
    assert r.json()["accepted"] == len(X), r.text
    settle(client, "new")
    got = client.post("/v1/regions/new/query", json={"points": X[:40].tolist()}).json()
    mean, std, _ = library(spec, X, V, X[:40])
    np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["std"], std, rtol=1e-6)
    assert "modes" not in got  # the columns a client of one class reads, unless it asks
    got = client.post("/v1/regions/new/query", json={"points": X[:40].tolist(), "modes": True}).json()
    assert len(got["modes"]["heading_deg"]) == 17 and np.shape(got["modes"]["share"]) == (40, 17)


def test_points_outside_the_region_are_answered_null_and_the_rest_as_alone(client):
    """A batch straying past the region's edge: those rows are null (JSON null, Arrow nulls,
    ``known`` false, counted), every other row is what the points inside alone get; a point
    not finite, or every point outside, is still a 422."""
    body = {**SPEC, "name": "edge", "directions": 4}
    client.post("/v1/regions", json=body)
    X, V = data(2, n=300)
    r = client.post(
        "/v1/regions/edge/observations",
        json={"points": X.tolist(), "velocities": V.tolist()},
        headers={"Idempotency-Key": "e"},
    )
    assert r.json()["accepted"] == 300
    inside = X[:5] + 1.0
    mixed = np.insert(inside, [1, 3], [[1e7, 0, 0], [0, 0, -1e3]], axis=0)  # rows 1 and 4 outside
    query = {"modes": True, "heading_deg": 30.0}
    alone = client.post("/v1/regions/edge/query", json={"points": inside.tolist(), **query}).json()
    r = client.post("/v1/regions/edge/query", json={"points": mixed.tolist(), **query})
    got = r.json()
    assert r.status_code == 200 and r.headers["X-Points-Outside"] == "2" and got["outside"] == 2
    assert got["mean"][1] is None and got["std"][4] is None and got["modes"]["share"][1] is None
    assert got["known"] == [alone["known"][0], False, *alone["known"][1:3], False, *alone["known"][3:]]
    keep = [0, 2, 3, 5, 6]
    assert [got["mean"][i] for i in keep] == alone["mean"] and [got["std"][i] for i in keep] == alone["std"]
    assert [got["modes"]["mean"][i] for i in keep] == alone["modes"]["mean"]
    r = client.post(
        "/v1/regions/edge/query",
        content=arrow_table(dict(zip("xyz", mixed.T, strict=True))),
        headers={"Content-Type": ARROW, "Accept": ARROW},
    )
    table = pa.ipc.open_stream(r.content).read_all()
    assert r.headers["X-Points-Outside"] == "2" and table.column("ve").null_count == 2
    assert table.column("ve").to_pylist()[1] is None and table.column("known").to_pylist()[4] is False
    plain = client.post("/v1/regions/edge/query", json={"points": inside.tolist()}).json()
    np.testing.assert_array_equal(table.column("ve").to_numpy()[keep], np.asarray(plain["mean"])[:, 0])
    for points, detail in (
        ([[0, 0, 0], [np.nan, 0, 0]], "rows [1]"),
        ([[1e7, 0, 0], [0, 0, -1e3]], "rows [0, 1]"),
    ):
        P = np.array(points, float)
        r = client.post(
            "/v1/regions/edge/query",
            content=arrow_table(dict(zip("xyz", P.T, strict=True))),
            headers={"Content-Type": ARROW},
        )
        assert r.status_code == 422 and detail in r.json()["detail"], r.text


def test_wgs84_bodies_equal_enu_bodies(client):
    X, V = data(1, n=300)
    spec = RegionSpec.model_validate(SPEC)
    frame = spec.frame()
    geo = frame.to_geodetic(X)
    # ADS-B style: velocities in each point's local axes; the service rotates them back
    to_local = np.linalg.inv(
        np.stack(
            [frame.rotate_velocity(geo[:, 0], geo[:, 1], np.tile(e, (len(geo), 1))) for e in np.eye(3)], -1
        )
    )
    V_local = np.einsum("nij,nj->ni", to_local, V)
    client.post("/v1/regions", json={**SPEC, "name": "geo"})
    r = client.post(
        "/v1/regions/geo/observations",
        json={"frame": "wgs84", "points": geo.tolist(), "velocities": V_local.tolist()},
        headers={"Idempotency-Key": "g"},
    )
    assert r.json()["accepted"] == 300
    client.post(
        f"/v1/regions/{NAME}/observations",
        json={"points": X.tolist(), "velocities": V.tolist()},
        headers={"Idempotency-Key": "e"},
    )
    Xq = X[:50] + 1.0
    a = client.post(f"/v1/regions/{NAME}/query", json={"points": Xq.tolist()}).json()
    b = client.post(
        "/v1/regions/geo/query", json={"frame": "wgs84", "points": frame.to_geodetic(Xq).tolist()}
    ).json()
    np.testing.assert_allclose(b["mean"], a["mean"], atol=1e-6)
    np.testing.assert_allclose(b["std"], a["std"], rtol=1e-6)


def test_rejected_rows_are_counted_and_never_stored(client):
    X, V = data(2, n=10)
    X[1, 0] = 1e6  # outside
    points, velocities = X.tolist(), V.tolist()
    velocities[2][1] = velocities[3][0] = None  # JSON's missing values; NaN is not JSON
    nan = client.post(
        f"/v1/regions/{NAME}/observations",
        content=json.dumps({"points": points, "velocities": [[np.nan, 0, 0], *velocities[1:]]}),
        headers={"Content-Type": "application/json", "Idempotency-Key": "nan"},
    )
    assert nan.status_code == 422 and "finite" in nan.json()["detail"]
    r = client.post(
        f"/v1/regions/{NAME}/observations",
        content=json.dumps({"points": points, "velocities": velocities}),
        headers={"Content-Type": "application/json", "Idempotency-Key": "bad-rows"},
    )
    assert r.json()["accepted"] == 7
    assert r.json()["rejected"] == {**NO_REJECTS, "non_finite": 2, "outside_region": 1}
    assert client.get(f"/v1/regions/{NAME}").json()["observations"] == 7


def test_etag_and_not_modified(client):
    X, V = data(3, n=200)
    body = {"points": X.tolist(), "velocities": V.tolist()}
    client.post(f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "1"})
    grid = (f"/v1/regions/{NAME}/grid", {"step": "50"})
    tubes = (f"/v1/regions/{NAME}/tubes", {"step": "50", "max_std_mps": 5})
    etags = {}
    for url, params in (grid, tubes):
        r = client.get(url, params=params, headers={"Accept": NPZ})
        etags[url] = r.headers["etag"]
        again = client.get(url, params=params, headers={"Accept": NPZ, "If-None-Match": r.headers["etag"]})
        assert again.status_code == 304 and again.content == b""
    assert etags[grid[0]] != etags[tubes[0]]  # an ETag names the request, not only the map
    other_box = {**grid[1], "bbox": "0,0,0,100,100,60"}
    r = client.get(grid[0], params=other_box, headers={"Accept": NPZ, "If-None-Match": etags[grid[0]]})
    assert r.status_code == 200 and r.headers["etag"] != etags[grid[0]]
    q = client.post(f"/v1/regions/{NAME}/query", json={"points": [[1, 1, 1]]})
    assert q.headers["etag"] != etags[grid[0]]
    r = client.post(
        f"/v1/regions/{NAME}/query",
        json={"points": [[1, 1, 1]]},
        headers={"If-None-Match": q.headers["etag"]},
    )
    assert r.status_code == 304
    r = client.post(
        f"/v1/regions/{NAME}/query",
        json={"points": [[2, 2, 2]]},
        headers={"If-None-Match": q.headers["etag"]},
    )
    assert r.status_code == 200 and r.json()["region_version"] == 1
    client.post(f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "2"})
    fresh = {**grid[1], "min_version": 2}  # read your write: not the previous map
    r = client.get(grid[0], params=fresh, headers={"Accept": NPZ, "If-None-Match": etags[grid[0]]})
    assert r.status_code == 200 and r.headers["etag"] != etags[grid[0]]


def test_small_fit_replaces_and_large_fit_runs_as_a_job(live_server):
    server = live_server(env={"BDF_FIT_JOB_POINTS": "500"})
    spec = RegionSpec.model_validate(SPEC)
    X, V = data(4, n=400)
    X2, V2 = data(5, n=3000)
    Xq = X[:40]
    with httpx.Client(base_url=server.url, timeout=60) as c:
        c.post("/v1/regions", json=SPEC)
        c.post(
            f"/v1/regions/{NAME}/observations",
            json={"points": X2[:100].tolist(), "velocities": V2[:100].tolist()},
            headers={"Idempotency-Key": "old"},
        )
        r = c.post(
            f"/v1/regions/{NAME}/fit",
            json={"points": X.tolist(), "velocities": V.tolist()},
            headers={"Idempotency-Key": "fit-1"},
        )
        assert r.status_code == 200 and r.json()["kind"] == "fit"
        assert c.get(f"/v1/regions/{NAME}").json()["observations"] == 400
        got = c.post(f"/v1/regions/{NAME}/query", json={"points": Xq.tolist()}).json()
        np.testing.assert_allclose(got["mean"], library(spec, X, V, Xq)[0], rtol=0, atol=1e-6)

        r = c.post(
            f"/v1/regions/{NAME}/fit",
            content=arrow_table(enu_columns(X2, V2)),
            headers={"Content-Type": ARROW, "Idempotency-Key": "fit-2"},
        )
        assert r.status_code == 202 and r.headers["location"] == f"/v1/jobs/{r.json()['id']}"
        seen = set()
        while True:
            # the old map answers until the new one commits: every answer is one of the two
            q = c.post(f"/v1/regions/{NAME}/query", json={"points": Xq.tolist()}).json()
            seen.add(q["region_version"])
            job = c.get(r.headers["location"]).json()
            if job["state"] in ("succeeded", "failed"):
                break
            time.sleep(0.02)
        assert job["state"] == "succeeded" and job["progress"] == 1.0, job
        assert job["result"]["accepted"] == 3000 and job["result"]["region_version"] == 3
        assert seen <= {2, 3}
        got = c.post(f"/v1/regions/{NAME}/query", json={"points": Xq.tolist()}).json()
        np.testing.assert_allclose(got["mean"], library(spec, X2, V2, Xq)[0], rtol=0, atol=1e-6)
        assert c.get("/v1/jobs/" + "0" * 32).status_code == 404


def test_a_fit_of_a_large_region_runs_as_a_job_whatever_its_rows(live_server):
    spec = RegionSpec.model_validate(SPEC)
    server = live_server(env={"BDF_FIT_JOB_HINGES": str(spec.grid.size - 1)})
    X, V = data(4, n=50)
    with httpx.Client(base_url=server.url, timeout=60) as c:
        c.post("/v1/regions", json=SPEC)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        r = c.post(f"/v1/regions/{NAME}/fit", json=body, headers={"Idempotency-Key": "big"})
        assert r.status_code == 202, r.text
        for _ in range(600):
            job = c.get(r.headers["location"]).json()
            if job["state"] in ("succeeded", "failed"):
                break
            time.sleep(0.05)
        assert job["state"] == "succeeded" and job["result"]["accepted"] == 50


def test_limits_and_errors_are_problem_json(live_server):
    server = live_server(
        env={
            "BDF_MAX_BODY_MB": "0.5",
            "BDF_MAX_POINTS": "1000",
            "BDF_MAX_GRID_VOXELS": "5000",
            "BDF_MAX_JSON_VOXELS": "100",
            "BDF_MAP_MEMORY_MB": "130",  # SPEC's map (one class: 125 MiB) fits, of "auto" (135) not
        }
    )
    with httpx.Client(base_url=server.url, timeout=60) as c:
        c.post("/v1/regions", json=SPEC)
        X, V = data(6, n=1001)
        obs = f"/v1/regions/{NAME}/observations"
        cases = [
            (c.post(obs, content=b"x" * (2**20), headers={"Idempotency-Key": "k"}), 413, "0.5 MiB"),
            (
                c.post(
                    obs,
                    content=arrow_table(enu_columns(X, V)),
                    headers={"Content-Type": ARROW, "Idempotency-Key": "k"},
                ),
                422,
                "limit is 1000",
            ),
            (c.post(obs, json={"points": [[0, 0, 0]], "velocities": [[0, 0, 0]]}), 422, "Idempotency-Key"),
            (
                c.post(obs, content=b"a,b", headers={"Content-Type": "text/csv", "Idempotency-Key": "k"}),
                415,
                "application/json",
            ),
            (
                c.post(obs, content=b"junk", headers={"Content-Type": ARROW, "Idempotency-Key": "k"}),
                400,
                "Arrow",
            ),
            (
                c.post(
                    obs,
                    content=arrow_table({"x": [1], "y": [1], "ve": [1], "vn": [1], "vu": [1]}),
                    headers={"Content-Type": ARROW, "Idempotency-Key": "k"},
                ),
                422,
                "columns",
            ),
            (
                c.post(obs, json={"points": [[0, 0, 0]], "velocities": []}, headers={"Idempotency-Key": "k"}),
                422,
                "velocities: List should have at least 1 item",
            ),
            (
                c.post(
                    "/v1/regions/nope/observations",
                    json={"points": [[0, 0, 0]], "velocities": [[0, 0, 0]]},
                    headers={"Idempotency-Key": "k"},
                ),
                404,
                "nope",
            ),
            (c.post(f"/v1/regions/{NAME}/query", json={"points": [[1e7, 0, 0]]}), 422, "outside region"),
            (  # latitude and longitude swapped: the region's in those terms, and the row as sent
                c.post(
                    f"/v1/regions/{NAME}/query",
                    json={"frame": "wgs84", "points": [[2.001, 48.0005, 20], [2.002, 48.0005, 20]]},
                ),
                422,
                "(latitude 48.00000 .. 48.00180, longitude 2.00000 .. 2.00402, altitude 0 .. 60 m near its "
                "origin; row 0 is [2.001, 48.0005, 20.0] (lat, lon, alt_m)): rows [0, 1]",
            ),
            (
                c.post(
                    f"/v1/regions/{NAME}/query", json={"points": [[0, 0, 0]]}, headers={"Accept": "text/html"}
                ),
                406,
                "available as",
            ),
            (
                c.get(f"/v1/regions/{NAME}/grid", params={"step": "1"}),
                422,
                "voxels ([301.0, 201.0, 61.0] per axis), more than 5000",
            ),
            (c.get(f"/v1/regions/{NAME}/grid", params={"step": "30"}), 422, "too many for JSON"),
            (
                c.get(f"/v1/regions/{NAME}/grid", params={"step": "30", "bbox": "0,0,0,1,1,1000"}),
                422,
                "leaves region",
            ),
            (c.get(f"/v1/regions/{NAME}/grid", params={"step": "-1"}), 422, "positive"),
            (c.get(f"/v1/regions/{NAME}/grid", params={"step": "a,b"}), 422, "comma-separated"),
            (
                c.get(f"/v1/regions/{NAME}/tubes", params={"step": "30", "max_std_mps": "-1"}),
                422,
                "max_std_mps",
            ),
            (
                c.post(
                    "/v1/regions", json={k: v for k, v in SPEC.items() if k != "directions"} | {"name": "a"}
                ),
                422,
                "more than this service's 130 MiB for one map: raise the spacing or gamma, or take fewer "
                '(model_)directions (of "auto", a fit may choose 32: name a count)',
            ),
            (c.get("/v1/regions/Bad%20Name"), 422, "must be 1 to 63 lowercase letters, digits, _ and -"),
            (c.post("/v1/regions", json={**SPEC, "name": "Paris"}), 422, "name: must be 1 to 63 lowercase"),
            (
                c.post("/v1/regions", json={**SPEC, "tile_size_m": [1, 1, 1]}),
                422,
                "more than 100000",
            ),
            (c.post("/v1/regions", json={**SPEC, "colour": "red"}), 422, "colour"),
            (c.post("/v1/regions", json=SPEC), 409, "exists"),
        ]
        for r, status, phrase in cases:
            assert r.status_code == status, (r.request.url, r.text)
            assert r.headers["content-type"] == "application/problem+json", r.request.url
            assert phrase in r.json()["detail"], (r.request.url, r.json())
        # nothing of it reached the map
        info = c.get(f"/v1/regions/{NAME}").json()
        assert (info["version"], info["observations"]) == (0, 0)


TOKENS = {f"tok-{s}-0123456789": [s] for s in ("read", "write", "admin")}


def test_every_route_declares_its_scope_and_enforces_it(live_server, tmp_path):
    """Walks all routes of the OpenAPI document: no token, a wrong token, each scope."""
    server = live_server(env={"BDF_TOKENS": json.dumps(TOKENS)})
    paths = create_app(Settings(store_url=f"sqlite:///{tmp_path / 'openapi'}")).openapi()["paths"]
    routes = [(m.upper(), p, op["x-scope"]) for p, verbs in paths.items() for m, op in verbs.items()]
    assert {scope for *_, scope in routes} == {"public", "read", "write", "admin"}
    assert len(routes) == 23
    fill = {
        "{name}": NAME,
        "{job_id}": "0" * 32,
        "{file}": "maplibre-gl.css",
        "{z}": "0",
        "{x}": "0",
        "{y}": "0",
    }
    with httpx.Client(base_url=server.url, timeout=60) as c:
        for method, path, scope in routes:
            url = path
            for k, v in fill.items():
                url = url.replace(k, v)
            attempts = {
                "none": {},
                "wrong": {"Authorization": "Bearer nope"},
                "basic": {"Authorization": "Basic tok-admin-0123456789"},
            }
            attempts.update(
                {s: {"Authorization": f"Bearer tok-{s}-0123456789"} for s in ("read", "write", "admin")}
            )
            for who, headers in attempts.items():
                status = c.request(method, url, headers=headers).status_code
                if scope == "public":
                    assert status == 200, (method, path, who, status)
                elif who == scope:
                    assert status not in (401, 403), (method, path, who, status)
                elif who in ("none", "wrong", "basic"):
                    assert status == 401, (method, path, who, status)
                else:
                    assert status == 403, (method, path, who, status)
    assert "tok-" not in server.log()  # tokens never reach the logs


def test_no_route_hands_a_request_to_a_worker_thread_before_its_work():
    """FastAPI runs a plain-function endpoint or dependency in a worker thread: a hand-off
    per request that costs more CPU than most of them. Every one is a coroutine; a route's
    work goes to its lane (:mod:`service.lanes`)."""

    def calls(dependant):
        yield dependant.call
        for dependency in dependant.dependencies:
            yield from calls(dependency)

    routes = [route for route in (*router.routes, *ops.routes) if isinstance(route, APIRoute)]
    assert len(routes) == 23  # every route of the OpenAPI document (the scope test's count)
    plain = {
        f"{route.path}: {call.__qualname__}"
        for route in routes
        for call in calls(route.dependant)
        if call is not None and not inspect.iscoroutinefunction(call)
    }
    assert plain == set()


def test_serve_refuses_a_public_address_without_tokens_and_warns_when_open(tmp_path, live_server):
    import subprocess
    import sys

    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "clients.cli",
            "serve",
            "--host",
            "0.0.0.0",
            "--data-dir",
            str(tmp_path / "d"),
        ],
        capture_output=True,
        text=True,
        env={"PATH": "/usr/bin:/bin"},
        timeout=60,
    )
    assert out.returncode == 2 and "refusing to listen on '0.0.0.0' without tokens" in out.stderr
    server = live_server()
    assert "OPEN" in server.log()
    with pytest.raises(ValueError, match="refusing"):
        Settings(host="10.1.2.3").check_bind()
    Settings(host="10.1.2.3", tokens={"t-0123456789abcdef": ["read"]}).check_bind()
    Settings(host="::1").check_bind()


def test_metrics_health_and_request_logs(client, server):
    X, V = data(7, n=100)
    client.post(
        f"/v1/regions/{NAME}/observations",
        json={"points": X.tolist(), "velocities": V.tolist()},
        headers={"Idempotency-Key": "m"},
    )
    for _ in range(3):  # the first waits for the map of version 1, the others find it
        client.post(f"/v1/regions/{NAME}/query", json={"points": X[:5].tolist()}, params={"min_version": 1})
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready"}
    text = client.get("/metrics").text
    metrics = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            metrics[name] = float(value)
    assert (
        metrics['bdf_http_requests_total{method="POST",route="/v1/regions/{name}/query",status="200"}'] == 3
    )
    assert (
        metrics['bdf_http_request_duration_seconds_count{method="POST",route="/v1/regions/{name}/query"}']
        == 3
    )
    assert metrics['bdf_uploads_applied_total{kind="observations"}'] == 1
    assert metrics['bdf_observations_total{outcome="accepted"}'] == 100
    assert metrics["bdf_posterior_cache_hits_total"] >= 2
    assert metrics["bdf_map_refreshes_total"] == 1 and metrics["bdf_map_refresh_seconds_total"] > 0
    assert metrics["bdf_answer_versions_behind_count"] == 3 and metrics["bdf_answer_versions_behind_sum"] == 0
    assert metrics['bdf_answer_seconds_behind_bucket{le="0.0"}'] == 3
    lines = [json.loads(line) for line in server.log().splitlines() if line.startswith("{")]
    queries = [line for line in lines if line["route"] == "/v1/regions/{name}/query"]
    assert len(queries) == 3 and all(
        q["status"] == 200 and q["region"] == NAME and q["ms"] > 0 for q in queries
    )


def test_a_client_gone_mid_body_is_its_fault_logged_in_one_line(client, server):
    """A client that closes its connection before its body arrives (a load generator
    stopping, a timeout) is a 400 in the logs and metrics, not a 500 with a traceback."""
    host, port = server.url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(
            f"POST /v1/regions/{NAME}/query HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            'Content-Length: 1000\r\n\r\n{"points": ['.encode()
        )
    deadline = time.monotonic() + 10
    while '"status": 400' not in server.log() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert "closed the connection before its request arrived" in server.log()
    assert "unhandled error" not in server.log() and "Traceback" not in server.log()
    metric = 'bdf_http_requests_total{method="POST",route="/v1/regions/{name}/query",status="400"} 1.0'
    assert metric in client.get("/metrics").text


def test_graceful_shutdown_finishes_an_upload_in_flight(live_server):
    """SIGTERM while an upload's body is still arriving: the upload completes and commits."""
    server = live_server()
    X, V = data(8, n=100_000)
    body = arrow_table(enu_columns(X, V))
    half_sent, result = threading.Event(), {}

    def slow_body():
        yield body[: len(body) // 2]
        half_sent.set()
        time.sleep(1.0)  # the server gets SIGTERM now, with this request in flight
        yield body[len(body) // 2 :]

    def upload():
        r = httpx.post(
            f"{server.url}/v1/regions/{NAME}/observations",
            content=slow_body(),
            headers={"Content-Type": ARROW, "Idempotency-Key": "big"},
            timeout=120,
        )
        result["status"], result["body"] = r.status_code, r.json()

    httpx.post(f"{server.url}/v1/regions", json=SPEC)
    thread = threading.Thread(target=upload)
    thread.start()
    assert half_sent.wait(30)
    time.sleep(0.2)
    assert server.stop() in (0, -15)  # uvicorn re-raises the signal once it has shut down
    thread.join(60)
    assert result["status"] == 200 and result["body"]["accepted"] == 100_000
    restarted = live_server()
    info = httpx.get(f"{restarted.url}/v1/regions/{NAME}").json()
    assert (info["version"], info["observations"]) == (1, 100_000)


def test_npz_bytes_are_what_numpy_writes():
    rng = np.random.default_rng(0)
    for arrays in (
        {"mean": rng.standard_normal((20, 10, 5, 3)), "known": rng.random((20, 10, 5)) > 0.5},
        {"x": np.arange(3.0)},  # far smaller than the headers' allowance: the buffer is cut back
    ):
        plain = io.BytesIO()
        np.savez(plain, **arrays)
        assert npz_bytes(**arrays) == plain.getvalue()


def test_arrow_body_is_what_pyarrow_writes():
    """The buffer sized from the schema and the record batch holds exactly the stream
    pyarrow writes unsized, with metadata, nulls, one row or none."""
    import pyarrow as pa

    rng = np.random.default_rng(0)
    columns = {
        "x": rng.standard_normal(1000),
        "known": rng.random(1000) > 0.5,
        "n": np.arange(1000),
        "v": pa.array(rng.standard_normal(1000), mask=rng.random(1000) > 0.9),
    }
    cases = [(columns, None), (columns, {"shape": "10,10,10"})]
    cases += [({name: values[:rows] for name, values in columns.items()}, None) for rows in (1, 0)]
    for columns, metadata in cases:
        batch = pa.record_batch(columns, metadata=metadata)
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, batch.schema) as writer:
            writer.write_batch(batch)
        assert bytes(arrow_body(columns, metadata)) == sink.getvalue().to_pybytes()
        assert arrow_bytes(columns, metadata) == sink.getvalue().to_pybytes()


def test_a_read_whose_map_is_not_ready_is_told_which_version_since_when_and_when_to_retry(
    tmp_path, monkeypatch
):
    """A map taking 3 s against a 2 s deadline: the read answers 503 before its deadline,
    naming the version being computed, since when and how long the last one took, with a
    Retry-After; never "nothing was stored". The retry, once the map is ready, gets it."""
    from fastapi.testclient import TestClient

    app = create_app(Settings(store_url=f"sqlite:///{tmp_path}", request_timeout_s=2.0))
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC).raise_for_status()
        X, V = data(1, n=200)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        c.post(
            f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "a"}
        ).raise_for_status()
        maps = app.state.service.maps
        assert maps.refresher.join(60)  # the first map, however long the machine takes
        c.post(f"/v1/regions/{NAME}/query?min_version=1", json={"points": X[:2].tolist()}).raise_for_status()
        compute = maps.refresher.posterior

        def slow(*args, **kw):
            threading.Event().wait(3.0)
            return compute(*args, **kw)

        monkeypatch.setattr(maps.refresher, "posterior", slow)
        c.post(
            f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "b"}
        ).raise_for_status()
        r = c.post(f"/v1/regions/{NAME}/query?min_version=2", json={"points": X[:2].tolist()})
        assert r.status_code == 503, r.text
        detail = r.json()["detail"]
        assert f"the map of region '{NAME}' at version 2 is computed since" in detail, detail
        assert "the last took" in detail and "stored" not in detail
        assert 1 <= int(r.headers["retry-after"]) <= 5
        time.sleep(int(r.headers["retry-after"]) + 1.5)
        again = c.post(f"/v1/regions/{NAME}/query?min_version=2", json={"points": X[:2].tolist()})
        assert again.status_code == 200 and again.json()["region_version"] == 2, again.text
