"""The ``bdf`` command line. Errors are one line on stderr and a non-zero exit code.

Exit codes: 0 success; 1 runtime failure (download, I/O, the service unreachable or
failing); 2 bad usage or bad input (including the service's 4xx answers); 3 the planner
found no route within its budget.

The client commands talk to ``--url`` (``$BDF_URL``, default http://127.0.0.1:$BDF_PORT,
port 8000 unless set) with ``--token`` (``$BDF_TOKEN``).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import difflib
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydantic

NO_ROUTE = 3
#: exit status of ``bdf assess`` when the vehicle cannot fly the route
NOT_FLYABLE = 4


def _floats(text: str, n: int | tuple[int, ...], name: str) -> list[float]:
    """``"1,2,3"`` -> floats; ``n`` the accepted counts."""
    counts = (n,) if isinstance(n, int) else n
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers, got {text!r}") from None
    if len(values) not in counts or not np.isfinite(values).all():
        raise ValueError(f"{name} needs {' or '.join(map(str, counts))} finite numbers, got {text!r}")
    return values


def _client(args):
    from clients.sdk import BDFClient

    return BDFClient(args.url, args.token)


def _print_json(value) -> None:
    print(json.dumps(value, indent=2, default=str))


def _region_create(args) -> int:
    from bdf.region.spec import RegionSpec

    spec = json.loads(Path(args.spec).read_text())
    with _client(args) as bdf:
        region = bdf.create_region(spec)
    created = RegionSpec.model_validate(region.spec)
    print(f"created region {created.name!r} ({created.tile_counts} tiles per axis)")
    return 0


def _region_list(args) -> int:
    with _client(args) as bdf:
        regions = bdf.regions()
    print(f"{'name':<20} {'version':>8} {'observations':>13} {'tiles':>6}")
    for r in regions:
        print(f"{r.spec['name']:<20} {r.version:>8} {r.observations:>13} {r.tiles:>6}")
    return 0


def _region_show(args) -> int:
    with _client(args) as bdf:
        r = bdf.region(args.name)
    _print_json(_iso_times(r.__dict__))
    return 0


def _iso_times(value):
    """``value`` with every time (``*_at``: epoch seconds) as ISO 8601 UTC."""
    if isinstance(value, dict):
        return {
            k: _iso(v) if k.endswith("_at") and isinstance(v, int | float) else _iso_times(v)
            for k, v in value.items()
        }
    return [_iso_times(v) for v in value] if isinstance(value, list) else value


def _iso(seconds: float) -> str:
    return datetime.datetime.fromtimestamp(seconds, datetime.UTC).isoformat(timespec="seconds")


def _region_delete(args) -> int:
    with _client(args) as bdf:
        bdf.delete_region(args.name)
    print(f"deleted region {args.name!r}")
    return 0


def _health(args) -> int:
    """Exit 0 when the service answers and its store is reachable (container healthchecks)."""
    with _client(args) as bdf:
        bdf.health()
    print("ready")
    return 0


def _send_observations(args, kind: str) -> int:
    """``bdf upload``, ``bdf fit`` or ``bdf retract`` of a file."""
    from bdf.region.spec import RegionSpec
    from clients.files import read_observations

    with _client(args) as bdf:
        spec = RegionSpec.model_validate(bdf.region(args.name).spec)
        obs = read_observations(args.file, spec)
        if obs.dropped:
            print(f"{args.file}: dropped {obs.dropped}", file=sys.stderr)
        kw = {
            "input_noise_std": obs.input_noise_std,
            "track": obs.track,
            "t": obs.time,
            "frame": obs.frame,
            "progress": args.progress,
        }
        if kind != "fit":
            kw["chunk_size"] = args.chunk_size
        result = getattr(bdf, kind)(args.name, obs.X, obs.V, **kw)
    done = {"upload": "uploaded", "fit": "fitted", "retract": "retracted"}[kind]
    # a retraction's "rejected" are the rows its upload had rejected: never in the map
    rejected = "never applied" if kind == "retract" else "rejected"
    reasons = ", ".join(f"{n} {why}" for why, n in result.rejected.items() if n)
    print(
        f"{done} {result.accepted} observations {'from' if kind == 'retract' else 'to'} {args.name!r} "
        f"({rejected} {sum(result.rejected.values())}{f': {reasons}' if reasons else ''}, "
        f"{result.chunks} request(s), {result.replayed_chunks} replayed); "
        f"region version {result.region_version}"
    )
    for warning in result.warnings:
        print(f"warning: {result.untracked} {warning}", file=sys.stderr)
    return 0


def _query(args) -> int:
    from clients.files import read_points

    if args.points:
        frame = args.frame
        P = np.array([_floats(p, 3, "--points") for p in args.points.split(";")])
    else:
        frame, P = read_points(args.file)
    with _client(args) as bdf:
        frame = _frame(bdf, args.name, P, frame)
        pred = bdf.query(args.name, P, frame=frame)
    lines = ["p0,p1,p2,ve,vn,vu,std_e,std_n,std_u,known"]
    for p, m, sd, k in zip(P, pred.mean, pred.std, pred.known, strict=True):
        lines.append(",".join(f"{v:.6g}" for v in (*p, *m, *sd)) + f",{int(k)}")
    text = "\n".join(lines) + "\n"
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}: {len(P)} points, region version {pred.region_version}")
    else:
        sys.stdout.write(text)
    return 0


def _frame(bdf, region: str, P: np.ndarray, frame: str | None) -> str:
    """The frame of points ``P`` given with ``frame`` (None: not said, ENU metres): points
    that read as latitude and longitude within a degree of the region's origin, given
    without a frame, are refused (as ENU metres they would be answered for the origin)."""
    if frame is not None:
        return frame
    origin = bdf.region(region).spec["origin"]
    near = (np.abs(P[:, 0] - origin["lat"]) < 1.0) & (np.abs(P[:, 1] - origin["lon"]) < 1.0)
    if near.all():
        raise ValueError(
            f"{P[0, :2].tolist()} look like latitude and longitude near region {region!r}'s origin "
            f"({origin['lat']}, {origin['lon']}): add --frame wgs84 (or --frame enu for metres)"
        )
    return "enu"


def _grid_args(args) -> dict:
    return {
        "step": _floats(args.step, (1, 3), "--step"),
        "bbox": None if args.bbox is None else _floats(args.bbox, 6, "--bbox"),
    }


def _grid(args) -> int:
    with _client(args) as bdf:
        grid = bdf.grid(args.name, **_grid_args(args))
    np.savez(args.out, x=grid.x, y=grid.y, z=grid.z, mean=grid.mean, std=grid.std, known=grid.known)
    print(f"wrote {args.out}: {grid.mean.shape[:3]} voxels, region version {grid.region_version}")
    return 0


def _tubes(args) -> int:
    with _client(args) as bdf:
        kw = dict(**_grid_args(args), component=args.component)
        if args.out.endswith((".geojson", ".json")):
            geo = bdf.tubes_geojson(args.name, args.max_std_mps, **kw)
            Path(args.out).write_text(json.dumps(geo))
            count = len(geo["features"])
        else:
            t = bdf.tubes(args.name, args.max_std_mps, **kw)
            np.savez(args.out, points=t.points, mean=t.mean, std=t.std, mask=t.mask, x=t.x, y=t.y, z=t.z)
            count = len(t.points)
    print(f"wrote {args.out}: {count} voxels with std < {args.max_std_mps} m/s")
    return 0


def _plot(args) -> int:
    from bdf.region.spec import RegionSpec
    from clients import plots

    with _client(args) as bdf:
        spec = RegionSpec.model_validate(bdf.region(args.name).spec)
        step = _floats(args.step, (1, 3), "--step") if args.step else None
        geo = {"title": args.name, "origin": (spec.origin.lat, spec.origin.lon)}
        if args.kind == "tube":
            step = step or (np.array(spec.spacing_m) / 2).tolist()
            tubes = bdf.tubes(args.name, args.max_std_mps, step)
            path = plots.plot_tube(tubes, args.max_std_mps, args.out, **geo)
        else:
            step = step or (np.array(spec.spacing_m) / 8).tolist()
            alt = min(max(args.alt_m, spec.lower[2]), spec.upper[2])
            bbox = [*spec.lower[:2], alt, *spec.upper[:2], alt]
            grid = bdf.grid(args.name, step, bbox, modes=args.kind == "modes")
            if args.kind == "slice":
                path = plots.plot_slice(grid, alt, args.component, args.out, **geo)
            elif args.kind == "modes":
                path = plots.plot_modes(grid, alt, args.out, **geo)
            else:
                path = plots.plot_arrows(grid, alt, args.out, **geo)
    print(f"wrote {path}")
    return 0


def _plan(args) -> int:
    from planner.costmap import CostWeights
    from planner.routes import plan_route
    from planner.search import Box

    weights = CostWeights(max_std_mps=args.max_std_mps, risk=args.w_risk, flow=args.w_flow, tube=args.tube)
    no_fly = tuple(Box(tuple(b[:3]), tuple(b[3:])) for b in (_floats(t, 6, "--no-fly") for t in args.no_fly))
    start, goal = _floats(args.start, 3, "--start"), _floats(args.goal, 3, "--goal")
    with _client(args) as bdf:
        plan = plan_route(
            bdf,
            args.region,
            start,
            goal,
            weights=weights,
            frame=_frame(bdf, args.region, np.array([start, goal]), args.frame),
            altitude_m=None
            if args.altitude_m is None
            else tuple(_floats(args.altitude_m, 2, "--altitude-m")),
            no_fly=no_fly,
            step=None if args.step is None else _floats(args.step, (1, 3), "--step"),
            planner=args.planner,
            **({} if args.time is None else {"time_s": args.time}),
            seed=args.seed,
            max_iterations=args.iterations,
            vehicle=_vehicle(args.vehicle),
        )
    print(plan.table())
    if args.out:
        Path(args.out).write_text(json.dumps(plan.geojson()))
        print(f"wrote {args.out}")
    if args.png:
        from planner.plot import plot_route

        print(f"wrote {plot_route(plan, args.png)}")
    if plan.route is None:
        budget = f"{args.iterations} iterations" if args.iterations else "the planning budget"
        print(f"bdf: no risk-aware route within {budget} ({plan.status})", file=sys.stderr)
        return NO_ROUTE
    return 0


def _vehicle(text: str):
    """``--vehicle``: a name (evtol, fixed-wing) or a JSON object of a vehicle's fields."""
    return json.loads(text) if text.lstrip().startswith("{") else text


