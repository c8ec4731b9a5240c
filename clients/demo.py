"""The demo, end to end on real ADS-B traffic around Paris (OpenSky, via ``traffic``).

It fetches the sample (once), starts the service on SQLite on 127.0.0.1, builds the map
from 80 % of the flights over HTTP, scores it on the held-out flights, draws the map,
finds the busiest flow of the route band (the cell most flights cross), plans a
risk-aware route and the shortest path between two tube points on opposite sides of it,
writes the pictures and the route to ``out``, and stops the service.

With ``url`` it runs against that live service instead: a ``paris`` region already there
is used as it is (the held-out score is then skipped: its map may hold every flight),
otherwise it is created and built there first. Nothing on that service is deleted.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from bdf import ingest, metrics
from bdf.region.spec import RegionSpec
from clients import plots, samples
from clients.local import LocalService
from clients.sdk import BDFClient

#: The flight band of the demo route, region ENU up, metres.
ROUTE_BAND_M = (1000.0, 2500.0)
#: the vehicle the demo plans for (:data:`bdf.region.route.VEHICLES`)
DEMO_VEHICLE = "evtol"
#: The tube bound is this quantile of the largest std over the band's voxels with data.
TUBE_QUANTILE = 0.2
#: The busiest flow is the horizontal cell of this size (metres) the most flights cross.
FLOW_CELL_M = 2000.0
#: Start and goal: the tube points nearest this far (metres) from the flow, on each side.
SIDE_OFFSET_M = 15_000.0
#: Heading sectors of the demo's map: chosen by its fit (arrivals, departures and cruise
#: traffic cross here, :mod:`bdf.region.resolution`).
DIRECTIONS = "auto"


def run(
    out: Path, plan_time_s: float | None = None, url: str | None = None, token: str | None = None
) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    spec = samples.paris_demo_region(lower, upper, directions=DIRECTIONS)
    report: dict[str, object] = {}
    svc = None
    with contextlib.ExitStack() as stack:
        if url is None:
            svc = stack.enter_context(LocalService(out / "bdf-data", log_path=out / "service.log"))
            url = svc.url
            print(f"service on {url} (SQLite in {out / 'bdf-data'}); log in {out / 'service.log'}")
        bdf = stack.enter_context(BDFClient(url, token))
        existing = spec.name in [r.spec["name"] for r in bdf.regions()]
        if existing and svc is None:
            spec = RegionSpec.model_validate(bdf.region(spec.name).spec)
            print(f"using the map of region {spec.name!r} on {url} as it is")
        else:
            if existing:  # the demo's own store, from an earlier run
                bdf.delete_region(spec.name)
            bdf.create_region(spec)
            spec = _build(bdf, spec, obs, test, report)
        plan = _plan(bdf, spec, busiest_flow(obs.subset(~test), ROUTE_BAND_M), plan_time_s)
        pictures = _pictures(bdf, spec, out, plan.costmap.weights.max_std_mps)
    print("\nrisk-aware route vs shortest path (metres, m/s, seconds)")
    print(plan.table())
    route_file = out / "route.geojson"
    route_file.write_text(json.dumps(plan.geojson()))
    from planner.plot import plot_route

    pictures.append(plot_route(plan, out / "route.png"))
    for path in [*pictures, route_file]:
        print(f"  wrote {path}")
    if svc is not None:
        print(
            f"\nto browse the map: {_command()} serve --data-dir {out / 'bdf-data'}, then open "
            "http://127.0.0.1:8000/viewer"
        )
    report["route"] = plan
    return report


def _command() -> str:
    """How to run ``bdf`` from here: itself where it is on PATH, else the path of the one
    beside this interpreter (``make demo`` installs it in .venv, which is not activated)."""
    here = Path(sys.executable).with_name("bdf")
    if here.exists() and shutil.which("bdf") != str(here):
        with contextlib.suppress(ValueError):
            return str(here.relative_to(Path.cwd()))
        return str(here)
    return "bdf"


def _build(bdf: BDFClient, spec, obs, test, report: dict) -> RegionSpec:
    """Learn the map from the training flights over HTTP, score it on the held-out
    flights, print both; the region's spec as its fit stored it (the sectors it chose)."""
    t0 = time.perf_counter()
    # the rows as they come, with their tracks: the service weighs each track's 1 Hz samples
    train = obs.subset(~test)
    fit = bdf.fit(spec.name, train.X, train.V, track=train.flight, t=train.time)
    report["map build over HTTP [s]"] = round(time.perf_counter() - t0, 2)
    report["train points / tiles updated"] = f"{fit.accepted} / {fit.tiles_updated}"
    t0 = time.perf_counter()
    pred = bdf.query(spec.name, obs.X[test])
    report["query of the held-out points [s]"] = round(time.perf_counter() - t0, 2)
    train = obs.V[~test]
    report["held-out flights: points"] = int(test.sum())
    report["RMSE [m/s]"] = round(float(metrics.rmse(obs.V[test], pred.mean)), 2)
    report["MSLL"] = round(
        float(metrics.msll(obs.V[test], pred.mean, pred.std, train.mean(0), train.std(0))), 3
    )
    report["95% coverage"] = round(float(metrics.coverage(obs.V[test], pred.mean, pred.std)), 3)
    chosen = RegionSpec.model_validate(bdf.region(spec.name).spec)
    for score in chosen.directions_scores or ():
        report[f"{score.directions} sectors: CV mixture MSLL, cond. RMSE"] = (
            f"{score.mixture_msll:.3f} +- {score.mixture_msll_se:.3f}, {score.conditional_rmse_mps:.2f}"
            + ("  (chosen)" if score.chosen else "")
        )
    _print("Paris velocity map (real ADS-B, OpenSky Network)", report)
    return chosen


