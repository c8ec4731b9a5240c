"""The slice picture endpoint and the viewer page (the page in headless Chromium)."""

import io
import os
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from matplotlib.image import imread

from service.slices import MAX_SIDE, render_slice, slice_axes
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # a browser

NAME = SPEC["name"]
ARTIFACTS = Path(os.environ.get("BDF_TEST_ARTIFACTS", Path(__file__).parents[2] / "test-artifacts"))
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def coloured_pixels(png: bytes) -> int:
    """Pixels that are neither grey nor white: the data's colours (and the colour bar's)."""
    rgb = imread(io.BytesIO(png))[..., :3]
    return int((np.ptp(rgb, axis=-1) > 0.05).sum())


def saturation(png: bytes) -> float:
    """The sum over pixels of how far from grey each is: paler colours count less."""
    rgb = imread(io.BytesIO(png))[..., :3]
    return float(np.ptp(rgb, axis=-1).sum())


def create_town(c: httpx.Client) -> None:
    """The region ``town`` with 900 observations, version 1."""
    assert c.post("/v1/regions", json=SPEC).status_code == 201
    X, V = data(0, n=900)
    body = {"points": X.tolist(), "velocities": V.tolist()}
    assert c.post(f"/v1/regions/{NAME}/observations", json=body, headers={"Idempotency-Key": "a"}).is_success


def test_slice_axes_default_bbox_and_limits():
    lo, hi, spacing = np.array([0, 0, 0.0]), np.array([300, 200, 60.0]), np.array([25, 25, 20.0])
    x, y = slice_axes(lo, hi, spacing, None, None)
    assert x[0] == 0 and x[-1] == 300 and np.allclose(np.diff(x), 6.25) and len(y) == 33
    x, y = slice_axes(lo, hi, spacing, (100, 50, 200, 150), 10.0)
    assert x.tolist() == list(np.arange(100, 201, 10.0)) and y.tolist() == list(np.arange(50, 151, 10.0))
    x, _ = slice_axes(lo, np.array([1e5, 100, 60]), spacing, None, None)  # coarser than spacing/4
    assert len(x) == MAX_SIDE and x[-1] == pytest.approx(1e5)
    for bbox, step, message in (
        ((0, 0, -1, 10), None, "xmax > xmin"),
        ((0, 0, 400, 10), None, "leaves the region"),
        (None, 0.5, f"exceeds {MAX_SIDE} per axis"),
    ):
        with pytest.raises(ValueError, match=message):
            slice_axes(lo, hi, spacing, bbox, step)


def test_render_slice_colours_only_what_the_layer_shows():
    x, y = np.linspace(0, 1000, 40), np.linspace(0, 800, 30)
    mean = np.zeros((40, 30, 3))
    mean[..., 0] = np.linspace(-5, 5, 40)[:, None]
    std = np.full((40, 30, 3), 0.5)
    known = np.ones((40, 30), bool)

    def draw(layer, bound=1.0, known=known):
        png = render_slice(
            x, y, mean, std, known, alt_m=100, layer=layer, component="e", max_std_mps=bound, title="t"
        )
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        return coloured_pixels(png)

    everything, none = draw("tube", bound=1.0), draw("tube", bound=0.4)  # std 0.5 in / out
    assert everything > none + 50_000  # the map area, beside the colour bar both share
    assert draw("mean") == everything  # the whole map is known and inside the tube
    assert draw("mean", known=np.zeros_like(known)) == none  # no data: grey map, same bar


def test_render_slice_draws_the_modes_of_the_classes_with_enough_share():
    x, y = np.linspace(0, 1000, 48), np.linspace(0, 800, 40)
    mean, std = np.zeros((48, 40, 3)), np.full((48, 40, 3), 0.5)
    known = np.ones((48, 40), bool)
    share = np.zeros((48, 40, 3))
    share[..., 0], share[..., 1] = 0.7, 0.3
    mode_mean = np.zeros((48, 40, 3, 3))
    mode_mean[..., 0, 0], mode_mean[..., 1, 1] = 20.0, -10.0  # east, and south

    def draw(layer, share=share, min_share=0.05, share_std=0.0, measure=None):
        png = render_slice(
            x,
            y,
            mean,
            std,
            known,
            alt_m=100,
            layer=layer,
            component="e",
            max_std_mps=1.0,
            title="t",
            share=share,
            share_std=np.full((48, 40), share_std),
            mode_mean=mode_mean,
            min_share=min_share,
        )
        return (measure or coloured_pixels)(png)

    both, one = draw("modes"), draw("modes", min_share=0.5)  # the 0.3 class's arrows go
    assert both > one + 1_000 > 2_000
    # a share less than one std above min_share is drawn faint (its colours paler)
    solid, faint = draw("modes", measure=saturation), draw("modes", share_std=0.68, measure=saturation)
    half = draw("modes", share_std=0.3, measure=saturation)  # the 0.7 class stays solid
    assert solid > half + 0.05 * solid and half > faint + 0.5 * solid
    assert draw("share") > 50_000
    with pytest.raises(ValueError, match="needs the modes"):
        render_slice(x, y, mean, std, known, alt_m=1, layer="modes", component="e", max_std_mps=1, title="t")


