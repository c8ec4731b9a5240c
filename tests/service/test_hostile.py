"""Hostile input, row by row (RELIABILITY.md, "Hostile input"): each request gets its status,
and the stored statistics, the region version and a query answer are unchanged after it."""

import concurrent.futures
import contextlib
import io
import json
import socket
import subprocess
import sys
import tempfile
import threading

import numpy as np
import pyarrow as pa
import pyarrow.ipc
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

import service.maps
from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from bdf.sectors import AUTO_DIRECTIONS
from service import slices
from service.app import create_app
from service.maps import RegionMaps
from service.settings import Settings
from service.store import RegionExists, StoreUnavailable, open_store
from service.store.base import checksum, key_str
from service.wire import ARROW, NPZ, PARQUET
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # hostile clients against a server, property tests of whole maps

NAME = SPEC["name"]
TOKENS = {
    "read-0123456789abcdef": ["read"],
    "write-0123456789abcdef": ["read", "write"],
    "admin-0123456789abcdef": ["read", "write", "admin"],
}
READ, WRITE, ADMIN = ({"Authorization": f"Bearer {t}"} for t in TOKENS)
PROBE = np.array([[20.0, 30.0, 10.0], [150.0, 100.0, 30.0], [280.0, 180.0, 50.0]])


@pytest.fixture
def app(tmp_path):
    return create_app(
        Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=TOKENS, max_decoded_mb=8, max_json_mb=1)
    )


@pytest.fixture
def client(app):
    """The region ``town`` with 300 observations in 6 tiles (version 1)."""
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        X, V = data(1, n=300)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        c.post(f"/v1/regions/{NAME}/observations", json=body, headers={**WRITE, "Idempotency-Key": "a"})
        yield c


def state(c) -> dict:
    """What a hostile request must not change: the stored totals, a query's answer and the
    hyperparameters that version's map found (recorded once its map is computed)."""
    version = c.get(f"/v1/regions/{NAME}", headers=READ).json()["version"]
    # this version's settled map (its first may stop a nat short of the evidence maximum);
    # 422 where there is nothing to fit (no data yet)
    for _ in range(60):  # 503 while the map is computed, past a short deadline: retry
        settled = c.post(f"/v1/regions/{NAME}/hyperparameters", headers=WRITE)
        if settled.status_code != 503:
            break
        threading.Event().wait(0.5)
    assert settled.status_code in (200, 422), settled.text
    at = {"min_version": version}  # this version's map, not one before
    answer = c.post(
        f"/v1/regions/{NAME}/query", params=at, json={"points": PROBE.tolist()}, headers=READ
    ).json()
    view = c.get(f"/v1/regions/{NAME}", headers=READ).json()
    tiles = c.get(f"/v1/regions/{NAME}/tiles", headers=READ).json()["tiles"]
    return {
        "version": view["version"],
        "observations": view["observations"],
        "hyperparameters": view["hyperparameters"],
        "tiles": sorted((t["key"], t["version"], t["count"], t["points"]) for t in tiles),
        "mean": answer["mean"],
        "std": answer["std"],
    }


def problem(r, status: int, *phrases: str) -> None:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/problem+json"
    for phrase in phrases:
        assert phrase in r.json()["detail"], r.json()


def arrow_stream(table: pa.Table, compression=None) -> bytes:
    sink = pa.BufferOutputStream()
    options = pa.ipc.IpcWriteOptions(compression=compression)
    with pa.ipc.new_stream(sink, table.schema, options=options) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def rows(X, V, **extra) -> dict:
    return {"points": np.asarray(X).tolist(), "velocities": np.asarray(V).tolist(), **extra}


def post_obs(c, body, key, route="observations", headers=WRITE):
    return c.post(f"/v1/regions/{NAME}/{route}", json=body, headers={**headers, "Idempotency-Key": key})


# -- 1: a column type that crashed the decoder -------------------------------------------------
def test_row_01_an_interval_column_is_a_422_and_the_server_keeps_answering(live_server):
    import httpx

    server = live_server(env={"BDF_TOKENS": json.dumps(TOKENS)})
    with httpx.Client(base_url=server.url, timeout=60) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        interval = pa.array([pa.MonthDayNano([1, 2, 3])] * 3, pa.month_day_nano_interval())
        table = pa.table({"x": interval, "y": [1.0, 2.0, 3.0], "z": [1.0, 2.0, 3.0]})
        r = c.post(
            f"/v1/regions/{NAME}/query",
            content=arrow_stream(table),
            headers={**READ, "Content-Type": ARROW, "Accept": ARROW},
        )
        problem(r, 422, "'x'", "month_day_nano_interval")
        assert c.get("/healthz").status_code == 200
        assert (
            c.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ).status_code
            == 200
        )
    assert server.proc.poll() is None


# -- 2, 18: schemas: repeated, unknown and non-numeric columns ----------------------------------
@pytest.mark.parametrize(
    "columns, phrases",
    [
        ({"x": [1.0], "y": [1.0], "z": [1.0], "x ": [1.0]}, ("unknown", "'x '")),
        ({"x": [1.0], "y": [1.0], "z": [1.0], "colour": [1.0]}, ("unknown", "colour")),
        ({"x": pa.array([1], pa.timestamp("s")), "y": [1.0], "z": [1.0]}, ("'x'", "timestamp")),
        ({"x": [True], "y": [1.0], "z": [1.0]}, ("'x'", "bool")),
        ({"x": ["1.5"], "y": [1.0], "z": [1.0]}, ("'x'", "string")),
        ({"x": pa.array([1.0]).dictionary_encode(), "y": [1.0], "z": [1.0]}, ("'x'", "dictionary")),
    ],
)
def test_row_18_columns_are_numbers_with_documented_names(client, columns, phrases):
    before = state(client)
    body = arrow_stream(pa.table(columns))
    r = client.post(f"/v1/regions/{NAME}/query", content=body, headers={**READ, "Content-Type": ARROW})
    problem(r, 422, *phrases)
    assert state(client) == before


def test_row_02_a_repeated_column_is_a_422(client):
    before = state(client)
    schema = pa.schema([("x", pa.float64()), ("x", pa.float64()), ("y", pa.float64()), ("z", pa.float64())])
    table = pa.Table.from_arrays([pa.array([1.0])] * 4, schema=schema)
    r = client.post(
        f"/v1/regions/{NAME}/query", content=arrow_stream(table), headers={**READ, "Content-Type": ARROW}
    )
    problem(r, 422, "more than once", "'x'")
    assert state(client) == before


