"""The demo, end to end on real ADS-B traffic around Paris (OpenSky, via ``traffic``).

It fetches the sample (once), starts the service on SQLite on 127.0.0.1, builds the map
from 80 % of the flights over HTTP, scores it on the held-out flights, draws the map,
plans a risk-aware route and the shortest path between two points of one tube, writes the
pictures and the route to ``out``, and stops the service.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from bdf import ingest, metrics
from clients import plots
from clients.local import LocalService
from clients.sdk import BDFClient

#: The flight band of the demo route, region ENU up, metres.
ROUTE_BAND_M = (1000.0, 2500.0)
#: The tube bound is this quantile of the largest std over the band's voxels with data.
TUBE_QUANTILE = 0.2


def run(out: Path, plan_time_s: float = 5.0) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    obs, lower, upper = ingest.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    spec = ingest.paris_region(lower, upper)
    report: dict[str, object] = {}
    with LocalService(out / "bdf-data", log_path=out / "service.log") as svc, BDFClient(svc.url) as bdf:
        print(f"service on {svc.url} (SQLite in {out / 'bdf-data'}); log in {out / 'service.log'}")
        if spec.name in [r.spec.name for r in bdf.regions()]:
            bdf.delete_region(spec.name)
        bdf.create_region(spec)
        t0 = time.perf_counter()
        # each flight counts once per grid cell it crosses: 1 Hz samples are not independent
        weight = ingest.track_weights(obs.subset(~test), spec.spacing_m)
        fit = bdf.fit(spec.name, obs.X[~test], obs.V[~test], sample_weight=weight)
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
        _print("Paris velocity map (real ADS-B, OpenSky Network)", report)

        pictures = _pictures(bdf, spec, out)
        plan = _plan(bdf, spec, plan_time_s)
    print("\nrisk-aware route vs shortest path (metres, m/s, seconds)")
    print(plan.table())
    route_file = out / "route.geojson"
    route_file.write_text(json.dumps(plan.geojson()))
    from planner.plot import plot_route

    pictures.append(plot_route(plan, out / "route.png"))
    for path in [*pictures, route_file]:
        print(f"  wrote {path}")
    print(
        f"\nto browse the map: bdf serve --data-dir {out / 'bdf-data'}, then open http://127.0.0.1:8000/viewer"
    )
    report["route"] = plan
    return report


def _print(title: str, report: dict) -> None:
    width = max(map(len, report))
    print(title)
    for key, value in report.items():
        print(f"  {key:<{width}}  {value}")


def _pictures(bdf: BDFClient, spec, out: Path) -> list[Path]:
    step = (np.array(spec.spacing_m) / 8).tolist()
    paths = []
    for alt, kind in ((1000.0, "slice"), (3000.0, "arrows")):
        grid = bdf.grid(spec.name, step, [*spec.lower[:2], alt, *spec.upper[:2], alt])
        if kind == "slice":
            paths.append(plots.plot_slice(grid, alt, "e", out / f"slice_e_{alt:.0f}m.png", title=spec.name))
        else:
            paths.append(plots.plot_arrows(grid, alt, out / f"flow_{alt:.0f}m.png", title=spec.name))
    tubes = bdf.tubes(spec.name, 25.0, (np.array(spec.spacing_m) / 4).tolist())
    paths.append(plots.plot_tube(tubes, 25.0, out / "tube_3d.png", title=spec.name))
    return paths


def tube_voxels(bdf: BDFClient, spec):
    """The planning grid over the demo band, the tube bound (a quantile of the largest std
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


def farthest_pair(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = P[np.argmax(np.linalg.norm(P - P.mean(0), axis=1))]
    return a, P[np.argmax(np.linalg.norm(P - a, axis=1))]


def _plan(bdf: BDFClient, spec, time_s: float):
    """A route between the two farthest points of the largest piece of the tube."""
    from planner.costmap import CostWeights
    from planner.routes import plan_route

    grid, bound, P = tube_voxels(bdf, spec)
    step = [float(a[1] - a[0]) for a in grid.axes]
    a, b = farthest_pair(P)
    print(
        f"\nplanning {np.linalg.norm(b - a) / 1e3:.1f} km from {a.round().tolist()} to {b.round().tolist()} "
        f"(ENU m) inside the tube std < {bound:.1f} m/s, band {ROUTE_BAND_M} m, BIT* {time_s:g} s"
    )
    return plan_route(
        bdf,
        spec.name,
        a,
        b,
        weights=CostWeights(max_std_mps=bound, cruise_mps=60.0),
        altitude_m=ROUTE_BAND_M,
        step=step,
        time_s=time_s,
        seed=1,
    )
