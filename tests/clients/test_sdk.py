"""The Python SDK against a real service on 127.0.0.1: numbers equal the library's, retries
never count twice, errors carry the service's problem detail."""

import asyncio

import httpx
import numpy as np
import pytest

from bdf.region.spec import RegionSpec
from clients.sdk import AsyncBDFClient, BDFClient, BDFError
from tests.service.test_api import library
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # the SDK against a server

NAME = SPEC["name"]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from clients.local import LocalService

    root = tmp_path_factory.mktemp("sdk")
    with LocalService(root / "data", {"BDF_FIT_JOB_POINTS": "400"}) as svc:
        yield svc


@pytest.fixture
def bdf(server):
    with BDFClient(server.url, backoff_s=0.01) as c:
        if NAME in [r.spec["name"] for r in c.regions()]:
            c.delete_region(NAME)
        c.create_region(SPEC)
        yield c


def test_chunked_upload_query_grid_tubes_equal_the_library_and_a_rerun_applies_nothing(bdf):
    spec = RegionSpec.model_validate(SPEC)
    X, V = data(0, n=900)
    result = bdf.upload(NAME, X, V, chunk_size=300)
    assert (result.accepted, result.chunks, result.replayed_chunks, result.region_version) == (900, 3, 0, 3)
    again = bdf.upload(NAME, X, V, chunk_size=300)  # the same data: the same keys
    assert (again.accepted, again.replayed_chunks) == (900, 3)
    assert bdf.region(NAME).observations == 900 and bdf.region(NAME).version == 3

    Xq = data(1, n=50)[0]
    bdf.fit_hyperparameters(NAME)  # the settled map (a refresh's first may be a nat short)
    mean, std, _ = library(spec, X, V, Xq)
    for transport in ("arrow", "json"):
        pred = bdf.query(NAME, Xq, transport=transport)
        np.testing.assert_allclose(pred.mean, mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(pred.std, std, rtol=1e-6)
        assert pred.known.all() and pred.region_version == 3
        assert (pred.versions_behind, pred.seconds_behind) == (0, 0.0)  # it reads its own writes
        # a point outside the region: its row is NaN, not known; the others as before
        strayed = bdf.query(NAME, np.vstack([Xq[:2], [[1e7, 0, 0]]]), transport=transport)
        assert np.isnan(strayed.mean[2]).all() and np.isnan(strayed.std[2]).all() and not strayed.known[2]
        np.testing.assert_array_equal(strayed.mean[:2], pred.mean[:2])

    grid = bdf.grid(NAME, step=[50, 50, 20], bbox=[0, 0, 0, 300, 200, 60])
    assert grid.mean.shape == (7, 5, 4, 3)
    mesh = np.stack(np.meshgrid(*grid.axes, indexing="ij"), -1).reshape(-1, 3)
    g_mean, g_std, _ = library(spec, X, V, mesh)
    np.testing.assert_allclose(grid.mean.reshape(-1, 3), g_mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(grid.std.reshape(-1, 3), g_std, rtol=1e-6)

    bound = float(np.median(grid.std))
    tubes = bdf.tubes(NAME, bound, step=[50, 50, 20])
    expected = (grid.std < bound).all(-1) & grid.known
    np.testing.assert_array_equal(tubes.mask, expected)
    assert len(tubes.points) == expected.sum() > 0
    geo = bdf.tubes_geojson(NAME, bound, step=[50, 50, 20])
    assert len(geo["features"]) == expected.sum()
    assert sum(t["points"] for t in bdf.tiles(NAME)["tiles"]) == 900  # each observation in one tile
    png = bdf.slice_png(NAME, 20, layer="tube", max_std_mps=bound, bbox=[0, 0, 150, 100], step=5)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png != bdf.slice_png(NAME, 40)


class LosesResponses(httpx.HTTPTransport):
    """Forwards every request; answers 503 before the first upload reaches the server, then
    drops the response of the second upload after the server applied it."""

    def __init__(self):
        super().__init__()
        self.uploads = 0

    def handle_request(self, request):
        if not request.url.path.endswith("/observations"):
            return super().handle_request(request)
        self.uploads += 1
        if self.uploads == 1:
            return httpx.Response(503, json={"title": "Service Unavailable", "detail": "injected"})
        response = super().handle_request(request)
        if self.uploads == 3:
            response.read()
            raise httpx.ReadError("injected: the response was lost")
        return response


def test_retries_after_5xx_and_lost_responses_never_double_count(server, bdf):
    X, V = data(2, n=600)
    transport = LosesResponses()
    with BDFClient(server.url, backoff_s=0.01, transport=transport) as flaky:
        result = flaky.upload(NAME, X, V, chunk_size=300)
    # 503, chunk 0 applied, chunk 1 applied but its answer lost, chunk 1 replayed
    assert transport.uploads == 4
    assert (result.accepted, result.replayed_chunks) == (600, 1)
    region = bdf.region(NAME)
    assert (region.observations, region.version) == (600, 2)


def test_errors_carry_the_problem_detail(server, bdf):
    with pytest.raises(BDFError) as err:
        bdf.region("nowhere")
    assert err.value.status == 404 and "nowhere" in err.value.detail
    with pytest.raises(BDFError) as err:
        bdf.grid(NAME, step=10, bbox=[0, 0, 0, 900, 200, 60])
    assert err.value.status == 422 and "leaves region" in err.value.detail
    with pytest.raises(ValueError, match="shape"):
        bdf.upload(NAME, np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(BDFError, match="outside region") as err:
        bdf.slice_png(NAME, alt_m=1000)
    assert err.value.status == 422
    with pytest.raises(ValueError, match="step needs 3"):
        bdf.grid(NAME, step=[1, 2])
    with BDFClient("http://127.0.0.1:9", retries=1, backoff_s=0) as dead:
        with pytest.raises(BDFError, match="cannot reach") as err:
            dead.regions()
    assert err.value.status == 0


def test_fit_job_is_polled_to_its_result(bdf):
    X, V = data(3, n=500)  # above BDF_FIT_JOB_POINTS: runs as a job
    bdf.upload(NAME, *data(4, n=100))
    result = bdf.fit(NAME, X, V, poll_s=0.05)
    assert result.accepted == 500 and result.region_version == 2
    assert bdf.region(NAME).observations == 500  # the fit replaced the earlier data
    job = bdf.fit(NAME, *data(5, n=450), wait=False)
    assert job["state"] in ("queued", "running", "succeeded") and len(job["id"]) == 32


def test_async_client_gives_the_same_answers(server, bdf):
    X, V = data(6, n=400)
    Xq = data(7, n=20)[0]

    async def run():
        async with AsyncBDFClient(server.url) as client:
            up = await client.upload(NAME, X, V, chunk_size=250)
            preds = await asyncio.gather(client.query(NAME, Xq), client.query(NAME, Xq[:5]))
            return up, preds

    up, (pred, first5) = asyncio.run(run())
    assert (up.accepted, up.chunks) == (400, 2)
    expected = bdf.query(NAME, Xq)
    np.testing.assert_array_equal(pred.mean, expected.mean)
    np.testing.assert_allclose(first5.std, expected.std[:5], rtol=1e-12)  # other BLAS shapes


def test_sample_weights_travel_with_the_upload(bdf):
    spec = RegionSpec.model_validate(SPEC)
    X, V = data(8, n=400)
    w = np.random.default_rng(8).uniform(0.1, 2.0, len(X))
    assert bdf.upload(NAME, X, V, sample_weight=w).accepted == 400
    Xq = data(9, n=30)[0]
    pred = bdf.query(NAME, Xq)
    mean, std, _ = library(spec, X, V, Xq, sample_weight=w)
    np.testing.assert_allclose(pred.mean, mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(pred.std, std, rtol=1e-6)
    unweighted, _, _ = library(spec, X, V, Xq)
    assert np.abs(unweighted - mean).max() > 1e-3  # the weights changed the answer


def test_a_retraction_undoes_a_chunked_upload_exactly_and_once(bdf):
    X, V = data(0, n=300)
    bdf.upload(NAME, X, V, chunk_size=100)
    Xq = data(1, n=20)[0]
    bdf.fit_hyperparameters(NAME)  # the settled map (a refresh's first may be a nat short)
    before = bdf.query(NAME, Xq)
    Xb, Vb = data(2, n=250)
    weight = np.linspace(0.5, 2.0, 250)
    bdf.upload(NAME, Xb, Vb + 30, sample_weight=weight, chunk_size=100)  # a broken sensor's
    assert np.abs(bdf.query(NAME, Xq).mean - before.mean).max() > 1
    done = bdf.retract(NAME, Xb, Vb + 30, sample_weight=weight, chunk_size=100)
    assert (done.accepted, done.chunks, done.replayed_chunks, done.region_version) == (250, 3, 0, 9)
    again = bdf.retract(NAME, Xb, Vb + 30, sample_weight=weight, chunk_size=100)
    assert (again.replayed_chunks, bdf.region(NAME).version) == (3, 9)
    assert bdf.region(NAME).observations == 300
    bdf.fit_hyperparameters(NAME)
    after = bdf.query(NAME, Xq)  # the same data's map: "auto" found again, from another start
    assert before.evidence_gap == after.evidence_gap == 0
    np.testing.assert_allclose(after.mean, before.mean, rtol=0, atol=1e-6 * np.abs(before.mean).max())
    np.testing.assert_allclose(after.std, before.std, rtol=1e-6)
    with pytest.raises(BDFError) as err:
        bdf.retract(NAME, Xb, Vb, chunk_size=100)  # not the rows of any upload
    assert err.value.status == 404
