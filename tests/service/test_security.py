"""Request ids, tokens kept out of logs, errors and metrics, CORS, security headers."""

import json
import logging

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.service.test_store import SPEC, data

NAME = SPEC["name"]
SECRETS = {"s3cret-read-4b1d": ["read"], "s3cret-admin-9f2e": ["read", "write", "admin"]}
ADMIN = {"Authorization": "Bearer s3cret-admin-9f2e"}


@pytest.fixture
def app(tmp_path):
    return create_app(Settings(store_url=f"sqlite:///{tmp_path / 'data'}", tokens=SECRETS, max_body_mb=0.01))


def test_every_error_carries_a_request_id_and_tokens_reach_no_log_error_or_metric(app, caplog):
    caplog.set_level(logging.DEBUG)
    with TestClient(app, raise_server_exceptions=False) as c:
        assert c.post("/v1/regions", json=SPEC, headers=ADMIN).status_code == 201
        X, V = data(1, n=50)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        obs = f"/v1/regions/{NAME}/observations"
        c.post(obs, json=body, headers={**ADMIN, "Idempotency-Key": "k"}).raise_for_status()

        def boom(*args, **kw):
            raise RuntimeError("injected fault")

        errors = {
            401: c.get("/v1/regions", headers={"Authorization": "Bearer s3cret-wrong-77"}),
            403: c.post(obs, json=body, headers={"Authorization": "Bearer s3cret-read-4b1d"}),
            404: c.get("/v1/regions/nowhere", headers=ADMIN),
            409: c.post(
                obs, json={**body, "points": X[::-1].tolist()}, headers={**ADMIN, "Idempotency-Key": "k"}
            ),
            413: c.post(obs, content=b"x" * 20_000, headers={**ADMIN, "Idempotency-Key": "big"}),
            415: c.post(
                obs, content=b"a,b", headers={**ADMIN, "Content-Type": "text/csv", "Idempotency-Key": "c"}
            ),
            422: c.post(f"/v1/regions/{NAME}/query", json={"points": [[1, 2]]}, headers=ADMIN),
        }
        app.state.service.maps.predict = boom
        errors[500] = c.post(f"/v1/regions/{NAME}/query", json={"points": [[1, 2, 3]]}, headers=ADMIN)
        ids = set()
        for status, r in errors.items():
            assert r.status_code == status, (status, r.text)
            assert r.headers["content-type"] == "application/problem+json"
            problem = r.json()
            assert problem["status"] == status and problem["request_id"] == r.headers["x-request-id"]
            ids.add(problem["request_id"])
        assert len(ids) == len(errors)
        assert "injected fault" not in errors[500].text  # details of our faults stay in the log
        assert errors[500].json()["request_id"] in caplog.text  # ... under the request's id

        ok = c.get("/v1/regions", headers={**ADMIN, "X-Request-ID": "client-trace.42"})
        assert ok.status_code == 200 and ok.headers["x-request-id"] == "client-trace.42"
        bad = c.get("/v1/regions", headers={**ADMIN, "X-Request-ID": "a b\tc"})
        assert bad.headers["x-request-id"] != "a b\tc" and len(bad.headers["x-request-id"]) == 32
        metrics = c.get("/metrics").text

    access = [json.loads(r.getMessage()) for r in caplog.records if r.name == "bdf.access"]
    assert {line["request_id"] for line in access} >= ids | {"client-trace.42"}
    everything = caplog.text + metrics + "".join(r.text for r in errors.values())
    assert "s3cret" not in everything


def test_cors_is_off_unless_configured(tmp_path):
    preflight = {"Origin": "https://fleet.example", "Access-Control-Request-Method": "POST"}
    with TestClient(create_app(Settings(store_url=f"sqlite:///{tmp_path / 'a'}"))) as c:
        r = c.options("/v1/regions", headers=preflight)
        assert "access-control-allow-origin" not in r.headers
        assert "access-control-allow-origin" not in c.get("/healthz", headers={"Origin": "https://x"}).headers
    settings = Settings(store_url=f"sqlite:///{tmp_path / 'b'}", cors_origins=["https://fleet.example"])
    with TestClient(create_app(settings)) as c:
        r = c.options("/v1/regions", headers=preflight)
        assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://fleet.example"
        r = c.options("/v1/regions", headers={**preflight, "Origin": "https://evil.example"})
        assert r.status_code == 400 and "access-control-allow-origin" not in r.headers
        r = c.get("/healthz", headers={"Origin": "https://fleet.example"})
        assert "x-request-id" in r.headers["access-control-expose-headers"].lower()


def test_security_headers_and_the_viewer_policy(app):
    with TestClient(app) as c:
        for r in (c.get("/healthz"), c.get("/v1/regions"), c.get("/viewer")):
            assert r.headers["x-content-type-options"] == "nosniff"
            assert r.headers["referrer-policy"] == "no-referrer"
            assert r.headers["x-frame-options"] == "DENY"
        page = c.get("/viewer")
        policy = page.headers["content-security-policy"]
        assert "default-src 'none'" in policy and "frame-ancestors 'none'" in policy
        assert "img-src 'self' data: blob:;" in policy and "connect-src 'self';" in policy  # nothing else
        assert "https:" not in policy and '<meta name="bdf-basemap" content="">' in page.text
        assert c.get("/static/maplibre-gl-csp.js").headers["content-type"].startswith("text/javascript")
        assert c.get("/static/..%2Fapp.py").status_code == 404  # only the files it lists


def test_a_basemap_is_one_setting_and_opens_the_policy_to_it(tmp_path):
    from service.app import create_app
    from service.settings import Settings

    url = "https://tiles.example.org/styles/liberty.json?key=a&b=c"
    with TestClient(create_app(Settings(store_url=f"sqlite:///{tmp_path}", viewer_basemap_url=url))) as c:
        page = c.get("/viewer")
    assert 'content="https://tiles.example.org/styles/liberty.json?key=a&amp;b=c"' in page.text
    assert "connect-src 'self' https:" in page.headers["content-security-policy"]
    with pytest.raises(ValueError, match="viewer_basemap_url"):
        Settings(store_url=f"sqlite:///{tmp_path}", viewer_basemap_url='https://x"><script>')