def _print(title: str, report: dict) -> None:
    width = max(map(len, report))
    print(title)
    for key, value in report.items():
        print(f"  {key:<{width}}  {value}")


def _pictures(bdf: BDFClient, spec, out: Path, bound: float) -> list[Path]:
    """The map's pictures, on its latitude and longitude too; the tube of the route's
    bound (``bound``, m/s)."""
    step, origin = (np.array(spec.spacing_m) / 8).tolist(), (spec.origin.lat, spec.origin.lon)
    paths = []
    for alt, kind in ((1000.0, "slice"), (3000.0, "arrows")):
        grid = bdf.grid(spec.name, step, [*spec.lower[:2], alt, *spec.upper[:2], alt])
        if kind == "slice":
            path = out / f"slice_e_{alt:.0f}m.png"
            paths.append(plots.plot_slice(grid, alt, "e", path, title=spec.name, origin=origin))
        else:
            paths.append(
                plots.plot_arrows(grid, alt, out / f"flow_{alt:.0f}m.png", title=spec.name, origin=origin)
            )
    for alt in (1000.0, 3000.0):
        grid = bdf.grid(spec.name, step, [*spec.lower[:2], alt, *spec.upper[:2], alt], modes=True)
        path = out / f"modes_{alt:.0f}m.png"
        paths.append(plots.plot_modes(grid, alt, path, title=spec.name, origin=origin))
    tubes = bdf.tubes(spec.name, bound, (np.array(spec.spacing_m) / 4).tolist())
    paths.append(plots.plot_tube(tubes, bound, out / "tube.png", title=spec.name, origin=origin))
    return paths


def tube_voxels(bdf, spec):
    """On any map source (the SDK, or a ``LocalMap``): the planning grid over the demo band,
    the tube bound (a quantile of the largest std
    where there is data), and the voxels deep inside the largest connected piece of the
    tube (all their neighbours are in it): start and goal points with a route between them."""
    step = (np.array(spec.spacing_m) / 4).tolist()
    grid = bdf.grid(spec.name, step, [*spec.lower[:2], ROUTE_BAND_M[0], *spec.upper[:2], ROUTE_BAND_M[1]])
    s = grid.std.max(axis=-1)
    bound = float(np.quantile(s[grid.known], TUBE_QUANTILE))
    labels, n = ndimage.label(grid.known & (s < bound))
    largest = 1 + int(np.argmax(ndimage.sum_labels(np.ones_like(s), labels, range(1, n + 1))))
    idx = np.argwhere(ndimage.binary_erosion(labels == largest, np.ones((3, 3, 3))))
    return grid, bound, np.stack([grid.x[idx[:, 0]], grid.y[idx[:, 1]], grid.z[idx[:, 2]]], axis=1)