def test_row_18_json_numbers_are_numbers(client):
    before = state(client)
    X, V = data(2, n=3)
    for bad in ("1.5", True, "NaN"):
        body = rows(X, V)
        body["velocities"][0][0] = bad
        problem(post_obs(client, body, f"json-{bad}"), 422, "velocities.0.0")
    text = json.dumps(rows(X, V)).replace(str(V[0, 0]), "1e400", 1)
    r = client.post(
        f"/v1/regions/{NAME}/observations",
        content=text,
        headers={**WRITE, "Idempotency-Key": "inf", "Content-Type": "application/json"},
    )
    problem(r, 422, "finite")
    assert state(client) == before


# -- 3, 4: implausible rows never reach the statistics -----------------------------------------
@pytest.mark.parametrize(
    "velocity, extra, reason",
    [
        ([1e155, 0, 0], {}, "implausible_speed"),
        ([1e20, 0, 0], {}, "implausible_speed"),
        ([0, 0, 150], {}, "implausible_speed"),
        ([10, 0, 0], {"sample_weight": [1e300]}, "implausible_weight"),
        ([10, 0, 0], {"sample_weight": [0.0]}, "implausible_weight"),
        ([10, 0, 0], {"sample_weight": [1e-300]}, "implausible_weight"),
        ([10, 0, 0], {"input_noise_std": [1e9]}, "implausible_noise"),
    ],
)
def test_rows_03_04_implausible_rows_are_rejected_and_counted(app, client, velocity, extra, reason):
    before = state(client)
    problem(post_obs(client, rows([[10.0, 10.0, 10.0]], [velocity], **extra), "one"), 422, f"1 {reason}")
    assert state(client) == before
    X, V = data(3, n=20)
    V[0] = velocity
    extra = {
        k: [v[0]] + [1.0] * 19 if k == "sample_weight" else [v[0]] + [0.0] * 19 for k, v in extra.items()
    }
    r = post_obs(client, rows(X, V, **extra), "mixed")
    assert r.status_code == 200 and r.json()["accepted"] == 19 and r.json()["rejected"][reason] == 1
    h = client.post(f"/v1/regions/{NAME}/hyperparameters", headers=WRITE)
    assert h.status_code == 200, h.text
    answer = client.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ).json()
    assert np.all(np.abs(answer["mean"]) < 50) and np.all(np.array(answer["std"]) > 0.01)
    # a fresh process computes the same map from the store
    fresh = create_app(app.state.service.settings)
    with TestClient(fresh, raise_server_exceptions=False) as c:
        again = c.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ)
        assert again.status_code == 200
        np.testing.assert_allclose(again.json()["mean"], answer["mean"], atol=1e-9)


# -- 5, 6: nothing accepted, nothing stored -----------------------------------------------------
@pytest.mark.parametrize("route", ["fit", "observations"])
def test_rows_05_06_a_request_with_no_accepted_row_changes_nothing(client, route):
    before = state(client)
    assert before["observations"] == 300 and len(before["tiles"]) == 6
    body = rows([[10.0, 10.0, 10.0]], [[1.0, 1.0, None]])
    problem(post_obs(client, body, "none", route), 422, "no row", "1 non_finite", "nothing was stored")
    assert state(client) == before


# -- 7: a region deleted and re-created while a write runs --------------------------------------
@pytest.mark.parametrize("spacing", [[25, 25, 20], [30, 30, 20]])
def test_row_07_a_write_to_a_region_recreated_meanwhile_is_a_409(client, app, monkeypatch, spacing):
    evidence = service.maps.accepted_rows_increments
    new_spec = {**SPEC, "spacing_m": spacing}

    def recreate_then(*args, **kw):
        out = evidence(*args, **kw)
        app.state.service.maps.store.delete_region(NAME)
        app.state.service.maps.store.create_region(RegionSpec.model_validate(new_spec))
        return out

    monkeypatch.setattr(service.maps, "accepted_rows_increments", recreate_then)
    X, V = data(4, n=50)
    problem(post_obs(client, rows(X, V), "racing"), 409, "re-created", "nothing was stored")
    monkeypatch.setattr(service.maps, "accepted_rows_increments", evidence)
    view = client.get(f"/v1/regions/{NAME}", headers=READ).json()
    assert view["version"] == 0 and view["observations"] == 0 and view["tiles"] == 0
    assert app.state.service.maps.store.verify() == {NAME: []}
    q = client.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ)
    assert q.status_code == 200 and q.json()["known"] == [False] * 3


def test_row_07_a_hyperparameter_fit_of_a_region_recreated_meanwhile_is_a_409(client, app, monkeypatch):
    posterior = app.state.service.maps.refresher.posterior

    def recreate_then(*args, **kw):
        out = posterior(*args, **kw)
        app.state.service.maps.store.delete_region(NAME)
        app.state.service.maps.store.create_region(RegionSpec.model_validate(SPEC))
        return out

    # no refresh of version 2
    monkeypatch.setattr(app.state.service.maps.refresher, "schedule", lambda region, version=0: None)
    assert post_obs(client, rows(*data(8, n=20)), "b").status_code == 200
    monkeypatch.setattr(app.state.service.maps.refresher, "posterior", recreate_then)
    problem(client.post(f"/v1/regions/{NAME}/hyperparameters", headers=WRITE), 409, "re-created")
    view = client.get(f"/v1/regions/{NAME}", headers=READ).json()
    assert view["version"] == 0 and view["hyperparameters"]["fitted_at"] is None


# -- 8: specs that could not be served ----------------------------------------------------------
@pytest.mark.parametrize(
    "change, phrase",
    [
        ({"gamma": [5e-324] * 3}, "reach"),
        ({"bounds_m": {"min": [0, 0, 0], "max": [1e16, 1e16, 1e16]}, "spacing_m": [1e308] * 3}, "within"),
        ({"spacing_m": [1000, 25, 20]}, "must not exceed the box"),
        ({"gamma": [10.0, 10.0, 10.0]}, "at least the spacing"),
        ({"gamma": [3e-4] * 3, "bounds_m": {"min": [0, 0, 0], "max": [600, 600, 200]}}, "offsets"),
    ],
)
def test_row_08_a_spec_that_cannot_be_served_is_a_422(client, change, phrase):
    problem(client.post("/v1/regions", json={**SPEC, "name": "other", **change}, headers=ADMIN), 422, phrase)
    assert [r["spec"]["name"] for r in client.get("/v1/regions", headers=READ).json()] == [NAME]