def _assess(args) -> int:
    """``bdf assess``: a GeoJSON route's metrics on the map and the vehicle's verdict."""
    doc = json.loads(Path(args.route).read_text())
    with _client(args) as bdf:
        vehicle = None if args.vehicle is None else _vehicle(args.vehicle)
        got = bdf.assess_route(
            args.name, doc, max_std_mps=args.max_std_mps, vehicle=vehicle, route_name=args.route_name
        )
    width = max(len(k) for k in got["total"])
    for key, value in got["total"].items():
        print(f"{key:<{width}}  {value:12.4g}")
    checks = {k: v for k, v in got["envelope"].items() if isinstance(v, bool) and k != "flyable"}
    failed = [k.removesuffix("_ok") for k, ok in checks.items() if not ok]
    limits = ", ".join(
        f"{k} {'none' if v is None else f'{v:.4g}'}"
        for k, v in got["envelope"].items()
        if not isinstance(v, bool)
    )
    print(f"envelope: {'flyable' if not failed else 'not flyable: ' + ', '.join(failed)} ({limits})")
    return 0 if not failed else NOT_FLYABLE


def _data_fetch(args) -> int:
    from clients import samples

    print(samples.fetch_sample(args.name, args.cache))
    return 0


def _demo(args) -> int:
    from clients.demo import run

    run(Path(args.out), url=args.url, token=args.token)
    return 0


