"""Fuzzing: schemathesis over every route of our OpenAPI document (no 5xx, every response
as the schema says), and hypothesis over the body decoders (every bad body a 4xx, and a
rejected upload changes nothing). Bounded and seeded; ``BDF_FUZZ_EXAMPLES`` raises the
examples per route for a longer run (bench/RESULTS.md, "Fuzzing")."""

import dataclasses
import io
import json
import os
import tempfile

import hypothesis.strategies as st
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, seed, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    ignored_auth,
    missing_required_header,
    negative_data_rejection,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
    unsupported_method,
)

from bdf.region.route import Vehicle
from service.app import create_app
from service.settings import Settings
from service.wire import ARROW, PARQUET
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # fuzzing every route

NAME = SPEC["name"]
TOKEN = "fuzz-admin-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    negative_data_rejection,  # a request the schema refuses is refused
    unsupported_method,  # 405 with the Allow header of every method of the path
    missing_required_header,
    ignored_auth,
]
# positive_data_acceptance is left out: its findings are cross-field rules and limits the
# schema cannot state, each listed in RELIABILITY.md (bench/bench_fuzz.py runs every check)
EXAMPLES = int(os.environ.get("BDF_FUZZ_EXAMPLES", "12"))


def make_app(tmp_dir):
    settings = Settings(
        store_url=f"sqlite:///{tmp_dir}",
        tokens={TOKEN: ["read", "write", "admin"]},
        max_grid_voxels=20_000,
        max_query_points=5_000,
        max_points=5_000,
        fit_job_points=5_000,
    )
    return create_app(settings)


def seeded(client) -> None:
    """The region ``town`` with data, (re)made where a fuzzed DELETE removed it."""
    if client.get(f"/v1/regions/{NAME}", headers=AUTH).status_code == 404:
        assert client.post("/v1/regions", json=SPEC, headers=AUTH).status_code == 201
        X, V = data(1, n=200)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        r = client.post(
            f"/v1/regions/{NAME}/observations", json=body, headers={**AUTH, "Idempotency-Key": "seed"}
        )
        assert r.status_code == 200, r.text


@schemathesis.serializer(ARROW, PARQUET)
def _binary(ctx, value) -> bytes:
    """Binary bodies as generated (bytes for ``format: binary``)."""
    return value if isinstance(value, bytes) else json.dumps(value).encode()


# schemathesis parametrizes from the app's schema at import, so the app is made here; its
# store lives as long as the test session
DATA = tempfile.TemporaryDirectory(prefix="bdf-fuzz-")
APP = make_app(DATA.name)
SCHEMA = schemathesis.openapi.from_asgi("/openapi.json", APP)
SCHEMA.config.update(headers=AUTH, parameters={"name": NAME})


@pytest.fixture(scope="module")
def live_app():
    with TestClient(APP) as client:
        yield client


@seed(20261123)
@SCHEMA.parametrize()
@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
def test_every_route_answers_fuzzed_requests_without_5xx_and_as_its_schema_says(case, live_app):
    seeded(live_app)
    checks = CHECKS
    if case.path.endswith("{y}.png"):
        # schemathesis reports the region name it mutated for this path template, then sends
        # the configured name: a valid request it calls negative; the tile's own bad z, x, y
        # and parameters are asserted in tests/service/test_viewer.py
        checks = [c for c in CHECKS if c is not negative_data_rejection]
    case.call_and_validate(headers=AUTH, checks=checks)


# -- decoders ---------------------------------------------------------------------------------

COLUMNS = ["x", "y", "z", "ve", "vn", "vu", "lat", "lon", "alt_m", "sample_weight", "input_noise_std", "junk"]
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**70), 2**70),
    st.just(1e308),
    st.text(max_size=3),
    st.none(),
    st.booleans(),
)


def json_bodies():
    row = st.lists(NUMBERS, max_size=4)
    value = st.one_of(NUMBERS, st.lists(row, max_size=5), row, st.dictionaries(st.text(max_size=4), NUMBERS))
    keys = st.sampled_from(
        ["points", "velocities", "input_noise_std", "sample_weight", "frame", "heading_deg", "x"]
    )
    return st.dictionaries(keys, value, max_size=4).map(lambda d: json.dumps(d, allow_nan=True).encode())


def table_bodies(kind: str):
    def encode(columns):
        n = min((len(v) for v in columns.values()), default=0)
        table = pa.table({k: pa.array(v[:n], type=pa.float64()) for k, v in columns.items()})
        if kind == ARROW:
            return _ipc(table)
        buf = io.BytesIO()
        pq.write_table(table, buf)
        return buf.getvalue()

    cell = st.floats(allow_nan=True, allow_infinity=True)
    columns = st.dictionaries(st.sampled_from(COLUMNS), st.lists(cell, max_size=6), max_size=7)
    return columns.map(encode)


def _ipc(table) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def mangled(bodies):
    """Valid-looking bodies, truncated or with bytes flipped."""
    return st.tuples(bodies, st.integers(0, 10_000), st.booleans()).map(
        lambda t: t[0][: t[1]] if t[2] else bytes(b ^ 0x5A if i % 7 == 3 else b for i, b in enumerate(t[0]))
    )


