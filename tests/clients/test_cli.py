"""The ``bdf`` client commands against a live service: files in, numbers and pictures out,
one-line errors with meaningful exit codes."""

import json
import os
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pytest

from clients.sdk import BDFClient
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # the bdf command against a server

NAME = SPEC["name"]
PNG = b"\x89PNG\r\n\x1a\n"


def bdf(*args):
    return subprocess.run(
        [sys.executable, "-m", "clients.cli", *args], capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from clients.local import LocalService

    with LocalService(tmp_path_factory.mktemp("cli") / "data") as svc:
        yield svc


def test_region_upload_query_grid_tubes_and_plots(server, tmp_path):
    url = ["--url", server.url]
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(SPEC))
    assert bdf("region", "create", str(spec_file), *url).returncode == 0
    X, V = data(0, n=600)
    csv = tmp_path / "obs.csv"
    cols = dict(zip(["x", "y", "z", "ve", "vn", "vu"], np.hstack([X, V]).T, strict=True))
    pacsv.write_csv(pa.table(cols), csv)
    run = bdf("upload", NAME, str(csv), "--chunk-size", "250", *url)
    assert run.returncode == 0, run.stderr
    assert "uploaded 600 observations" in run.stdout and "3 request(s)" in run.stdout
    listing = bdf("region", "list", *url).stdout
    assert NAME in listing and " 600 " in listing

    with BDFClient(server.url) as client:  # the map settled first: both queries read the same
        client.fit_hyperparameters(NAME)
        run = bdf("query", NAME, "--points", "10,20,30;150,100,30", *url)
        expected = client.query(NAME, [[10, 20, 30], [150, 100, 30]])
    rows = [r.split(",") for r in run.stdout.strip().splitlines()[1:]]
    np.testing.assert_allclose(np.array(rows, float)[:, 3:6], expected.mean, rtol=1e-5)

    npz = tmp_path / "grid.npz"
    assert bdf("grid", NAME, "--step", "50,50,20", "--out", str(npz), *url).returncode == 0
    with np.load(npz) as g:
        assert g["mean"].shape == (7, 5, 4, 3)
        bound = float(np.median(g["std"]))
        in_tube = int(((g["std"] < bound).all(-1) & g["known"]).sum())
    geo = tmp_path / "tube.geojson"
    run = bdf("tubes", NAME, "--max-std-mps", repr(bound), "--step", "50,50,20", "--out", str(geo), *url)
    assert run.returncode == 0 and len(json.loads(geo.read_text())["features"]) == in_tube

    for kind in ("slice", "arrows", "tube"):
        png = tmp_path / f"{kind}.png"
        run = bdf(
            "plot",
            NAME,
            "--kind",
            kind,
            "--alt-m",
            "30",
            "--max-std-mps",
            repr(bound),
            "--out",
            str(png),
            *url,
        )
        assert run.returncode == 0, run.stderr
        assert png.read_bytes()[:8] == PNG and png.stat().st_size > 10_000


