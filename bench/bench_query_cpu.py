"""Server CPU per query of this tree against another commit, or against this tree's map of
another number of sectors, side by side on one machine (these machines are noisy: the ratio
is the figure, not either time).

    .venv/bin/python bench/bench_query_cpu.py (--against 9d1bbb5 | --against-directions 8)
        [--directions 1] [--model-directions M] [--seconds 8] [--connections 4] [--rounds 2]
        [--profile] [--no-append]

Each side is ``bdf serve`` (2 uvicorn workers, SQLite) of its own checkout (the other commit
in a temporary git worktree; this tree again with ``--against-directions``), holding the
demo's Paris map (``paris_demo_region``, fitted over HTTP from the flight split's training
rows); ``wrk`` POSTs the same 1,000 held-out points as Arrow on ``--connections`` for
``--seconds``, the two sides alternating for ``--rounds``. Reported: requests/s, p50, the
CPU of each server's process tree per request (/proc) and their ratio (this tree over the
other), and the least busy worker's CPU in its least even round (0 when the other worker
held every connection). ``--profile``: one more run of this tree under py-spy (every
worker, 200 Hz), and where a query's time goes: the share of
the samples inside the query's work that lie in each of :data:`PROFILED`.
"""

from __future__ import annotations

import contextlib
import datetime
import subprocess
import sys
import tempfile
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_core import arguments, publish, rows_table  # bench/ is on the path as a script
from bench_service import QUERY, arrow_points, build, query_body, wrk_load

from bdf import ingest
from clients.local import LocalService
from clients.samples import load_paris, paris_demo_region
from service.wire import ARROW

ROOT = Path(__file__).resolve().parents[1]
#: what --profile reports (py-spy frame names): the compute, then the request's other work
PROFILED = {
    "the map's answer": "RegionMaps.predict",
    "  the midpoint-lattice gather (variance, data density)": "Posterior._midpoints",
    "  the mean's gather": "Posterior.mean",
    "  known's normalisation": "_normalised",
    "  a mixture's gathers (every mode's tables)": "Mixture._gather",
    "  a mixture's moments": "Mixture._moments",
    "the region read (and ETag)": "MapAnswer.region_or_304",
    "decoding the Arrow body": "read_query",
    "encoding the answer": "encode_points",
}