BODIES = st.one_of(
    st.tuples(st.just("application/json"), json_bodies()),
    st.tuples(st.just("application/json"), mangled(json_bodies())),
    st.tuples(st.just(ARROW), table_bodies(ARROW)),
    st.tuples(st.just(ARROW), mangled(table_bodies(ARROW))),
    st.tuples(st.just(PARQUET), table_bodies(PARQUET)),
    st.tuples(st.just(PARQUET), mangled(table_bodies(PARQUET))),
    st.tuples(st.sampled_from(["application/json", ARROW, PARQUET]), st.binary(max_size=300)),
)


@seed(20261124)
@given(body=BODIES)
@settings(max_examples=EXAMPLES * 8, deadline=None, suppress_health_check=list(HealthCheck))
def test_bad_bodies_are_4xx_and_a_rejected_upload_changes_nothing(body, live_app):
    seeded(live_app)
    media, content = body
    region = f"/v1/regions/{NAME}"
    before = live_app.get(region, headers=AUTH).json()
    probe = {"points": [[150.0, 100.0, 30.0]]}
    at = f"{region}/query?min_version={before['version']}"  # this version's map, not the one before
    answer = live_app.post(at, json=probe, headers=AUTH).json()
    key = f"fuzz-{hash(content)}"
    r = live_app.post(
        f"{region}/observations",
        content=content,
        headers={**AUTH, "Content-Type": media, "Idempotency-Key": key},
    )
    assert r.status_code < 500, r.text
    if r.status_code >= 400:
        assert r.headers["content-type"] == "application/problem+json"
        after = live_app.get(region, headers=AUTH).json()
        assert (after["version"], after["observations"]) == (before["version"], before["observations"])
        assert live_app.post(at, json=probe, headers=AUTH).json() == answer
    q = live_app.post(f"{region}/query", content=content, headers={**AUTH, "Content-Type": media})
    assert q.status_code < 500, q.text


# -- routes, tubes, slices and grids ------------------------------------------------------------

EXTREMES = st.sampled_from([0, -1, 1e-310, 5e-324, 1e308, -1e308, 1e400, 2**70, 0.5, 30, 150])
ROUTE_KEYS = [
    "type", "features", "geometry", "coordinates", "properties", "points", "frame", "times_s",
    "heading_deg", "max_std_mps", "vehicle", "cruise_mps", "min_turn_radius_m", "floor_m",
]  # fmt: skip


def route_documents():
    """Any JSON document built of a route's words and extreme numbers, and routes inside the
    region whose times, headings, tube bound and vehicle are extreme."""
    leaf = st.one_of(
        NUMBERS, EXTREMES, st.sampled_from(["LineString", "Feature", "FeatureCollection", "evtol"])
    )
    anything = st.recursive(
        leaf,
        lambda inner: (
            st.lists(inner, max_size=4) | st.dictionaries(st.sampled_from(ROUTE_KEYS), inner, max_size=4)
        ),
        max_leaves=24,
    )
    point = st.tuples(st.floats(0, 300), st.floats(0, 200), st.floats(0, 60)).map(list)
    vehicle = st.fixed_dictionaries({f.name: EXTREMES for f in dataclasses.fields(Vehicle)})
    route = st.fixed_dictionaries(
        {"points": st.lists(point, min_size=2, max_size=5), "max_std_mps": EXTREMES},
        optional={
            "times_s": st.lists(EXTREMES, min_size=2, max_size=5),
            "heading_deg": st.lists(EXTREMES, min_size=1, max_size=4),
            "vehicle": vehicle | st.sampled_from(["evtol", "fixed-wing", "blimp"]),
        },
    )
    return st.one_of(anything, route).map(lambda d: json.dumps(d, allow_nan=True).encode())


@seed(20261127)
@given(
    media=st.sampled_from(["application/json", "application/geo+json"]),
    content=st.one_of(route_documents(), mangled(route_documents()), st.binary(max_size=200)),
)
@settings(max_examples=EXAMPLES * 8, deadline=None, suppress_health_check=list(HealthCheck))
def test_any_route_document_is_answered_without_a_server_error(media, content, live_app):
    seeded(live_app)
    r = live_app.post(
        f"/v1/regions/{NAME}/routes/assess", content=content, headers={**AUTH, "Content-Type": media}
    )
    assert r.status_code < 500, r.text
    if r.status_code >= 400:
        assert r.headers["content-type"] == "application/problem+json"


PARAMETER = st.one_of(
    EXTREMES.map(str), st.text(max_size=12), st.sampled_from(["nan", "inf", "-inf", "1e-310", ",,,", "0,0,0"])
)
MAP_ROUTES = {
    "grid": ["step", "bbox", "min_version", "modes"],
    "tubes": ["step", "bbox", "max_std_mps", "component", "heading_deg", "min_share"],
    "slice.png": ["alt_m", "layer", "component", "max_std_mps", "bbox", "step", "min_share"],
}


@seed(20261127)
@given(
    route=st.sampled_from(sorted(MAP_ROUTES)),
    values=st.dictionaries(st.sampled_from(sorted({p for ps in MAP_ROUTES.values() for p in ps})), PARAMETER),
)
@settings(max_examples=EXAMPLES * 8, deadline=None, suppress_health_check=list(HealthCheck))
def test_any_parameters_of_a_grid_a_tube_or_a_slice_are_answered_without_a_server_error(
    route, values, live_app
):
    seeded(live_app)
    r = live_app.get(f"/v1/regions/{NAME}/{route}", params=values, headers=AUTH)
    assert r.status_code < 500, r.text