def _serve(args) -> int:
    """Settings: flags over environment (BDF_*) over the TOML file (--config / BDF_CONFIG).

    Flags travel as environment variables so that every uvicorn worker process builds the
    same settings.
    """
    # Requests are the unit of parallelism: one BLAS thread each (set before numpy loads;
    # worker processes inherit it), so BLAS threads do not compete with request threads.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    from service import server
    from service.settings import Settings
    from service.store import redacted

    if args.config:
        os.environ["BDF_CONFIG"] = str(args.config)
    for flag in ("host", "port", "workers", "store_url", "data_dir"):
        value = getattr(args, flag)
        if value is not None:
            os.environ[f"BDF_{flag.upper()}"] = str(value)
    settings = Settings()
    settings.check_bind()
    logging.basicConfig(level=settings.log_level.upper(), format="%(message)s", force=True)
    log = logging.getLogger("bdf.service")
    if settings.open:
        log.warning(
            "no tokens configured: the service is OPEN (every request has every scope) on %s; "
            "for local development only",
            settings.host,
        )
    log.info("store: %s", redacted(settings.store))
    server.run(settings)
    return 0


def _build(args) -> int:
    """A Dask build straight into the store (no HTTP): the service replicas see it at once."""
    from distributed import Client

    from service.build import build, local_cluster
    from service.store import RegionNotFound, UploadConflict

    store = _open_store(args)
    try:
        with contextlib.ExitStack() as stack:
            if args.scheduler:
                client = stack.enter_context(Client(args.scheduler))
            else:
                cluster = stack.enter_context(local_cluster(args.workers, args.worker_memory))
                client = stack.enter_context(Client(cluster))
            result = build(
                store,
                args.region,
                args.files,
                client,
                replace=not args.add,
                upload_id=args.upload_id,
                **{k: v for k in ("rows_per_task", "batch_rows") if (v := getattr(args, k)) is not None},
            )
    except (RegionNotFound, UploadConflict) as exc:
        raise ValueError(str(exc)) from None
    finally:
        store.close()
    rejected = ", ".join(f"{n} {why}" for why, n in result["rejected"].items() if n)
    print(
        f"{result['accepted']} accepted{f' ({rejected} rejected)' if rejected else ''}, "
        f"{result['tiles_updated']} tiles, region {args.region!r} version {result['region_version']}"
        f"{' (a replay: nothing changed)' if result['replayed'] else ''}; evidence "
        f"{result['seconds']['evidence']:.1f} s, commit {result['seconds']['commit']:.1f} s"
    )
    for warning in result.get("warnings", []):
        print(f"warning: {result['untracked']} {warning}", file=sys.stderr)
    return 0