# -- 9: concurrent creates of one name ----------------------------------------------------------
def test_row_09_concurrent_creates_of_one_name_give_one_region_and_409s(store_url):
    stores = [open_store(store_url) for _ in range(6)]
    spec = RegionSpec.model_validate(SPEC)

    def create(store):
        try:
            return store.create_region(spec).region_id
        except RegionExists:
            return "exists"

    try:
        with concurrent.futures.ThreadPoolExecutor(6) as pool:
            outcomes = list(pool.map(create, stores))
        assert outcomes.count("exists") == 5
        assert stores[0].region(NAME).region_id in outcomes
    finally:
        for s in stores:
            s.close()


# -- 10, 11: the body is read after the token, and bounded while it streams ---------------------
def test_row_10_a_region_body_without_a_token_is_refused_before_it_is_read(live_server):
    server = live_server(env={"BDF_TOKENS": json.dumps(TOKENS)})
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(
            b"POST /v1/regions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 100000000\r\n\r\n{"
        )
        head = sock.recv(4096)  # answered with 99.99 MB of the body never sent
    assert head.startswith(b"HTTP/1.1 401"), head


def test_row_11_a_chunked_body_over_the_limit_is_a_413(tmp_path):
    app = create_app(Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=TOKENS, max_body_mb=0.01))

    def chunks():
        for _ in range(100):
            yield b" " * 1024

    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.post("/v1/regions", content=chunks(), headers={**ADMIN, "Content-Type": "application/json"})
        problem(r, 413, "limit")
        assert c.get("/v1/regions", headers=READ).json() == []


# -- 12: bodies that decode into far more than they weigh ---------------------------------------
def test_row_12_rows_and_decoded_size_are_checked_before_decoding(client):
    before = state(client)
    zeros = np.zeros(1_000_000)
    table = pa.table({c: zeros for c in ("x", "y", "z", "ve", "vn", "vu")})
    body = arrow_stream(table, "zstd")
    assert len(body) < 100_000  # 48 MB of columns in a few kB
    pool = pa.proxy_memory_pool(pa.default_memory_pool())
    previous = pa.default_memory_pool()
    pa.set_memory_pool(pool)
    try:
        r = client.post(
            f"/v1/regions/{NAME}/observations",
            content=body,
            headers={**WRITE, "Content-Type": ARROW, "Idempotency-Key": "zip"},
        )
    finally:
        pa.set_memory_pool(previous)
    problem(r, 413, "decodes into 45.8 MiB", "limit is 8 MiB")
    assert pool.max_memory() < 2**20  # refused from the metadata: no column was decoded
    parquet = io.BytesIO()
    pq.write_table(
        pa.table({c: np.zeros(3_000_000) for c in table.column_names}), parquet, compression="zstd"
    )
    r = client.post(
        f"/v1/regions/{NAME}/observations",
        content=parquet.getvalue(),
        headers={**WRITE, "Content-Type": PARQUET, "Idempotency-Key": "pq"},
    )
    problem(r, 422, "3000000 rows", "limit is 2000000")
    big_json = b'{"points": [' + b"[1, 1, 1]," * 200_000 + b"[1, 1, 1]]}"
    r = client.post(
        f"/v1/regions/{NAME}/query", content=big_json, headers={**READ, "Content-Type": "application/json"}
    )
    problem(r, 413, "JSON body", ARROW)
    assert state(client) == before


def test_row_12_a_batch_that_lies_about_its_buffers_is_refused(client):
    """A compressed buffer's declared length (its first 8 bytes) is what gets allocated."""
    table = pa.table({"x": np.zeros(1000), "y": np.zeros(1000), "z": np.zeros(1000)})
    body = bytearray(arrow_stream(table, "lz4"))
    marker = (8000).to_bytes(8, "little")
    at = body.index(marker)
    body[at : at + 8] = (2**40).to_bytes(8, "little")  # "this buffer decodes into 1 TiB"
    r = client.post(f"/v1/regions/{NAME}/query", content=bytes(body), headers={**READ, "Content-Type": ARROW})
    problem(r, 413, "decodes into")


# -- 13: tokens ---------------------------------------------------------------------------------
@pytest.mark.parametrize("tokens", [{"": ["admin"]}, {"short": ["read"]}, {"   padded-short  ": ["read"]}])
def test_row_13_empty_or_short_tokens_are_refused_at_startup(tokens):
    with pytest.raises(ValueError, match="shorter than 16"):
        Settings(tokens=tokens)


def test_row_13_an_empty_bearer_never_matches(client):
    for header in ("Bearer", "Bearer ", "Bearer    "):
        problem(client.get("/v1/regions", headers={"Authorization": header}), 401, "bearer token")


# -- 14: parameters are finite before use -------------------------------------------------------
def test_row_14_parameters_are_validated_finite(client):
    before = state(client)
    r = client.get(
        f"/v1/regions/{NAME}/tubes",
        params={"max_std_mps": "inf", "step": "50"},
        headers={**READ, "Accept": NPZ},
    )
    problem(r, 422, "max_std_mps")
    problem(
        client.get(f"/v1/regions/{NAME}/slice.png", params={"alt_m": "4.1e16"}, headers=READ), 422, "alt_m"
    )
    problem(client.get(f"/v1/regions/{NAME}/slice.png", params={"alt_m": "nan"}, headers=READ), 422, "alt_m")
    r = client.get(f"/v1/regions/{NAME}/grid", params={"step": "1e-300"}, headers={**READ, "Accept": NPZ})
    problem(r, 422, "step: must be 1 or 3 comma-separated positive numbers")
    r = client.get(f"/v1/regions/{NAME}/grid", params={"step": "1e-90"}, headers={**READ, "Accept": NPZ})
    problem(r, 422, "voxels")
    assert state(client) == before


