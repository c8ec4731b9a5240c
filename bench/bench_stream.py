"""Maps under a stream of uploads, on real ADS-B traffic around Paris (issue 35).

    .venv/bin/python bench/bench_stream.py [--directions 1,8] [--uploads 1,10,100]
        [--seconds 30] [--parts calibration,refresh,staleness] [--uploaders 8] [--rates 0,2,0.1]
        [--no-append]

Data: the flight split of the core benchmark (`clients.samples.load_paris`: 20 % of whole
flights held out, seed 0), track weights (`bdf.ingest.track_weights` on the core
benchmark's 4 km x 4 km x 1 km cells, as bench_core.py). Region: the demo's
(`clients.samples.paris_demo_region`, 2 km x 2 km x 1 km hinges, cutoff 1e-9), with 1 and with
8 heading sectors.

1. Calibration: the region built in process through `RegionMaps` on SQLite from the
   training flights as 1, 10 and 100 uploads (flights in a shuffled order, cut at random
   sizes), the newest version served; against one `BayesianDynamicField` fitted on all the
   data at once (the single fit): held-out 95 % coverage per component, MSLL, and for the
   directional map the mixture's MSLL and the conditional coverage and RMSE (each test
   point's own heading sector); the largest difference of the means from the single fit's
   (over the climatology std) and of ln(alpha / beta).
2. Refreshes: a cold map (a new `RegionMaps` and fresh caches: every tile decoded, the
   support's symbolic analysis, the search from nothing) against the refresh after a
   1,000-row upload as the background computes it (warm: only the changed tiles decoded,
   the search from where the last one pointed, stopping within a nat of the optimum), then
   its settling pass (the optimum itself, when no newer version waits); seconds,
   factorisations and the gap, against the cold map and against the same map computed at
   the optimum found, given (no search: what staying calibrated costs).
3. Staleness: `bdf serve` (SQLite, defaults) holding each region; 8 uploaders post
   1,000-row batches (as fast as they can, rate 0: the stress, the region's whole data
   again every few seconds; or ``--rates`` uploads per second in all: a busy fleet) and 8
   readers query 1,000 points, for ``--seconds``; every answer's
   X-Region-Versions-Behind, X-Region-Seconds-Behind, X-Region-Refreshes-Behind and
   X-Region-Evidence-Gap, and the refreshes (and settling passes, and those a newer version
   abandoned) done during the load and their time (/metrics). Target: at most one refresh
   behind: an answer lacks only versions written since the refresh under way began, so no
   map finished since the first of them was written (refreshes behind 0), or only the one
   under way then (1). In seconds that is the rest of that refresh and the next: when
   uploads come less often than refreshes, one refresh plus the wait for a settling pass
   to give up (a factorisation, or the selected inversion); about two under a continuous
   stream.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import logging
import platform
import re
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import publish, rows_table  # bench/ is on the path when run as a script
from bench_service import arrow_points

from bdf import ingest, metrics, sparse
from bdf.region.evidence import region_total
from bdf.region.map import RegionMap, region_field
from clients import samples
from clients.local import LocalService
from clients.samples import PARIS_SPACING_M
from service.maps import RegionMaps
from service.store import open_store

ARROW = "application/vnd.apache.arrow.stream"


def split():
    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    train = obs.subset(~test)
    weight = train.track_weights(1 / np.asarray(PARIS_SPACING_M) ** 2)
    return train, weight, obs.subset(test), lower, upper


def held_out(spec, post, train, test) -> dict:
    """Held-out accuracy of a posterior (the served map's, or the single fit's)."""
    modes = RegionMap(spec, post).predict_modes(test.X)
    mean, std, _ = RegionMap(spec, post).predict(test.X, modes=modes)
    cov = metrics.coverage(test.V, mean, std, axis=0)
    row = {
        "cov95 e": cov[0],
        "cov95 n": cov[1],
        "cov95 u": cov[2],
        "MSLL": float(metrics.msll(test.V, mean, std, train.V.mean(0), train.V.std(0))),
    }
    if not spec.one_class:
        own = spec.sectors.classify(test.V)
        rows = np.arange(len(test.V))
        row["mixture MSLL"] = metrics.mixture_msll(
            test.V, modes.share, modes.mean, modes.std, train.V.mean(0), train.V.std(0)
        )
        row["cond. cov95"] = float(metrics.coverage(test.V, modes.mean[rows, own], modes.std[rows, own]))
        cond = metrics.coverage(test.V, modes.mean[rows, own], modes.std[rows, own], axis=0)
        row["cond. cov95 e, n, u"] = ", ".join(f"{c:.3f}" for c in cond)
        row["cond. RMSE"] = float(metrics.rmse(test.V, modes.mean[rows, own]))
    return row


def calibration(directions, counts, train, weight, test, lower, upper, tmp) -> tuple[list[dict], dict]:
    spec = samples.paris_demo_region(lower, upper, directions=directions)
    t0 = time.perf_counter()
    single = region_field(spec).fit(train.X, train.V, sample_weight=weight).posterior_
    single_s = time.perf_counter() - t0
    climate = np.sqrt((train.V**2).mean(0))
    probe = np.random.default_rng(2).uniform(spec.lower, spec.upper, (20_000, 3))
    want = RegionMap(spec, single).predict(probe)[0]
    rows = [{"directions": directions, "built by": "single fit", **held_out(spec, single, train, test)}]
    timing = {"single fit [s]": single_s}
    flights = np.unique(train.flight)
    for uploads in counts:
        store = open_store(f"sqlite:///{tmp}/d{directions}-u{uploads}")
        store.create_region(spec)
        maps = RegionMaps(store, cache_mb=2048)
        rng = np.random.default_rng(uploads)
        order = rng.permutation(flights)
        cuts = np.sort(rng.choice(np.arange(1, len(order)), uploads - 1, replace=False))
        t0 = time.perf_counter()
        for k, part in enumerate(np.split(order, cuts)):
            rows_k = np.isin(train.flight, part)
            maps.upload(spec.name, f"u{k}", train.X[rows_k], train.V[rows_k], sample_weight=weight[rows_k])
        state = maps.refresh(spec.name)
        build_s = time.perf_counter() - t0
        post = state.posterior
        got = RegionMap(spec, post).predict(probe)[0]
        lam = np.log(post.alpha / post.beta) - np.log(single.alpha / single.beta)
        rows.append(
            {
                "directions": directions,
                "built by": f"{uploads} uploads",
                **held_out(spec, post, train, test),
                "max |mean - single| / clim. std": float(np.max(np.abs(got - want) / climate)),
                "max |ln lam - single|": float(np.abs(lam).max()),
                "refreshes": maps.stats.count,
                "skipped versions": maps.stats.skipped,
                "build [s]": build_s,
            }
        )
        maps.close()
        store.close()
    return rows, timing


class _SearchPoints(logging.Handler):
    """The points ``x = ln lam`` the first search evaluated (:mod:`bdf.hyperparameters`'s debug log,
    up to its end: the map with one class's)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.x, self.ended = [], False

    def emit(self, record):
        if record.msg.startswith("evidence fit"):
            self.ended = True
        elif record.msg.startswith("x=") and not self.ended:
            self.x.append(record.args[0])


def refreshes(directions, train, weight, lower, upper, tmp, rounds=3) -> dict:
    """Cold map against warm refreshes after 1,000-row uploads (medians over ``rounds``)."""
    spec = samples.paris_demo_region(lower, upper, directions=directions)
    store = open_store(f"sqlite:///{tmp}/refresh-d{directions}")
    store.create_region(spec)
    rng = np.random.default_rng(5)
    extra = rng.permutation(len(train.X))[: 1000 * rounds]
    keep = np.ones(len(train.X), bool)
    keep[extra] = False
    RegionMaps(store).upload(spec.name, "base", train.X[keep], train.V[keep], sample_weight=weight[keep])
    cold, cold_f = [], []
    for _ in range(rounds):
        sparse.lattice_stencil.cache_clear()  # a new process: no analysis, no decoded tiles, no optimum
        maps = RegionMaps(store, cache_mb=2048)
        maps.refresher.start = lambda *a: None  # nor the store's record of the optimum
        t0 = time.perf_counter()
        state = maps.refresh(spec.name)
        cold.append(time.perf_counter() - t0)
        cold_f.append(state.posterior.factorisations)
        maps.close()
    maps = RegionMaps(store, cache_mb=2048)
    maps.refresh(spec.name)
    maps.refresher.schedule = lambda region: None  # each refresh is timed here, not in the background
    quick, quick_f, gaps, settle, settle_f, upload, fixed = [], [], [], [], [], [], []
    search = logging.getLogger("bdf.hyperparameters")
    for r in range(rounds):
        rows = extra[1000 * r : 1000 * (r + 1)]
        t0 = time.perf_counter()
        maps.upload(spec.name, f"extra{r}", train.X[rows], train.V[rows], sample_weight=weight[rows])
        upload.append(time.perf_counter() - t0)
        search.setLevel(logging.DEBUG)
        search.addHandler(points := _SearchPoints())  # the map with one class's search
        t0 = time.perf_counter()  # what the background refresh computes first: within a nat
        state = maps.refresher.compute(spec.name, store.region(spec.name).version)
        quick.append(time.perf_counter() - t0)
        quick_f.append(state.posterior.factorisations)
        gaps.append(state.posterior.evidence_gap)
        search.removeHandler(points)
        search.addHandler(settling := _SearchPoints())
        t0 = time.perf_counter()  # then, no newer version waiting: settled
        state = maps.refresh(spec.name)
        settle.append(time.perf_counter() - t0)
        search.removeHandler(settling)
        settle_f.append(state.posterior.factorisations)
        # the same map at the optimum found, given: what a refresh without the search costs
        post = state.posterior
        evidence = region_total(spec, store.snapshot(spec.name).evidence)
        t0 = time.perf_counter()
        region_field(spec, post.alpha, post.beta).set_evidence(evidence).posterior_.compact()
        fixed.append(time.perf_counter() - t0)
    maps.close()
    store.close()
    given = float(np.median(fixed))
    return {
        "directions": directions,
        "hinges": spec.grid.size,
        "cold map [s]": float(np.median(cold)),
        "cold factorisations": int(np.median(cold_f)),
        "upload of 1,000 rows [s]": float(np.median(upload)),
        "at the optimum given [s]": given,
        "refresh within a nat [s]": float(np.median(quick)),
        "its factorisations": int(np.median(quick_f)),
        "its gap [nats]": float(np.median(gaps)),
        "settling pass [s]": float(np.median(settle)),
        "its factorisations ": int(np.median(settle_f)),
        "searches' points (ln lam): within a nat; settling": " ".join(f"{x:.7f}" for x in points.x)
        + "; "
        + " ".join(f"{x:.7f}" for x in settling.x),
        "refresh / cold": float(np.median(quick) / np.median(cold)),
        "refresh / at the optimum given": float(np.median(quick)) / given,
        "(refresh + settling) / at the optimum given": float(np.median(np.add(quick, settle))) / given,
    }


async def staleness(url, train, weight, seconds, uploaders=8, readers=8, rate=0.0) -> dict:
    rng = np.random.default_rng(11)
    queries = arrow_points(rng.uniform(*QUERY_BOX, (1000, 3)))
    behind, behind_s, refreshes, versions, gaps = [], [], [], [], []
    stop = time.monotonic() + seconds
    async with httpx.AsyncClient(base_url=url, timeout=600) as c:

        async def upload(k):
            j, began = 0, time.monotonic()
            while time.monotonic() < stop:
                if rate > 0:  # uploader k of n: its j-th upload at (j n + k) / rate, a steady stream
                    await asyncio.sleep(max(began + (j * uploaders + k) / rate - time.monotonic(), 0.0))
                    if time.monotonic() >= stop:
                        break
                rows = rng.integers(0, len(train.X), 1000)
                r = await c.post(
                    "/v1/regions/paris/observations",
                    content=arrow_points(
                        train.X[rows], train.V[rows], None if weight is None else weight[rows]
                    ),
                    headers={"Content-Type": ARROW, "Idempotency-Key": f"stream-{k}-{j}"},
                )
                assert r.status_code == 200, r.text
                j += 1

        async def read():
            while time.monotonic() < stop:
                r = await c.post(
                    "/v1/regions/paris/query",
                    content=queries,
                    headers={"Content-Type": ARROW, "Accept": ARROW},
                )
                assert r.status_code == 200, r.text
                behind.append(int(r.headers["X-Region-Versions-Behind"]))
                behind_s.append(float(r.headers["X-Region-Seconds-Behind"]))
                refreshes.append(int(r.headers["X-Region-Refreshes-Behind"]))
                versions.append(int(r.headers["X-Region-Version"]))
                gaps.append(float(r.headers["X-Region-Evidence-Gap"]))

        before = map_metrics((await c.get("/metrics")).text)
        await asyncio.gather(*(upload(k) for k in range(uploaders)), *(read() for _ in range(readers)))
        after = map_metrics((await c.get("/metrics")).text)
    value = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}  # during the load
    settles = value.get("bdf_map_settles", 0)
    quick = value.get("bdf_map_refreshes", 0) - settles  # the refreshes of a new version
    quick_s = (value.get("bdf_map_refresh_seconds", 0) - value.get("bdf_map_settling_seconds", 0)) / max(
        quick, 1
    )
    return {
        "answers": len(behind),
        "versions written": max(versions, default=0) + max(behind[-1:], default=0),
        "versions behind p50": float(np.percentile(behind, 50)),
        "versions behind p95": float(np.percentile(behind, 95)),
        "seconds behind p50": float(np.percentile(behind_s, 50)),
        "seconds behind p95": float(np.percentile(behind_s, 95)),
        "seconds behind max": float(np.max(behind_s)),
        "seconds behind max / refresh": float(np.max(behind_s)) / quick_s if quick else float("nan"),
        "refreshes behind p50 / max": f"{np.percentile(refreshes, 50):g} / {np.max(refreshes)}",
        "evidence gap p50 / max [nats]": f"{np.percentile(gaps, 50):.3g} / {np.max(gaps):.3g}",
        "refreshes done": int(quick),
        "their mean [s]": quick_s,
        "settling passes": int(settles),
        "abandoned": int(value.get("bdf_map_settles_abandoned", 0)),
        "versions skipped": int(value.get("bdf_map_versions_skipped", 0)),
    }