def busiest_flow(obs: ingest.Observations, band, cell_m: float = FLOW_CELL_M):
    """The busiest flow in the altitude ``band``: the centre (x, y) of the horizontal cell
    the most distinct flights cross, the unit direction of their headings there (the
    principal axis of their unit horizontal velocities, pointing along the mean), and the
    number of flights."""
    inside = (obs.X[:, 2] >= band[0]) & (obs.X[:, 2] <= band[1])
    X, V, flight = obs.X[inside], obs.V[inside], obs.flight[inside]
    cell = np.floor(X[:, :2] / cell_m).astype(np.int64)
    pairs = np.unique(np.column_stack([cell, flight]), axis=0)  # one row per flight and cell
    cells, flights = np.unique(pairs[:, :2], axis=0, return_counts=True)
    busiest = cells[np.argmax(flights)]
    here = (cell == busiest).all(axis=1)
    heading = V[here, :2] / np.maximum(np.linalg.norm(V[here, :2], axis=1, keepdims=True), 1e-9)
    direction = np.linalg.eigh(heading.T @ heading)[1][:, -1]
    if direction @ heading.sum(axis=0) < 0:
        direction = -direction
    return (busiest + 0.5) * cell_m, direction, int(flights.max())


def across_flow(P: np.ndarray, centre, direction, offset_m: float = SIDE_OFFSET_M):
    """The points of ``P`` (n, 3) nearest ``offset_m`` to each side of the flow through
    ``centre`` along ``direction`` (horizontal): start on its right, goal on its left."""
    normal = np.array([-direction[1], direction[0]])  # to the left of the flow
    side = (P[:, :2] - centre) @ normal
    along = (P[:, :2] - centre) @ direction
    ends = []
    for sign in (-1.0, 1.0):
        mine = np.flatnonzero(sign * side > 0.25 * offset_m)
        if len(mine) == 0:
            raise ValueError(f"the tube has no point {0.25 * offset_m:g} m or more on one side of the flow")
        ends.append(P[mine[np.argmin((side[mine] - sign * offset_m) ** 2 + along[mine] ** 2)]])
    return ends[0], ends[1]


def _plan(bdf: BDFClient, spec, flow, time_s: float | None):
    """A route across the busiest flow, between tube points on either side of it (each
    planner's budget ``time_s``, by default ``plan_route``'s)."""
    from planner.costmap import CostWeights
    from planner.routes import PLAN_TIME_S, plan_route

    time_s = PLAN_TIME_S if time_s is None else time_s
    grid, bound, P = tube_voxels(bdf, spec)
    step = [float(a[1] - a[0]) for a in grid.axes]
    centre, direction, flights = flow
    a, b = across_flow(P, centre, direction)
    heading = np.degrees(np.arctan2(direction[0], direction[1])) % 360
    print(
        f"\nbusiest flow in the band {ROUTE_BAND_M} m: {flights} flights cross the {FLOW_CELL_M / 1e3:g} km "
        f"cell at {np.round(centre / 1e3, 1).tolist()} km (ENU), heading {heading:.0f} deg"
        f"\nplanning {np.linalg.norm(b - a) / 1e3:.1f} km across it from {a.round().tolist()} to "
        f"{b.round().tolist()} (ENU m) inside the tube std < {bound:.1f} m/s, planning in {time_s:g} s"
    )
    return plan_route(
        bdf,
        spec.name,
        a,
        b,
        weights=CostWeights(max_std_mps=bound),
        altitude_m=ROUTE_BAND_M,
        step=step,
        time_s=time_s,
        seed=1,
        vehicle=DEMO_VEHICLE,
    )