# -- 15: ETags name the request -----------------------------------------------------------------
def test_row_15_an_etag_names_the_request(client):
    first = client.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ)
    etag = {"If-None-Match": first.headers["etag"]}
    same = client.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers={**READ, **etag})
    assert same.status_code == 304
    other = client.post(
        f"/v1/regions/{NAME}/query", json={"points": PROBE[:1].tolist()}, headers={**READ, **etag}
    )
    assert other.status_code == 200 and len(other.json()["mean"]) == 1
    junk = client.post(
        f"/v1/regions/{NAME}/query",
        content=b"not json",
        headers={**READ, **etag, "Content-Type": "application/json"},
    )
    assert junk.status_code == 422
    grid = client.get(f"/v1/regions/{NAME}/grid", params={"step": "50"}, headers={**READ, "Accept": NPZ})
    g_etag = {"If-None-Match": grid.headers["etag"]}
    box = {"step": "50", "bbox": "0,0,0,100,100,60"}
    assert (
        client.get(
            f"/v1/regions/{NAME}/grid", params=box, headers={**READ, "Accept": NPZ, **g_etag}
        ).status_code
        == 200
    )
    arrow = client.get(
        f"/v1/regions/{NAME}/grid", params={"step": "50"}, headers={**READ, "Accept": ARROW, **g_etag}
    )
    assert arrow.status_code == 200 and arrow.headers["content-type"] == ARROW


# -- 16: errors say what to do, not where the database lives ------------------------------------
def test_row_16_unavailable_details_do_not_name_the_database(client, app, monkeypatch):
    def down(*args, **kw):
        raise StoreUnavailable(
            'connection to server at "10.0.0.7", port 5432 failed: /var/run/postgresql/.s.PGSQL.5432'
        )

    monkeypatch.setattr(app.state.service.maps.store, "region", down)
    r = client.get(f"/v1/regions/{NAME}", headers=READ)
    problem(r, 503, "retry")
    assert (
        not any(s in r.text for s in ("10.0.0.7", "5432", "/var/run")) and int(r.headers["retry-after"]) > 0
    )


def test_row_16_an_internal_numeric_failure_is_a_500_with_a_request_id(client, app, monkeypatch):
    def singular(*args, **kw):
        raise ValueError("the precision is not positive definite: increase alpha")

    monkeypatch.setattr(app.state.service.maps, "predict", singular)
    r = client.post(f"/v1/regions/{NAME}/query", json={"points": PROBE.tolist()}, headers=READ)
    problem(r, 500, "request id")
    assert r.json()["request_id"] == r.headers["x-request-id"] and "alpha" not in r.text