def map_metrics(text: str) -> dict:
    return {m[0]: float(m[1]) for m in re.findall(r"^(bdf_map_\w+?)(?:_total)? ([0-9.e+-]+)$", text, re.M)}


def served(directions, train, weight, lower, upper, data, seconds, uploaders=8, rate=0.0) -> dict:
    """:func:`staleness` on a service holding the region of ``directions`` built from the
    training data (its first map computed before the load starts), with the rows' track
    weights, or (``weight`` None) without: the raw rows, whose evidence maximum lies at the
    search's floor (consecutive samples of a track are far from independent), where every
    refresh searches from the anchor."""
    spec = samples.paris_demo_region(lower, upper, directions=directions)
    with LocalService(data) as svc:
        with httpx.Client(base_url=svc.url, timeout=900) as c:
            c.post("/v1/regions", json=spec.model_dump(mode="json")).raise_for_status()
            c.post(
                "/v1/regions/paris/observations",
                content=arrow_points(train.X, train.V, weight),
                headers={"Content-Type": ARROW, "Idempotency-Key": "base"},
            ).raise_for_status()
            while True:  # the first map takes longer than a request's deadline: 503 until it is ready
                r = c.post(
                    "/v1/regions/paris/query",
                    params={"min_version": 1},
                    content=arrow_points(train.X[:10]),
                    headers={"Content-Type": ARROW},
                )
                if r.status_code != 503:
                    break
                time.sleep(float(r.headers["retry-after"]))
            r.raise_for_status()
        return {
            "directions": directions,
            "track weights": weight is not None,
            "uploaders": uploaders,
            "uploads per s": rate or "as fast as they can",
            **asyncio.run(staleness(svc.url, train, weight, seconds, uploaders, rate=rate)),
        }


