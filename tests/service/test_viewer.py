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
    # the whole map is known and inside the tube: the same colours (to the legends' boxes)
    assert abs(draw("mean") - everything) < 0.005 * everything
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
    """Debian's Chromium, driven by Playwright (no browser download), WebGL on SwiftShader
    (the CPU). Skipped where it is missing, unless ``BDF_TEST_BROWSER=required`` (CI), where
    its absence fails."""
    if CHROMIUM is None:
        if os.environ.get("BDF_TEST_BROWSER") == "required":
            pytest.fail("BDF_TEST_BROWSER=required but no chromium on PATH (apt-get install chromium)")
        pytest.skip("no chromium on PATH: `make browser` installs Debian's package")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=BROWSER_FLAGS)
        yield browser
        browser.close()


#: headless, WebGL on the CPU (SwiftShader), nothing fetched but the page's own requests
BROWSER_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def tile_of(lat: float, lon: float, z: int) -> tuple[int, int]:
    """The XYZ tile holding a point (Web Mercator)."""
    n = 2**z
    y = (1 - np.log(np.tan(np.radians(lat)) + 1 / np.cos(np.radians(lat))) / np.pi) / 2 * n
    return int((lon + 180) / 360 * n), int(y)


def test_map_tiles_flows_and_the_tube_outline(live_server):
    """A tile over the region is coloured inside it and clear outside; a tile far away is
    clear; its ETag answers 304; the flows point along the mean; the outline encloses the
    tube; nonsense is a 4xx naming what."""
    server = live_server()
    with httpx.Client(base_url=server.url, timeout=60) as c:
        create_town(c)
        view = c.get(f"/v1/regions/{NAME}").json()
        ring = np.array(view["outline_wgs84"])
        assert ring.shape == (65, 2) and np.array_equal(ring[0], ring[-1])
        centre = ring[:-1].mean(axis=0)
        x, y = tile_of(centre[1], centre[0], 17)  # 300 m at 48 degrees: a tile holds the region
        url = f"/v1/regions/{NAME}/tiles/17/{x}/{y}.png"
        c.post(f"/v1/regions/{NAME}/hyperparameters").raise_for_status()  # settled: the ETag holds
        r = c.get(url, params={"alt_m": 20, "layer": "std"})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.headers["x-region-version"] == "1"
        rgba = imread(io.BytesIO(r.content))
        assert rgba.shape == (256, 256, 4)
        opaque = rgba[..., 3] > 0
        assert 500 < opaque.sum() < 256 * 256  # the region, and the clear tile around it
        assert (
            c.get(
                url, params={"alt_m": 20, "layer": "std"}, headers={"If-None-Match": r.headers["etag"]}
            ).status_code
            == 304
        )
        far = imread(io.BytesIO(c.get(f"/v1/regions/{NAME}/tiles/17/0/0.png", params={"alt_m": 20}).content))
        assert far[..., 3].max() == 0
        for path, params, status, message in (
            ("tiles/18/0/0.png", {"alt_m": 20, "layer": "wind"}, 422, "layer"),
            ("tiles/3/8/0.png", {"alt_m": 20}, 404, "does not exist"),
            ("tiles/23/0/0.png", {"alt_m": 20}, 422, "z"),
            ("flows", {"alt_m": 5000}, 422, "leaves region"),
            ("tube_outline", {"alt_m": 20}, 422, "max_std_mps"),
        ):
            r = c.get(f"/v1/regions/{NAME}/{path}", params=params)
            assert r.status_code == status and message in r.json()["detail"], (path, r.text)

        flows = c.get(f"/v1/regions/{NAME}/flows", params={"alt_m": 20, "step_m": 40, "arrow_s": 10}).json()
        assert flows["type"] == "FeatureCollection" and len(flows["features"]) > 10
        points = [f["geometry"]["coordinates"][0][0] for f in flows["features"]]
        answer = c.post(
            f"/v1/regions/{NAME}/query",
            json={"points": [[lat, lon, 20] for lon, lat in points], "frame": "wgs84"},
        ).json()
        for feature, (ve, vn, _) in zip(flows["features"], answer["mean"], strict=True):
            heading = np.degrees(np.arctan2(ve, vn)) % 360
            assert abs((feature["properties"]["heading_deg"] - heading + 180) % 360 - 180) < 0.1
            assert feature["properties"]["speed_mps"] == pytest.approx(np.hypot(ve, vn), abs=0.01)

        stds = np.array(
            c.post(f"/v1/regions/{NAME}/query", json={"points": [[150, 100, 20]]}).json()["std"][0]
        )
        bound = float(stds.max()) * 1.5  # the region's middle is inside this tube
        outline = c.get(
            f"/v1/regions/{NAME}/tube_outline", params={"alt_m": 20, "max_std_mps": bound, "step_m": 5}
        ).json()
        lines = outline["features"][0]["geometry"]["coordinates"]
        assert lines and 0 < outline["features"][0]["properties"]["inside"] < 1


def test_viewer_web_map_in_headless_chromium(live_server, browser):
    """The page asks for a token, lists the region, draws its tiles, flows and tube
    outline; a click shows the answer there; the layer menu redraws and the view is in the
    URL. A screenshot goes to ``test-artifacts/``."""
    server = live_server(env={"BDF_TOKENS": '{"tok-0123456789abcdef": ["read", "write", "admin"]}'})
    auth = {"Authorization": "Bearer tok-0123456789abcdef"}
    with httpx.Client(base_url=server.url, timeout=60, headers=auth) as c:
        create_town(c)
        c.post(
            f"/v1/regions/{NAME}/query?min_version=1", json={"points": [[150, 100, 20]]}
        ).raise_for_status()

    page = browser.new_page(viewport={"width": 1200, "height": 800})
    errors, tiles = [], []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("response", lambda r: tiles.append((r.status, r.url)) if "/tiles/" in r.url else None)
    page.goto(f"{server.url}/viewer")
    page.wait_for_selector("#status.error")  # no token yet: the problem's text is shown
    assert "401" in page.text_content("#status")

    page.fill("#token", "tok-0123456789abcdef")
    page.press("#token", "Enter")
    page.wait_for_selector(f"#map[data-drawn='{NAME}@20/speed']")
    page.wait_for_function("() => document.querySelectorAll('.maplibregl-canvas').length === 1")
    page.wait_for_timeout(1500)  # the tiles of the view arrive
    assert tiles and all(status == 200 for status, _ in tiles), tiles
    assert page.text_content("#legend").startswith("horizontal speed of the mean velocity (m/s)")

    box = page.locator("#map").bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)  # the region's middle
    page.wait_for_selector("#answer[data-answered]")
    text = page.text_content("#answer")
    assert "m/s towards" in text and "known" in text and "version1" in text.replace(" ", "")

    page.select_option("#layer", "std")
    page.wait_for_selector(f"#map[data-drawn='{NAME}@20/std']")
    page.wait_for_timeout(1500)
    assert any("layer=std" in url for _, url in tiles)
    assert "layer=std" in page.url and "region=town" in page.url and "#" in page.url
    assert page.text_content("#legend").startswith("predictive std")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=ARTIFACTS / "viewer.png")
    assert (ARTIFACTS / "viewer.png").stat().st_size > 20_000
    assert errors == []