# -- 17: bdf verify ------------------------------------------------------------------------------
def verify(data_dir) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "clients.cli", "verify", "--data-dir", str(data_dir)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def test_row_17_verify_reports_implausible_statistics_and_a_file_that_is_no_store(tmp_path):
    store = open_store(f"sqlite:///{tmp_path / 'data'}")
    loose = {**SPEC, "envelope": {"max_horizontal_speed_mps": 1e30, "max_sample_weight": 1e6}}
    spec = RegionSpec.model_validate(SPEC)
    region_id = store.create_region(spec).region_id
    X, V = data(5, n=30)
    V[0, 0] = 1e20  # what an older server accepted, written past today's envelope
    tile_increments = increments(RegionSpec.model_validate(loose), X, V)
    store.apply(NAME, region_id, "old", "digest", tile_increments, observations=30)
    store.close()
    done = verify(tmp_path / "data")
    assert done.returncode == 1 and "beyond the envelope" in done.stdout and "1 problems" in done.stdout
    (tmp_path / "junk").mkdir()
    db = (tmp_path / "data" / "maps.sqlite3").read_bytes()
    (tmp_path / "junk" / "maps.sqlite3").write_bytes(db[: len(db) // 3])
    done = verify(tmp_path / "junk")
    assert done.returncode == 1 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "not a bdf store, or is damaged" in done.stderr


# -- properties: no accepted row can break a map; every accepted spec can be served ------------
#: seeded and unshrunk: a failure is reported as drawn (each example costs a posterior)
PROPERTY = settings(
    derandomize=True,
    deadline=None,
    phases=(Phase.explicit, Phase.reuse, Phase.generate),
    suppress_health_check=list(HealthCheck),
)
EDGE_SPEEDS = [0.0, 1e-9, 50.0, 282.84, 399.99]
extreme_rows = st.lists(
    st.tuples(
        st.tuples(*(st.sampled_from([0.0, 1e-9, hi / 2, hi]) for hi in (300.0, 200.0, 60.0))),
        st.tuples(
            st.sampled_from(EDGE_SPEEDS), st.sampled_from([-1.0, 1.0]), st.sampled_from([0.0, -100.0, 100.0])
        ),
        st.sampled_from([1e-6, 1e-3, 1.0, 1000.0]),  # sample weight
        st.sampled_from([0.0, 1e-3, 30.0, 1000.0]),  # input noise std
    ),
    min_size=1,
    max_size=12,
)


def _arrays(batch):
    X = np.array([r[0] for r in batch])
    speed, sign, vu = (np.array([r[1][i] for r in batch]) for i in range(3))
    # the horizontal speed split between east and north, within the envelope
    V = np.stack([sign * speed / np.sqrt(2), speed / np.sqrt(2), vu], axis=1)
    return X, V, np.array([r[2] for r in batch]), np.array([r[3] for r in batch])


@settings(PROPERTY, max_examples=20)
@given(
    uploads=st.lists(extreme_rows, min_size=1, max_size=4),
    directions=st.sampled_from([1, 4]),
    hyper=st.sampled_from([{}, {"alpha": 1.0}, {"alpha": 0.01, "beta": 100.0}]),  # auto, the paper's
)
def test_no_accepted_rows_in_any_order_can_break_a_map(uploads, directions, hyper):
    with tempfile.TemporaryDirectory() as tmp:
        store = open_store(f"sqlite:///{tmp}")
        try:
            spec = RegionSpec.model_validate({**SPEC, "directions": directions, **hyper})
            store.create_region(spec)
            maps = RegionMaps(store)
            for i, batch in enumerate(uploads):
                X, V, weight, noise = _arrays(batch)
                result = maps.upload(NAME, f"u{i}", X, V, sample_weight=weight, input_noise_std=noise)
                assert result["accepted"] == len(X)  # every row is inside the envelope
            served = assert_serves(maps, spec)
            if spec.auto:
                maps.fit_hyperparameters(NAME)
                served = assert_serves(maps, spec)
            fresh = RegionMaps(store)  # what a new process computes from the store
            again = assert_serves(fresh, spec)
            # at fixed values, the same map ("auto": the maximum found again, still finite)
            if not fresh.refresh(NAME).posterior.fitted:
                np.testing.assert_allclose(again, served, rtol=1e-7, atol=1e-9)
            assert store.verify() == {NAME: []}
        finally:
            store.close()


def assert_serves(maps: RegionMaps, spec: RegionSpec) -> np.ndarray:
    """Points, modes and a grid of the region's map are finite, with positive std."""
    X = np.concatenate([PROBE, spec.lower[None], spec.upper[None]]) if spec.name == NAME else spec.lower[None]
    X = np.clip(X, spec.lower, spec.upper)
    version = maps.store.region(spec.name).version  # this version's map, not one before
    pred = maps.predict(spec.name, X, min_version=version, modes=True)
    for a in (pred.mean, pred.std, pred.modes.share, pred.modes.mean, pred.modes.std):
        assert np.isfinite(a).all()
    assert (pred.std > 0).all()
    axes = [np.linspace(lo, hi, 3) for lo, hi in zip(spec.lower, spec.upper, strict=True)]
    grid = maps.predict_grid(spec.name, axes, min_version=version)
    assert np.isfinite(grid.mean).all() and (grid.std > 0).all()
    return np.concatenate([pred.mean.ravel(), pred.std.ravel()])


specs = st.builds(
    lambda extent, hinges, reach, tiles, cutoff, directions, corner: {
        "name": "prop",
        "origin": {"lat": 48.0, "lon": 2.0},
        "bounds_m": {"min": corner, "max": [c + e for c, e in zip(corner, extent, strict=True)]},
        "tile_size_m": [e / t for e, t in zip(extent, tiles, strict=True)],
        "spacing_m": [e / h for e, h in zip(extent, hinges, strict=True)],
        # the kernel's reach at the cutoff, in spacings (below one: refused)
        "gamma": [
            np.log(1 / cutoff) / (e / h * r) ** 2 for e, h, r in zip(extent, hinges, reach, strict=True)
        ],
        "cutoff": cutoff,
        "directions": directions,
    },
    extent=st.tuples(*[st.floats(50.0, 1e5)] * 3),
    hinges=st.tuples(*[st.floats(0.5, 12.0)] * 3),  # spacings per side (below 1: refused)
    reach=st.tuples(*[st.floats(0.3, 4.0)] * 3),
    tiles=st.tuples(*[st.floats(0.5, 6.0)] * 3),
    cutoff=st.sampled_from([1e-12, 1e-9, 1e-6]),
    directions=st.sampled_from([1, 8, 32, "auto"]),
    corner=st.tuples(*[st.floats(-5e5, 5e5)] * 3),
)


@settings(PROPERTY, max_examples=30)
@given(body=specs)
def test_every_accepted_spec_takes_an_upload_and_answers_a_query_a_grid_and_a_slice(body):
    try:
        spec = RegionSpec.model_validate(body)
    except ValueError:
        assume(False)  # refused with a reason (the 422s above); accepted ones must be served
    # small maps here (a second each: a factor per class); the largest a spec may have is
    # bounded by MAX_COUPLINGS, and what it costs is the isolation issue's memory budget
    assume(spec.couplings * spec.fit_classes <= 1e7)
    assume(np.prod(spec.tile_counts) <= 1000)
    with tempfile.TemporaryDirectory() as tmp:
        store = open_store(f"sqlite:///{tmp}")
        try:
            store.create_region(spec)
            maps = RegionMaps(store)
            rng = np.random.default_rng(0)
            X = rng.uniform(spec.lower, spec.upper, (50, 3))
            V = rng.uniform(-50, 50, (50, 3))
            assert maps.upload(spec.name, "u", X, V)["accepted"] == 50
            assert_serves(maps, spec)
            if spec.directions == "auto":  # a fit chooses the sectors (rows: 50 groups)
                assert maps.upload(spec.name, "f", X, V, replace=True)["accepted"] == 50
                spec = maps.store.region(spec.name).spec
                assert spec.directions_scores is not None and spec.model_directions in AUTO_DIRECTIONS
                assert_serves(maps, spec)
            x, y = slices.slice_axes(spec.lower, spec.upper, spec.spacing_m, None, None)
            cut = maps.predict_grid(
                spec.name, [x, y, spec.lower[2:]], min_version=maps.store.region(spec.name).version
            )
            assert np.isfinite(cut.mean).all()
        finally:
            store.close()


def test_a_retraction_over_http_needs_admin_and_is_counted(client):
    before = state(client)
    X, V = data(6, n=40)
    post_obs(client, rows(X, V), "broken").raise_for_status()
    assert state(client)["version"] == before["version"] + 1
    problem(post_obs(client, rows(X, V), "broken", "retractions"), 403, "admin")
    done = post_obs(client, rows(X, V), "broken", "retractions", headers=ADMIN)
    assert done.status_code == 200 and (done.json()["kind"], done.json()["accepted"]) == ("retraction", 40)
    after = state(client)
    assert after["observations"] == before["observations"] and after["tiles"] != before["tiles"]
    np.testing.assert_allclose(after["mean"], before["mean"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(after["std"], before["std"], rtol=1e-8)  # 8 modes searched from other starts
    metrics = client.get("/metrics").text
    assert 'bdf_observations_total{outcome="retracted"} 40.0' in metrics
    assert 'bdf_uploads_applied_total{kind="retraction"} 1.0' in metrics


# -- 19-21: route assessment within its budget, its input a 4xx ------------------------------------
WIDE = {
    "name": "wide",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [20_000, 20_000, 1000]},
    "tile_size_m": [10_000, 10_000, 1000],
    "spacing_m": [2000, 2000, 500],
    "gamma": [1 / 2000**2, 1 / 2000**2, 1 / 500**2],
}
VEHICLE = {
    "cruise_mps": 60.0,
    "min_turn_radius_m": 800.0,
    "max_climb_deg": 8.0,
    "max_descent_deg": 8.0,
    "floor_m": 0.0,
    "ceiling_m": 1000.0,
}


def assess(c, body, region="wide", media="application/json"):
    content = body if isinstance(body, bytes) else json.dumps(body).encode()
    return c.post(
        f"/v1/regions/{region}/routes/assess", content=content, headers={**READ, "Content-Type": media}
    )


@pytest.fixture
def wide(client):
    """The region ``town`` (version 1) and the empty 20 km region ``wide``."""
    client.post("/v1/regions", json=WIDE, headers=ADMIN).raise_for_status()
    return client


def test_row_19_a_vehicle_turning_on_a_coin_is_judged_at_metre_samples(wide):
    """Radius 0.01 m on a 20 km route sampled every 0.8 mm took 3.5 GB and 33 s: the envelope
    is sampled every metre at the finest (20,001 samples), and the corner judged flyable."""
    before = state(wide)
    route = {
        "points": [[0, 0, 500], [10_000, 0, 500], [10_000, 10_000, 500]],
        "max_std_mps": 5,
        "vehicle": {**VEHICLE, "min_turn_radius_m": 0.01},
    }
    r = assess(wide, route)
    assert r.status_code == 200, r.text
    verdict = r.json()["envelope"]
    assert verdict["turn_ok"] and verdict["min_turn_radius_m"] == pytest.approx(3 / np.sqrt(2), rel=0.01)
    assert state(wide) == before


def test_row_20_a_route_longer_than_a_query_is_refused_before_work_and_stops_at_its_deadline(wide, app):
    """A 5,000-vertex zig-zag across 20 km (100,000 km, 10 M samples) is a 422 before any
    work; a route within the limit that runs past its deadline stops within a chunk."""
    before = state(wide)
    zigzag = [[0 if i % 2 else 20_000, 4 * i, 500] for i in range(5000)]
    r = assess(wide, {"points": zigzag, "max_std_mps": 5, "vehicle": VEHICLE})
    problem(r, 422, "9.998e+04 km", "10002999 samples on the map", "more than the 200000", "shorter parts")
    assert state(wide) == before


def test_row_20_an_assessment_past_its_deadline_stops_within_a_chunk(tmp_path, monkeypatch):
    """50 legs of 20 km: 100,000 samples on the map, 25 chunks; each chunk held 0.2 s, the
    deadline 1 s: the 503 comes at the deadline and the thread reads a few chunks more at
    most, not the 25 (it held a lane's thread 58 s past its deadline)."""
    import bdf.region.route

    settings = Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=TOKENS, request_timeout_s=1.0)
    app = create_app(settings)
    chunks, read = [], bdf.region.route._read

    def slow_read(*args):
        chunks.append(1)
        threading.Event().wait(0.2)
        return read(*args)

    monkeypatch.setattr(bdf.region.route, "_read", slow_read)
    zigzag = [[0 if i % 2 else 20_000, 400 * i, 500] for i in range(51)]
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=WIDE, headers=ADMIN).raise_for_status()
        short = {"points": zigzag[:2], "max_std_mps": 5, "vehicle": VEHICLE}
        for _ in range(60):  # the region's map first (503 while it is computed)
            if assess(c, short).status_code == 200:
                break
            threading.Event().wait(0.5)
        chunks.clear()
        r = assess(c, {"points": zigzag, "max_std_mps": 5, "vehicle": VEHICLE})
        problem(r, 503, "no answer within the deadline of 1 s", "retry in")
        assert "stored" not in r.json()["detail"]  # a read stores nothing: it says nothing of it
        lanes = app.state.service.lanes
        for _ in range(100):  # until the thread has stopped
            if lanes.light.stats.busy + lanes.heavy.stats.busy == 0:
                break
            threading.Event().wait(0.1)
        assert lanes.light.stats.busy + lanes.heavy.stats.busy == 0
    assert len(chunks) <= 8, len(chunks)  # of 25


@pytest.mark.parametrize(
    ("body", "media", "phrases"),
    [
        ({"max_std_mps": 1e-310}, None, ["max_std_mps", "greater than or equal to 0.001"]),
        ({"times_s": [0, 1e-310]}, None, ["times_s: segment 0 is flown at inf m/s"]),
        ({"vehicle": {**VEHICLE, "cruise_mps": 1e308}}, None, ["cruise_mps", "less than or equal to 1000"]),
        ({"type": "FeatureCollection", "features": [1]}, "geo", ["holds one LineString, not 0"]),
        ({"type": "FeatureCollection", "features": "ab"}, "geo", ["features are a list"]),
        ({"type": "Feature", "geometry": [1]}, "geo", ["LineString geometry"]),
        (
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": [[2.0, 48.0, 10], [2.01, 48.01, 20]]},
                "properties": "times_s",
            },
            "geo",
            ["properties are an object"],
        ),
        (b"[" * 100_000 + b"]" * 100_000, None, ["not JSON", "recursion limit"]),
        (b"[" * 100_000 + b"]" * 100_000, "geo", ["not JSON", "recursion limit"]),
        (b'{"points": "\xff\xfe"}', None, ["not JSON", "invalid unicode"]),
    ],
    ids=[
        "tube",
        "times",
        "cruise",
        "features-1",
        "features-ab",
        "geometry",
        "properties",
        "deep",
        "deep-geo",
        "utf8",
    ],
)
def test_row_21_route_values_that_overflow_and_malformed_documents_are_422(wide, body, media, phrases):
    before = state(wide)
    if isinstance(body, dict) and "type" not in body:
        body = {"points": [[100, 100, 500], [5000, 100, 500]], "max_std_mps": 5, "vehicle": VEHICLE, **body}
    r = assess(wide, body, media="application/geo+json" if media else "application/json")
    problem(r, 422, *phrases)
    assert state(wide) == before