QUERY_BOX = ([-30_000.0, -30_000.0, 0.0], [30_000.0, 30_000.0, 5_000.0])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--directions", default="1,8")
    parser.add_argument("--uploads", default="1,10,100")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--parts", default="calibration,refresh,staleness")
    parser.add_argument("--uploaders", type=int, default=8)
    parser.add_argument(
        "--rates", default="0,2,0.1", help="uploads per second in all; 0: as fast as they can"
    )
    parser.add_argument("--no-append", action="store_true")
    args = parser.parse_args(argv)
    parts = args.parts.split(",")
    directions = [int(d) for d in args.directions.split(",")]
    counts = [int(u) for u in args.uploads.split(",")]
    train, weight, test, lower, upper = split()
    given = sys.argv[1:] if argv is None else argv
    report = [
        f"\n## Calibrated under a stream of uploads ({datetime.date.today()}, {platform.machine()}, "
        f"bench/bench_stream.py)\n",
        f"Command: `.venv/bin/python bench/bench_stream.py {' '.join(given)}`. "
        f"Paris flight split: {len(train.X)} training, "
        f"{len(test.X)} held-out points; the demo's region.\n",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        if "calibration" in parts:
            rows = []
            for d in directions:
                part, timing = calibration(d, counts, train, weight, test, lower, upper, tmp)
                rows += part
                print(rows_table(part), timing, flush=True)
            report += ["Held-out accuracy of the served map, built by uploads, against the single fit:", ""]
            report += rows_table(rows).splitlines()
        if "refresh" in parts:
            timing_rows = [refreshes(d, train, weight, lower, upper, tmp) for d in directions]
            print(rows_table(timing_rows), flush=True)
            report += ["", "Refresh after a 1,000-row upload against a cold map (medians of 3):", ""]
            report += rows_table(timing_rows).splitlines()
        if "staleness" in parts:
            stale = [
                served(d, train, w, lower, upper, Path(tmp) / f"s{d}{k}{r}", args.seconds, args.uploaders, r)
                for d in directions
                for r in [float(r) for r in args.rates.split(",")]
                for k, w in enumerate([weight] if r else [weight, None])
            ]
            print(rows_table(stale), flush=True)
            report += [
                "",
                f"Staleness under {args.uploaders} uploaders (1,000 rows each; all uploads per s: "
                f"{args.rates}, 0 as fast as they can) and 8 readers (1,000 "
                f"points) for {args.seconds:g} s, `bdf serve` on SQLite (defaults):",
                "",
                *rows_table(stale).splitlines(),
            ]
    publish(report, not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