def test_errors_are_one_line_with_meaningful_exit_codes(server, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    for args, code, words in (
        (["upload", "nowhere", str(bad), "--url", server.url], 2, "404"),
        (["grid", NAME, "--step", "1,2", "--out", "x.npz", "--url", server.url], 2, "--step"),
        (["region", "list", "--url", "http://127.0.0.1:9"], 1, "cannot reach"),
    ):
        run = bdf(*args)
        assert run.returncode == code and words in run.stderr and run.stderr.count("\n") == 1, run.stderr
    with BDFClient(server.url) as client:
        if NAME not in [r.spec["name"] for r in client.regions()]:
            client.create_region(SPEC)
    run = bdf("upload", NAME, str(bad), "--url", server.url)
    assert run.returncode == 2 and "need the columns" in run.stderr
    words = tmp_path / "words.csv"
    words.write_text("x,y,z,ve,vn,vu\n1,2,3,4,5,6\nabc,2,3,4,5,6\n")
    run = bdf("upload", NAME, str(words), "--url", server.url)
    assert run.returncode == 2 and "column 'x', data row 2: 'abc' is not a number" in run.stderr, run.stderr
    run = bdf("upload", NAME, str(tmp_path / "nosuch.parquet"), "--url", server.url)
    assert run.returncode == 2 and "no such file: " in run.stderr and "nosuch.parquet" in run.stderr
    # latitude and longitude given without a frame are not read as metres at the origin
    run = bdf("query", NAME, "--points", "48.0005,2.0005,10", "--url", server.url)
    assert run.returncode == 2 and "look like latitude and longitude" in run.stderr, run.stderr
    assert (
        bdf("query", NAME, "--points", "48.0005,2.0005,10", "--frame", "enu", "--url", server.url).returncode
        == 0
    )
    # a negative first coordinate is a value, not an option (argparse said "expected one argument")
    run = bdf("query", NAME, "--points", "-5,10,20", "--url", server.url)
    assert run.returncode == 2 and "outside" in run.stderr, run.stderr


def test_usage_errors_come_from_the_command_and_secrets_are_not_echoed(tmp_path):
    """A typo is told by the command that got it, with its usage and the likely option
    (the top-level usage came); a short token at startup is refused without echoing it."""
    run = bdf("region", "list", "--urll", "x")
    assert run.returncode == 2 and "usage: bdf region list" in run.stderr
    assert "unrecognized arguments: --urll x (did you mean --url?)" in run.stderr
    env = {**os.environ, "BDF_TOKENS": json.dumps({"sekrit-tok": ["read"]}), "BDF_DATA_DIR": str(tmp_path)}
    run = subprocess.run(
        [sys.executable, "-m", "clients.cli", "serve", "--port", "1"], capture_output=True, text=True, env=env
    )
    assert run.returncode == 2 and "shorter than 16 characters" in run.stderr and "sekrit" not in run.stderr


def test_region_show_prints_times_as_iso_8601(server):
    with BDFClient(server.url) as client:
        if NAME not in [r.spec["name"] for r in client.regions()]:
            client.create_region(SPEC)
    run = bdf("region", "show", NAME, "--url", server.url)
    shown = json.loads(run.stdout)
    assert run.returncode == 0 and shown["created_at"].endswith("+00:00") and "T" in shown["created_at"]


def test_slice_plot_greys_the_mean_where_no_tile_has_data(tmp_path):
    from matplotlib.image import imread

    from clients import plots
    from clients.sdk import Grid
    from service.slices import UNKNOWN_GREY

    x, y, z = np.linspace(0, 1000, 40), np.linspace(0, 800, 30), np.array([100.0])
    mean = np.zeros((40, 30, 1, 3))
    mean[..., 0] = np.linspace(-5, 5, 40)[:, None, None]
    std = np.ones_like(mean)

    def grey_pixels(known):
        path = plots.plot_slice(Grid(x, y, z, mean, std, known, 1), 100.0, "e", tmp_path / "s.png")
        rgb = (imread(path)[..., :3] * 255).round()
        return int((np.abs(rgb - float(UNKNOWN_GREY) * 255) < 1.5).all(-1).sum())

    everything = np.ones((40, 30, 1), bool)
    half = everything.copy()
    half[:20] = False  # the west half has no data
    assert grey_pixels(everything) < 400  # the legend's swatch of the grey
    assert grey_pixels(half) > 20_000
    assert grey_pixels(np.zeros_like(everything)) > 1.8 * grey_pixels(half)


def test_retract_undoes_an_upload_of_the_same_file(server, tmp_path):
    url = ["--url", server.url]
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps({**SPEC, "name": "undo"}))
    assert bdf("region", "create", str(spec_file), *url).returncode == 0
    files = []
    for seed in (0, 1):
        X, V = data(seed, n=300)
        files.append(tmp_path / f"obs{seed}.csv")
        pacsv.write_csv(
            pa.table(dict(zip(["x", "y", "z", "ve", "vn", "vu"], np.hstack([X, V]).T, strict=True))),
            files[-1],
        )
        assert bdf("upload", "undo", str(files[-1]), "--chunk-size", "200", *url).returncode == 0
    run = bdf("retract", "undo", str(files[1]), "--chunk-size", "200", *url)
    assert run.returncode == 0, run.stderr
    assert "retracted 300 observations from 'undo'" in run.stdout and "2 request(s)" in run.stdout
    assert "(never applied 0, 2 request(s)" in run.stdout and "rejected" not in run.stdout
    with BDFClient(server.url) as client:
        assert client.region("undo").observations == 300
    run = bdf("retract", "undo", str(files[1]), "--chunk-size", "100", *url)  # other chunks: other keys
    assert run.returncode == 2 and "no upload" in run.stderr


def test_assess_prints_the_routes_metrics_and_fails_a_route_the_vehicle_cannot_fly(server, tmp_path):
    """``bdf assess`` of a GeoJSON route equals the SDK's ``assess_route``; a straight level
    route within the vehicle's altitudes is flyable (exit 0), a route with corners is not
    (exit 4, the failed limit named)."""
    url = ["--url", server.url]
    name = "routes"
    with BDFClient(server.url) as client:
        client.create_region({**SPEC, "name": name})
        client.upload(name, *data(5, n=400))
        frame = client.region(name).spec["origin"]
    from bdf.frames import ENUFrame

    enu = ENUFrame(frame["lat"], frame["lon"], frame["alt_m"])
    craft = {"cruise_mps": 20.0, "min_turn_radius_m": 50.0, "max_climb_deg": 10.0, "max_descent_deg": 10.0,
             "floor_m": 0.0, "ceiling_m": 100.0}  # fmt: skip

    def route_file(points, path):
        lat, lon, alt = enu.to_geodetic(np.asarray(points, float)).T
        line = {"type": "LineString", "coordinates": np.column_stack([lon, lat, alt]).tolist()}
        doc = {"type": "Feature", "geometry": line, "properties": {"max_std_mps": 3.0, "vehicle": craft}}
        path.write_text(json.dumps(doc))
        return doc

    level = route_file([[10.0, 100.0, 30.0], [290.0, 100.0, 30.0]], tmp_path / "level.geojson")
    run = bdf("assess", name, str(tmp_path / "level.geojson"), *url)
    assert run.returncode == 0, run.stderr
    with BDFClient(server.url) as client:
        want = client.assess_route(name, level)
    printed = dict(line.split() for line in run.stdout.splitlines()[:-1])
    for key, value in want["total"].items():
        assert float(printed[key]) == pytest.approx(value, rel=1e-3), key
    assert run.stdout.splitlines()[-1].startswith("envelope: flyable")
    route_file([[10.0, 10.0, 30.0], [150.0, 10.0, 30.0], [150.0, 190.0, 30.0]], tmp_path / "corner.geojson")
    run = bdf("assess", name, str(tmp_path / "corner.geojson"), *url)
    assert run.returncode == 4 and "envelope: not flyable: turn" in run.stdout, run.stdout + run.stderr