# -- 22-23: answers that tell the truth about what was stored -------------------------------------
def test_row_22_an_upload_that_waits_past_its_deadline_for_the_write_lock_stores_nothing(tmp_path):
    """Another writer holds SQLite's write lock for 2.5 s; the upload's deadline is 1 s. Its
    503 says the outcome is not known and to retry under the same key; the upload, which won
    the lock after its deadline, rolled back; the retry applies it once."""
    import sqlite3

    data_dir = tmp_path / "data"
    settings = Settings(store_url=f"sqlite:///{data_dir}", tokens=TOKENS, request_timeout_s=1.0)
    app = create_app(settings)
    X, V = data(2, n=50)
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        post_obs(c, rows(*data(1, n=300)), "a").raise_for_status()
        before = state(c)
        other = sqlite3.connect(
            app.state.service.maps.store.path, isolation_level=None, check_same_thread=False
        )
        other.execute("BEGIN IMMEDIATE")
        release = threading.Timer(2.5, other.rollback)
        release.start()
        r = post_obs(c, rows(X, V), "late")
        problem(r, 503, "may have been stored or not", "same Idempotency-Key")
        release.join()
        lanes = app.state.service.lanes
        for _ in range(100):  # until the upload's thread has ended
            if lanes.light.stats.busy + lanes.heavy.stats.busy == 0:
                break
            threading.Event().wait(0.1)
        assert state(c) == before
        again = post_obs(c, rows(X, V), "late")
        assert again.status_code == 200 and not again.json()["replayed"], again.text
        assert state(c)["observations"] == before["observations"] + 50