def _open_store(args):
    """The store ``--store-url`` or ``--data-dir`` names, as ``bdf serve`` would open it."""
    from service.settings import Settings
    from service.store import open_store

    overrides = {k: v for k, v in (("store_url", args.store_url), ("data_dir", args.data_dir)) if v}
    return open_store(Settings(**overrides).store)


def _verify(args) -> int:
    """Check every region and stored tile; exit 1 if any has a problem."""
    from service.store import StoreError

    try:
        store = _open_store(args)
        try:
            report = store.verify()
        finally:
            store.close()
    except StoreError as exc:  # not a store at all, or one whose file is damaged
        print(f"bdf: error: {exc}", file=sys.stderr)
        return 1
    for region, problems in report.items():
        print(f"{region}: {'ok' if not problems else f'{len(problems)} problems'}")
        for problem in problems:
            print(f"  {problem}")
    found = sum(map(len, report.values()))
    print(f"{len(report)} regions, {found} problems")
    return 1 if found else 0


def store_options(p: argparse.ArgumentParser) -> None:
    """The options of commands that open the store directly (no HTTP)."""
    p.add_argument(
        "--store-url", help="sqlite:///dir or postgresql://... (default: $BDF_STORE_URL or --data-dir)"
    )
    p.add_argument("--data-dir", help="folder of the default SQLite store (default ./bdf-data)")