def test_slice_png_endpoint(live_server):
    server = live_server()
    with httpx.Client(base_url=server.url, timeout=60) as c:
        create_town(c)
        url = f"/v1/regions/{NAME}/slice.png"
        r = c.get(url, params={"alt_m": 20})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.headers["x-region-version"] == "1"
        shape = imread(io.BytesIO(r.content)).shape
        assert shape[0] > 300 and shape[1] > 300
        assert (
            c.get(url, params={"alt_m": 20}, headers={"If-None-Match": r.headers["etag"]}).status_code == 304
        )
        assert c.get(url, params={"alt_m": 40}).content != r.content
        tube = [
            coloured_pixels(c.get(url, params={"alt_m": 20, "layer": "tube", "max_std_mps": b}).content)
            for b in (0.01, 100.0)
        ]
        assert tube[1] > tube[0] + 50_000
        for params, message in (
            ({"alt_m": 61}, "outside region"),
            ({"alt_m": 20, "bbox": "0,0,500,100"}, "leaves the region"),
            ({"alt_m": 20, "bbox": "0,0,5"}, "bbox: must be 4 comma-separated numbers"),
            ({"alt_m": 20, "layer": "speed"}, "layer"),
            ({"alt_m": 20, "step": 0.1}, "per axis"),
        ):
            r = c.get(url, params=params)
            assert r.status_code == 422, params
            assert r.headers["content-type"] == "application/problem+json"
            assert message in r.json()["detail"], (params, r.json())
        assert c.get("/v1/regions/nowhere/slice.png", params={"alt_m": 1}).status_code == 404


@pytest.fixture
def browser():
    """Debian's Chromium, driven by Playwright (no browser download). Skipped where it is
    missing, unless ``BDF_TEST_BROWSER=required`` (CI), where its absence fails."""
    if CHROMIUM is None:
        if os.environ.get("BDF_TEST_BROWSER") == "required":
            pytest.fail("BDF_TEST_BROWSER=required but no chromium on PATH (apt-get install chromium)")
        pytest.skip("no chromium on PATH: `make browser` installs Debian's package")
    from playwright.sync_api import sync_playwright

    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
    ]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=flags)
        yield browser
        browser.close()


def test_viewer_page_in_headless_chromium(live_server, browser):
    """The page asks for a token, lists the region, draws a slice; the slider (keyboard)
    and the layer menu change the picture. Screenshots go to ``test-artifacts/``."""
    server = live_server(env={"BDF_TOKENS": '{"tok-0123456789abcdef": ["read", "write", "admin"]}'})
    auth = {"Authorization": "Bearer tok-0123456789abcdef"}
    with httpx.Client(base_url=server.url, timeout=60, headers=auth) as c:
        create_town(c)
        png_at_30 = c.get(f"/v1/regions/{NAME}/slice.png", params={"alt_m": 30}).content

    page = browser.new_page(viewport={"width": 1100, "height": 900})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{server.url}/viewer")
    page.wait_for_selector("#status.error")  # no token yet: the problem's text is shown
    assert "401" in page.text_content("#status")

    page.fill("#token", "tok-0123456789abcdef")
    page.press("#token", "Enter")  # commits the field: its change event reloads the regions
    page.wait_for_selector("#image[data-alt-m='20']")
    assert page.text_content("#status") == f"{NAME} at 20 m, region version 1"
    assert page.input_value("#alt") == "20" and page.text_content("#altLabel") == "20 m"
    before = page.locator("#image").screenshot()

    page.focus("#alt")
    page.keyboard.press("ArrowRight")  # step: half the vertical spacing, 10 m
    page.wait_for_selector("#image[data-alt-m='30']")
    after = page.locator("#image").screenshot()
    assert after != before
    size = page.eval_on_selector("#image", "i => [i.naturalHeight, i.naturalWidth]")
    assert size == list(imread(io.BytesIO(png_at_30)).shape[:2])  # the endpoint's picture

    page.select_option("#layer", "std")
    page.wait_for_selector("#image[data-layer='std']")
    assert page.locator("#image").screenshot() != after
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=ARTIFACTS / "viewer.png", full_page=True)
    assert (ARTIFACTS / "viewer.png").stat().st_size > 20_000
    assert errors == []