def test_row_23_a_running_fit_jobs_key_with_other_rows_is_a_409(tmp_path, monkeypatch):
    """The job's own rows again get its id (202); other rows under its key a 409, as the
    ledger answers once the job committed; the job applies its own rows only."""
    settings = Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=TOKENS, fit_job_points=10)
    app = create_app(settings)
    go = threading.Event()
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        maps = app.state.service.maps
        upload = maps.upload

        def held(*args, **kw):
            go.wait(30)
            return upload(*args, **kw)

        monkeypatch.setattr(maps, "upload", held)
        first, other = rows(*data(1, n=300)), rows(*data(2, n=300))
        job = post_obs(c, first, "job", route="fit")
        assert job.status_code == 202, job.text
        assert post_obs(c, first, "job", route="fit").json()["id"] == job.json()["id"]
        problem(post_obs(c, other, "job", route="fit"), 409, "still", "different data")
        go.set()
        for _ in range(300):
            done = c.get(f"/v1/jobs/{job.json()['id']}", headers=WRITE).json()
            if done["state"] in ("succeeded", "failed"):
                break
            threading.Event().wait(0.1)
        assert done["state"] == "succeeded", done
        problem(post_obs(c, other, "job", route="fit"), 409, "already used for different data")
        assert state(c)["observations"] == 300


# -- 28-29: secrets stay out of logs and answers ----------------------------------------------------
def test_row_28_store_urls_are_logged_without_any_password():
    from service.store import open_store, redacted

    url = "postgresql://bdf:hunter2@db:5432/maps?sslmode=require&password=hunter3&sslpassword=hunter4"
    assert redacted(url) == "postgresql://bdf:***@db:5432/maps?sslmode=require&password=***&sslpassword=***"
    assert redacted("postgresql://db/maps?PassWord=x") == "postgresql://db/maps?PassWord=***"
    assert redacted("sqlite:////var/lib/bdf") == "sqlite:////var/lib/bdf"
    with pytest.raises(ValueError) as err:
        open_store("mysql://bdf:hunter2@db/maps?password=hunter3")
    assert "hunter" not in str(err.value)


def test_row_29_a_job_that_failed_on_the_database_does_not_name_it(tmp_path, monkeypatch):
    settings = Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=TOKENS, fit_job_points=10)
    app = create_app(settings)
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()

        def down(*args, **kw):
            raise StoreUnavailable('connection to server at "10.0.0.7", port 5432 failed: timeout expired')

        monkeypatch.setattr(app.state.service.maps.store, "apply", down)
        job = post_obs(c, rows(*data(1, n=300)), "job", route="fit")
        assert job.status_code == 202, job.text
        for _ in range(300):
            done = c.get(f"/v1/jobs/{job.json()['id']}", headers=WRITE).json()
            if done["state"] in ("succeeded", "failed"):
                break
            threading.Event().wait(0.1)
        assert done["state"] == "failed" and "cannot be reached right now" in done["error"], done
        assert not any(s in done["error"] for s in ("10.0.0.7", "5432"))


# -- 24: the store comes back -----------------------------------------------------------------------
def test_row_24_a_database_that_lost_its_tables_is_503_then_recreated_without_a_restart(store_url):
    """The schema dropped under a running service (as a database dropped and re-created
    empty, or restored from an empty dump): /readyz and the routes answer 503 (it was 500
    UndefinedTable on every route until a restart), then the next connection creates the
    tables again and the service works on the empty store."""
    if store_url.startswith("sqlite"):
        pytest.skip("a SQLite store is its file: no server drops its tables under the service")
    import psycopg

    base, _, query = store_url.partition("?")
    schema = query.removeprefix("schema=")
    app = create_app(Settings(store_url=store_url, tokens=TOKENS))
    with TestClient(app, raise_server_exceptions=False) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        post_obs(c, rows(*data(1, n=300)), "a").raise_for_status()
        assert c.get("/readyz").status_code == 200
        assert app.state.service.maps.refresher.join(60)  # no refresh reads the store meanwhile

        def drop():
            with psycopg.connect(base, autocommit=True) as conn:
                conn.execute(f"DROP SCHEMA {schema} CASCADE")

        drop()
        problem(c.get(f"/v1/regions/{NAME}", headers=READ), 503, "retry")  # not 500
        assert c.get("/readyz").status_code == 200  # the tables were created again
        drop()
        problem(c.get("/readyz"), 503, "unreachable")
        assert c.get("/readyz").status_code == 200
        problem(c.get(f"/v1/regions/{NAME}", headers=READ), 404, NAME)
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        post_obs(c, rows(*data(1, n=300)), "a").raise_for_status()
        assert state(c)["observations"] == 300


# -- 26-27: headers within limits, pipelined answers kept --------------------------------------------
def read_answers(sock) -> list[int]:
    """The statuses of the answers on ``sock`` until the server closes it."""
    import re

    received = b""
    with contextlib.suppress(OSError):
        while chunk := sock.recv(65536):
            received += chunk
    return [int(code) for code in re.findall(rb"HTTP/1\.1 (\d{3}) ", received)]