def build_parser() -> argparse.ArgumentParser:
    from planner.search import PLANNERS  # numpy and scipy only: ompl loads when a plan runs

    parser = argparse.ArgumentParser(prog="bdf", description="bdf-maps: 3D velocity maps with uncertainty.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    sub = parser.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="sample data").add_subparsers(dest="action", required=True)
    fetch = data.add_parser("fetch", help="download a sample data set (once) and print its path")
    fetch.add_argument("name", choices=["paris"], help="paris: 284,505 ADS-B state vectors (OpenSky)")
    fetch.add_argument(
        "--cache", type=Path, default=None, help="cache folder (default: $BDF_CACHE or ~/.cache/bdf-maps)"
    )
    fetch.set_defaults(run=_data_fetch)

    demo = sub.add_parser(
        "demo",
        help="learn the Paris map, print its accuracy, plan a route across its busiest flow, write plots",
    )
    demo.add_argument("--out", default="demo-output", help="folder for the plots (default: demo-output)")
    demo.add_argument(
        "--url",
        help="run against this live service (its 'paris' region as it is, else built there) "
        "instead of starting one on SQLite in --out",
    )
    demo.add_argument(
        "--token", default=os.environ.get("BDF_TOKEN"), help="bearer token (default $BDF_TOKEN)"
    )
    demo.set_defaults(run=_demo)

    serve = sub.add_parser(
        "serve",
        help="run the HTTP service (uvicorn)",
        description="Run the HTTP service. Every setting also reads BDF_<NAME> from the environment "
        "and the TOML file named by --config or BDF_CONFIG (see service/settings.py).",
    )
    serve.add_argument("--host", help="address to bind (default 127.0.0.1; others need tokens)")
    serve.add_argument("--port", type=int, help="port (default 8000)")
    serve.add_argument("--workers", type=int, help="worker processes (default 1)")
    serve.add_argument(
        "--store-url", help="sqlite:///dir or postgresql://... (default: SQLite in --data-dir)"
    )
    serve.add_argument("--data-dir", help="folder of the default SQLite store (default ./bdf-data)")
    serve.add_argument("--config", type=Path, help="TOML settings file")
    serve.set_defaults(run=_serve)

    text = "learn a region from observation files of any size on a Dask cluster, straight into the store"
    p = sub.add_parser(
        "build",
        help=text,
        description=f"{text[0].upper()}{text[1:]}. Files (Parquet, Arrow IPC, CSV, gzipped CSV) hold "
        "the columns an upload takes (x,y,z or lat,lon,alt_m; ve,vn,vu; optional input_noise_std, "
        "sample_weight, track and t) or ADS-B state vectors (traffic/OpenSky Impala or OpenSky file "
        "columns). "
        "Workers read slices of them (Parquet row groups, row ranges, CSV byte ranges) in bounded "
        "batches, so on a cluster every worker must see the paths. The build is one exactly-once "
        "upload: re-running it is a replay.",
    )
    p.add_argument("files", nargs="+", type=Path, help=".parquet, .arrow, .csv or .csv.gz files")
    p.add_argument("--region", required=True, help="an existing region")
    store_options(p)
    p.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://scheduler:8786 (default: local)")
    p.add_argument(
        "--workers", type=int, default=os.cpu_count(), help="local worker processes (default: cores)"
    )
    p.add_argument(
        "--worker-memory",
        default="auto",
        help="memory limit per local worker, e.g. 1GB (default: RAM / workers)",
    )
    p.add_argument("--rows-per-task", type=int, help="rows per task (default 500,000)")
    p.add_argument(
        "--batch-rows", type=int, help="rows a worker holds at once (default 200,000; about 1 kB each)"
    )
    p.add_argument("--add", action="store_true", help="add to the map instead of replacing it")
    p.add_argument("--upload-id", help="ledger id (default: derived from the files' content)")
    p.set_defaults(run=_build)

    p = sub.add_parser(
        "verify",
        help="check a store's regions and tiles (checksums, decoding, finite and plausible statistics)",
        description="Reads every region and every stored tile, checks the tile against the checksum "
        "stored with it, decodes it and checks that its statistics are finite and within the "
        "region's envelope. Lists the problems and exits 1 if there are any.",
    )
    store_options(p)
    p.set_defaults(run=_verify)

    def connection(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
        p.add_argument(
            "--url",
            default=os.environ.get("BDF_URL", f"http://127.0.0.1:{os.environ.get('BDF_PORT', '8000')}"),
            help="the service (default $BDF_URL, else http://127.0.0.1:$BDF_PORT, port 8000 by default)",
        )
        p.add_argument(
            "--token", default=os.environ.get("BDF_TOKEN"), help="bearer token (default $BDF_TOKEN)"
        )
        return p

    def client(name: str, help: str, **kw) -> argparse.ArgumentParser:
        return connection(sub.add_parser(name, help=help, description=help, **kw))

    def grid_options(p: argparse.ArgumentParser, step_required: bool = True) -> None:
        p.add_argument("--step", required=step_required, help="voxel size: dx,dy,dz or one number (m)")
        p.add_argument("--bbox", help="xmin,ymin,zmin,xmax,ymax,zmax in region ENU metres (default: all)")

    region = sub.add_parser("region", help="create, list, show or delete regions")
    actions = region.add_subparsers(dest="action", required=True)
    for action, text in (
        ("list", "list the regions"),
        ("show", "a region's spec and counters as JSON"),
        ("delete", "delete a region and its map"),
        ("create", "create a region from a spec"),
    ):
        p = connection(actions.add_parser(action, help=text, description=text))
        if action == "create":
            p.add_argument(
                "spec", type=Path, help="JSON file of the region spec (bdf.region.spec.RegionSpec)"
            )
        elif action != "list":
            p.add_argument("name", help="region name")
        p.set_defaults(
            run={
                "list": _region_list,
                "show": _region_show,
                "delete": _region_delete,
                "create": _region_create,
            }[action]
        )

    for name, text in (
        ("upload", "add the observations in a file to the region's map (chunked, exactly once)"),
        ("fit", "replace the region's map with the observations in a file"),
        ("retract", "undo the upload of a file exactly (the same file and --chunk-size; admin scope)"),
    ):
        p = client(
            name,
            text,
            epilog="Files: CSV, Parquet or JSON(.gz) with x,y,z or lat,lon,alt_m and "
            "ve,vn,vu columns (and track, t: each row's track id and time in seconds, so the "
            "service weighs a track's correlated rows), or ADS-B state vectors (OpenSky/traffic "
            "columns; tracks by icao24 and callsign).",
        )
        p.add_argument("name", help="region name")
        p.add_argument("file", type=Path, help="observations file")
        if name != "fit":
            p.add_argument(
                "--chunk-size", type=int, default=200_000, help="rows per request (default 200000)"
            )
        p.add_argument(
            "--progress",
            action=argparse.BooleanOptionalAction,
            default=None,
            help="progress bar (default: on a terminal)",
        )
        p.set_defaults(run=lambda args, kind=name: _send_observations(args, kind))

    p = client("health", "check that the service answers and its store is reachable (exit 0)")
    p.set_defaults(run=_health)

    p = client("query", "predictive mean and std at points, as CSV")
    p.add_argument("name", help="region name")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--points", help="'x,y,z;x,y,z;...' (or lat,lon,alt_m with --frame wgs84)")
    src.add_argument("--file", type=Path, help="CSV/Parquet/JSON with x,y,z or lat,lon,alt_m columns")
    p.add_argument("--frame", choices=["enu", "wgs84"], help="frame of --points (default enu: metres)")
    p.add_argument("--out", help="CSV file (default: stdout)")
    p.set_defaults(run=_query)

    p = client("grid", "mean and std on a voxel grid, to an .npz file")
    p.add_argument("name", help="region name")
    grid_options(p)
    p.add_argument("--out", required=True, help=".npz file (x, y, z, mean, std, known)")
    p.set_defaults(run=_grid)

    p = client("tubes", "the voxels whose std is below a bound, to .npz or .geojson")
    p.add_argument("name", help="region name")
    p.add_argument("--max-std-mps", type=float, required=True, help="tube bound on the std (m/s)")
    grid_options(p)
    p.add_argument("--component", choices=["all", "e", "n", "u"], default="all", help="whose std is bounded")
    p.add_argument("--out", required=True, help=".npz (points, mean, std, mask, axes) or .geojson")
    p.set_defaults(run=_tubes)

    p = client("plot", "PNG pictures of a map: slice, flow arrows, or the 3D tube")
    p.add_argument("name", help="region name")
    p.add_argument(
        "--kind",
        choices=["slice", "arrows", "modes", "tube"],
        default="slice",
        help="slice: mean and std of a component (paper fig. 4); arrows: flow over std; "
        "modes: each traffic class's flow (directional regions); "
        "tube: the tube in 3D coloured by vertical velocity (paper fig. 7)",
    )
    p.add_argument("--alt-m", type=float, default=1000.0, help="slice altitude, region ENU up (default 1000)")
    p.add_argument("--component", choices=["e", "n", "u"], default="e", help="slice component (default e)")
    p.add_argument("--max-std-mps", type=float, default=5.0, help="tube bound (default 5)")
    p.add_argument("--step", help="voxel size (default: an eighth of the hinge spacing; tube: a half)")
    p.add_argument("--out", required=True, help="PNG file")
    p.set_defaults(run=_plot)

    p = client("plan", "a risk-aware route on the velocity tubes, and the shortest path beside it")
    p.add_argument("--region", required=True, help="region name")
    p.add_argument("--start", required=True, help="x,y,z ENU metres (or lat,lon,alt_m with --frame wgs84)")
    p.add_argument("--goal", required=True, help="as --start")
    p.add_argument("--frame", choices=["enu", "wgs84"], help="frame of --start/--goal (default enu: metres)")
    p.add_argument("--max-std-mps", type=float, required=True, help="tube bound on the largest std (m/s)")
    p.add_argument(
        "--tube",
        choices=["hard", "soft", "off"],
        default="hard",
        help="hard: never leave the tube; soft: a penalty; off: risk only (default hard)",
    )
    p.add_argument("--w-risk", type=float, default=1.0, help="weight of the integrated risk (default 1)")
    p.add_argument("--w-flow", type=float, default=0.5, help="weight of the flow mismatch (default 0.5)")
    p.add_argument(
        "--vehicle",
        default="evtol",
        help="evtol, fixed-wing, or a JSON object of cruise_mps, min_turn_radius_m, max_climb_deg, "
        "max_descent_deg, floor_m, ceiling_m (default evtol): the routes are made flyable by it",
    )
    p.add_argument("--altitude-m", help="min,max altitude band (default: the region's)")
    p.add_argument("--no-fly", action="append", default=[], help="xmin,ymin,zmin,xmax,ymax,zmax (repeatable)")
    p.add_argument("--step", help="cost-map voxel size (default: a quarter of the hinge spacing)")
    p.add_argument(
        "--planner",
        default="bitstar",
        choices=PLANNERS,
        help="default bitstar",
    )
    p.add_argument("--time", type=float, help="the plan's budget in seconds (default 5)")
    p.add_argument("--seed", type=int, help="OMPL seed (reproducible with --iterations)")
    p.add_argument("--iterations", type=int, help="stop after this many iterations instead of --time")
    p.add_argument("--out", help="GeoJSON file with both routes and their metrics")
    p.add_argument("--png", help="PNG with the top view over the tube and the altitude profile")
    p.set_defaults(run=_plan)

    p = client("assess", "a route's metrics on the map and whether a vehicle can fly it")
    p.add_argument("name", help="region name")
    p.add_argument(
        "route", help="GeoJSON file: a LineString Feature or a collection of one ([lon, lat, alt_m])"
    )
    p.add_argument("--max-std-mps", type=float, help="tube bound (default: the file's max_std_mps property)")
    p.add_argument("--vehicle", help="evtol, fixed-wing or a JSON object (default: the file's, else evtol)")
    p.add_argument(
        "--route",
        dest="route_name",
        help="the route of a collection to assess, by its name (bdf plan writes two)",
    )
    p.set_defaults(run=_assess)
    return parser


#: options whose value may start with a minus (a negative coordinate first)
NUMERIC_OPTIONS = ("--start", "--goal", "--points", "--bbox")


def _glued(argv: list[str]) -> list[str]:
    """``--start -16604,29825,1750`` as ``--start=-16604,...``: argparse would take a value
    starting with a minus for an option (and say "expected one argument")."""
    out, rest = [], list(argv)
    while rest:
        arg = rest.pop(0)
        negative = bool(rest) and rest[0][:1] == "-" and (rest[0][1:2].isdigit() or rest[0][1:2] == ".")
        if arg in NUMERIC_OPTIONS and negative:
            arg = f"{arg}={rest.pop(0)}"
        out.append(arg)
    return out


def _validation_messages(exc: pydantic.ValidationError) -> str:
    """What is wrong, by field, without the values given."""
    parts = []
    for error in exc.errors():
        where = ".".join(map(str, error["loc"]))
        parts.append(f"{where}: {error['msg']}" if where else error["msg"])
    return "; ".join(parts)


def _parser_of(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The (sub)command's own parser of ``args``: its usage and options, for its errors."""
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        name = getattr(args, subs[0].dest, None) if subs else None
        if name not in (subs[0].choices if subs else {}):
            return parser
        parser = subs[0].choices[name]


def main(argv=None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(_glued(sys.argv[1:] if argv is None else list(argv)))
    if extra:  # told by the command that got them, with its own usage, and the likely option
        own = _parser_of(parser, args)
        options = [o for action in own._actions for o in action.option_strings]
        near = difflib.get_close_matches(extra[0].split("=")[0], options, n=1)
        own.error(
            f"unrecognized arguments: {' '.join(extra)}" + (f" (did you mean {near[0]}?)" if near else "")
        )
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    from clients.sdk import BDFError

    try:
        return args.run(args)
    except BDFError as exc:
        hint = " (give the service's token: --token or BDF_TOKEN)" if exc.status in (401, 403) else ""
        print(f"bdf: error: {exc}{hint}", file=sys.stderr)
        return 2 if 400 <= exc.status < 500 else 1
    except FileNotFoundError as exc:
        print(f"bdf: error: no such file: {exc.filename or exc}", file=sys.stderr)
        return 2
    except pydantic.ValidationError as exc:  # its messages only: the input may hold secrets (tokens)
        print(f"bdf: error: {_validation_messages(exc)}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"bdf: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, RuntimeError, subprocess.CalledProcessError) as exc:
        print(f"bdf: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