def profile(pid: int, run) -> dict:
    """py-spy over the process tree ``pid`` while ``run()`` loads it: each of
    :data:`PROFILED`'s share of the samples in the query's work (``query.<locals>.step``)."""
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "raw.txt"
        spy = subprocess.Popen(
            ["py-spy", "record", "-p", str(pid), "--subprocesses", "-f", "raw", "-r", "200", "-o", str(raw)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        run()
        spy.send_signal(2)  # py-spy writes its samples on SIGINT
        spy.wait(60)
        counts = {name: 0 for name in PROFILED}
        busy = 0
        for line in raw.read_text().splitlines():
            stack, _, n = line.rpartition(" ")
            frames = {f.split(" (")[0] for f in stack.split(";")}
            if "query.<locals>.step" not in frames:
                continue
            busy += int(n)
            for name, frame in PROFILED.items():
                counts[name] += int(n) * (frame in frames)
    return {name: 100.0 * c / max(busy, 1) for name, c in counts.items()}


@contextlib.contextmanager
def served(checkout: Path, data: Path, body: dict, obs, test):
    """``bdf serve`` of ``checkout`` (its own modules first on the path) with the map of
    spec ``body`` built."""
    env = {"BDF_WORKERS": "2", "BDF_LOG_LEVEL": "warning", "PYTHONPATH": str(checkout)}
    env["BDF_REQUEST_TIMEOUT_S"] = "600"  # a fresh checkout compiles its kernels during the first fit
    with contextlib.chdir(checkout), LocalService(data, env) as svc:
        build(svc.url, body, obs, test)
        yield svc


def main(argv=None) -> int:
    parser = arguments(__doc__.splitlines()[0])
    against = parser.add_mutually_exclusive_group(required=True)
    against.add_argument("--against", help="the other commit (any git revision)")
    against.add_argument(
        "--against-directions", type=int, help="the other side: this tree's map of this many sectors"
    )
    parser.add_argument("--directions", type=int, default=1)
    parser.add_argument(
        "--model-directions",
        type=int,
        help="this tree's model sectors (default: the spec's); the other commit gets the spec without "
        "them if it predates them (its one class: the paper's model)",
    )
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--connections", type=int, default=4)
    parser.add_argument("--points", type=int, default=1000, help="points per query (1: the fixed cost)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--profile", action="store_true", help="where this tree's query time goes (py-spy)")
    args = parser.parse_args(argv)
    obs, lower, upper = load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    spec = paris_demo_region(lower, upper, directions=args.directions, model_directions=args.model_directions)
    here = spec.model_dump(mode="json")
    body = (
        query_body(obs.X[test], "arrow")
        if args.points == 1000
        else (arrow_points(obs.X[test][: args.points]), ARROW)
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        if args.against_directions is not None:
            other, label = ROOT, f"this tree, {args.against_directions} sectors"
            there = paris_demo_region(lower, upper, directions=args.against_directions).model_dump(
                mode="json"
            )
        else:
            other, label = Path(tmp) / "other", args.against
            older = subprocess.run(
                ["git", "-C", str(ROOT), "show", f"{args.against}:bdf/region/spec.py"],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            there = (
                here
                if "model_directions" in older
                else {k: v for k, v in here.items() if k != "model_directions"}
            )
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(other), args.against],
                check=True,
            )
            stack.callback(
                subprocess.run, ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)]
            )
        sides = {
            "this tree": stack.enter_context(served(ROOT, Path(tmp) / "here", here, obs, test)),
            label: stack.enter_context(served(other, Path(tmp) / "there", there, obs, test)),
        }
        for svc in sides.values():  # every worker has the map before the load
            for _ in range(4):
                httpx.post(
                    f"{svc.url}{QUERY}?min_version=1",
                    content=body[0],
                    headers={"Content-Type": body[1], "Accept": body[1]},
                    timeout=300,
                )
        runs = {name: [] for name in sides}
        for _ in range(args.rounds):
            for name, svc in sides.items():
                runs[name].append(wrk_load(svc.url, svc.proc.pid, body, args.connections, args.seconds))
        shares = None
        if args.profile:
            here = sides["this tree"]
            shares = profile(
                here.proc.pid, lambda: wrk_load(here.url, here.proc.pid, body, args.connections, args.seconds)
            )
        for name, results in runs.items():
            rows.append(
                {
                    "server": name,
                    "requests/s": float(np.mean([r["req/s"] for r in results])),
                    "p50 ms": float(np.mean([r["p50 ms"] for r in results])),
                    "server CPU ms/request": float(np.mean([r["server CPU ms/req"] for r in results])),
                    "idlest worker, cores": float(np.min([r["idlest worker, cores"] for r in results])),
                }
            )
    ratio = rows[0]["server CPU ms/request"] / rows[1]["server CPU ms/request"]
    other_flag = (
        f"--against {args.against}"
        if args.against_directions is None
        else f"--against-directions {args.against_directions}"
    )
    publish(
        [
            "",
            f"## Query CPU against {label}, {datetime.date.today()}",
            "",
            f"`python bench/bench_query_cpu.py {other_flag} --directions {args.directions} "
            f"{f'--model-directions {args.model_directions} ' if args.model_directions else ''}"
            f"--seconds {args.seconds:g} --connections {args.connections} --rounds {args.rounds}"
            f"{f' --points {args.points}' if args.points != 1000 else ''}"
            f"{' --profile' if args.profile else ''}`: "
            f"{args.points:,}-point Arrow queries of the demo's map "
            f"({'one class' if args.directions == 1 else f'{args.directions} sectors'}), 2 workers, SQLite.",
            "",
            rows_table(rows),
            "",
            f"Server CPU per request, this tree / {label}: **{ratio:.3f}**.",
            *(
                []
                if shares is None
                else ["", "Where this tree's query time goes (% of the samples in its work, py-spy):", ""]
                + [f"- {name.strip()}: {share:.0f} %" for name, share in shares.items()]
            ),
        ],
        not args.no_append,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