def test_rows_26_huge_or_many_headers_are_431_before_they_are_parsed(live_server):
    """1-64 MB header values and 10,000 headers, no token: 431 (a 1 MB header was answered
    401 after the parser had joined it; two 64 MB values stalled /healthz 3.3 s)."""
    import httpx

    server = live_server(env={"BDF_TOKENS": json.dumps(TOKENS), "BDF_MAX_BODY_MB": "0.5"})
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        # a body answered 413 at its length, then sent: it is body, not headers, and the
        # connection's next request is answered
        sock.sendall(b"POST /v1/regions HTTP/1.1\r\nHost: x\r\nContent-Length: 1048576\r\n\r\n")
        threading.Event().wait(0.5)  # the 413 goes out before the body comes
        sock.sendall(b"x" * 1048576 + b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert read_answers(sock) == [413, 200]
    for header in (b"X-Big: " + b"a" * 1_000_000, b"X-Big: " + b"a" * 64_000_000, b"X-A: 1\r\n" * 10_000):
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
            sock.sendall(b"GET /v1/regions HTTP/1.1\r\nHost: x\r\n")
            with contextlib.suppress(OSError):  # the server may close before all is sent
                sock.sendall(header.rstrip(b"\r\n") + b"\r\n\r\n")
            assert read_answers(sock) == [431]
    with httpx.Client(base_url=server.url, timeout=30) as c:
        assert c.get("/healthz").status_code == 200
        assert c.get("/v1/regions", headers={**READ, "X-Fine": "a" * 8000}).status_code == 200


def test_row_27_a_slow_request_pipelined_behind_a_fast_one_keeps_its_answer(live_server):
    """The header deadline (here 0.05 s) is not armed for a request already at work: a query
    waiting for the map of a fresh upload (a process to start, a map to compute), pipelined
    behind /healthz, gets its answer (the connection was closed at the header deadline after
    the first answer, and the second lost)."""
    import httpx

    server = live_server(env={"BDF_TOKENS": json.dumps(TOKENS), "BDF_HEADER_TIMEOUT_S": "0.05"})
    with httpx.Client(base_url=server.url, timeout=30) as c:
        c.post("/v1/regions", json=SPEC, headers=ADMIN).raise_for_status()
        post_obs(c, rows(*data(1, n=300)), "a").raise_for_status()
    body = json.dumps({"points": PROBE.tolist()}).encode()
    slow = (
        f"POST /v1/regions/{NAME}/query?min_version=1 HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
        f"Authorization: {READ['Authorization']}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode() + body
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n" + slow)
        assert read_answers(sock) == [200, 200]


# -- 25: exact undo at any weight ratio the envelope allows -------------------------------------------
@pytest.mark.parametrize(("heavy", "light"), [(1000.0, 1e-6), (1000.0, 1e-3), (1.0, 1e-6), (1e-6, 1000.0)])
def test_row_25_a_retraction_is_exact_at_any_weight_ratio_the_envelope_allows(store_url, heavy, light):
    """An upload of weights ``heavy`` retracted from tiles that also hold rows of weights
    ``light``, inside the envelope: the stored statistics are those of the region built
    without it to 1e-9 of each statistic's largest (they were 64 % off at 1000 : 1e-6, the
    sum in float64 cancelling), its map the same, and verify is clean."""
    store = open_store(store_url)
    try:
        for name in (NAME, "clean"):
            store.create_region(RegionSpec.model_validate({**SPEC, "name": name}))
        maps = RegionMaps(store)
        (Xl, Vl), (Xh, Vh) = data(1, n=300), data(2, n=300)
        for name in (NAME, "clean"):
            maps.upload(name, "light", Xl, Vl, sample_weight=np.full(300, light))
        maps.upload(NAME, "heavy", Xh, Vh + 5.0, sample_weight=np.full(300, heavy))
        maps.retract(NAME, "heavy", Xh, Vh + 5.0, sample_weight=np.full(300, heavy))
        got, want = store.snapshot(NAME).evidence, store.snapshot("clean").evidence
        assert set(got) == set(want)
        for key, expected in want.items():
            for a, b in zip(got[key].classes, expected.classes, strict=True):
                for name in ("density", "proj", "mass", "v_sum", "v_sq", "count"):
                    x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
                    assert np.abs(x - y).max() <= 1e-9 * np.abs(y).max(), (key, name)
        maps.fit_hyperparameters(NAME), maps.fit_hyperparameters("clean")
        mine, clean = maps.predict(NAME, PROBE, min_version=3), maps.predict("clean", PROBE, min_version=1)
        np.testing.assert_allclose(mine.std, clean.std, rtol=1e-9)
        np.testing.assert_allclose(mine.mean, clean.mean, rtol=0, atol=1e-9 * np.abs(clean.mean).max())
        assert store.verify() == {NAME: [], "clean": []}
    finally:
        store.close()


def test_row_25_verify_reports_tiles_a_retraction_cannot_have_left_exact(tmp_path):
    """Tiles stored before retractions were compensated (format 4), in a region with a
    retraction, and a tile whose sums of non-negative terms went negative (a retraction of
    more than was there): verify names each and says its statistics cannot be trusted."""
    store = open_store(f"sqlite:///{tmp_path / 'data'}")
    try:
        store.create_region(RegionSpec.model_validate(SPEC))
        maps = RegionMaps(store)
        (Xl, Vl), (Xh, Vh) = data(1, n=300), data(2, n=300)
        maps.upload(NAME, "light", Xl, Vl, sample_weight=np.full(300, 1e-6))
        maps.upload(NAME, "heavy", Xh, Vh, sample_weight=np.full(300, 1000.0))
        maps.retract(NAME, "heavy", Xh, Vh, sample_weight=np.full(300, 1000.0))
        assert store.verify() == {NAME: []}
        info = store.region(NAME)
        stored = store.snapshot(NAME).evidence
        heavy = increments(info.spec, Xh, Vh, sample_weight=np.full(300, 1000.0))
        first, second = sorted(stored)[:2]
        with store._write() as q:
            blob = stored[first].to_bytes()  # format 4: no residual
            where = "WHERE region_id = ? AND key = ?"
            q(
                f"UPDATE tiles SET stats = ?, format_version = 4, checksum = ? {where}",
                (blob, checksum(blob), info.region_id, key_str(first)),
            )
            over = stored[second] - heavy[second].evidence  # more than the tile holds
            row = store._tile_row(info.region_id, second, 3, over, None, 1, 0.0)
            q(
                "UPDATE tiles SET stats = ?, checksum = ? WHERE region_id = ? AND key = ?",
                (row[5], row[8], *row[:2]),
            )
        problems = store.verify()[NAME]
        assert len(problems) == 2 and all("cannot be trusted" in p for p in problems), problems
        assert "statistics format 4" in problems[0] and "negative" in problems[1]
    finally:
        store.close()
