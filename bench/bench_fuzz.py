"""The suite's fuzzing, longer: schemathesis over every route and hypothesis over the body
decoders (tests/service/test_fuzz.py) with ``--examples`` per route instead of the suite's 12;
then schemathesis's command line with every check (``--checks all``, seeded) against ``bdf
serve`` on 127.0.0.1 with a region of data. Its findings are listed in RELIABILITY.md.

    .venv/bin/python bench/bench_fuzz.py [--examples 200] [--no-append]
"""

from __future__ import annotations

import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import arguments, publish  # bench/ is on the path as a script

from clients.local import LocalService
from tests.service.test_store import SPEC, data

TOKEN = "fuzz-admin-0123456789"
SEED = 20261126


def all_checks(examples: int) -> tuple[str, list[str]]:
    """``st run --checks all`` against a live service: its summary line and findings."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {"BDF_TOKENS": json.dumps({TOKEN: ["read", "write", "admin"]}), "BDF_MAX_GRID_VOXELS": "20000"}
        with LocalService(Path(tmp) / "data", env) as svc:
            auth = {"Authorization": f"Bearer {TOKEN}"}
            httpx.post(f"{svc.url}/v1/regions", json=SPEC, headers=auth).raise_for_status()
            X, V = data(1, n=200)
            body = {"points": X.tolist(), "velocities": V.tolist()}
            httpx.post(
                f"{svc.url}/v1/regions/{SPEC['name']}/observations",
                json=body,
                headers={**auth, "Idempotency-Key": "seed"},
            ).raise_for_status()
            st = Path(sys.executable).with_name("schemathesis")
            cmd = [
                str(st),
                "run",
                f"{svc.url}/openapi.json",
                "--checks",
                "all",
                "-H",
                f"Authorization: Bearer {TOKEN}",
            ]
            cmd += ["--seed", str(SEED), "-n", str(examples), "-w", "1"]
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp).stdout  # its cache there
    findings = re.findall(r"_{3,} (\S+ \S+) _{3,}\n.*?\n- (ST\d+ [^\n]+).*?`(\{[^`]*\})`", out, re.S)
    listed = [f"{op}: {code}: {json.loads(problem)['detail']}" for op, code, problem in findings]
    summary = [line for line in out.splitlines() if " generated, " in line or re.match(r"=+ .* in ", line)]
    return " ".join(s.strip() for s in summary), listed


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--examples", type=int, default=200)
    args = parser.parse_args()
    root = Path(__file__).resolve().parents[1]
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/service/test_fuzz.py"],
        cwd=root,
        env={**os.environ, "BDF_FUZZ_EXAMPLES": str(args.examples)},
        capture_output=True,
        text=True,
    )
    print(done.stdout[-3000:])
    outcome = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-500:]
    cli_summary, findings = all_checks(args.examples)
    publish(
        [
            f"## Fuzzing, {datetime.date.today().isoformat()} (issues 19, 34)",
            "",
            f"`python bench/bench_fuzz.py --examples {args.examples}`: schemathesis, up to {args.examples} "
            "examples per operation (every route, admin token; checks: no 5xx, status code, content type, "
            f"headers and body as documented), and hypothesis, up to {8 * args.examples} bad bodies "
            "(JSON, Arrow, Parquet: random, truncated, bytes flipped, NaN/inf, wrong columns) each "
            "uploaded and queried.",
            "",
            f"Outcome: `{outcome}` in {time.perf_counter() - started:.0f} s (exit {done.returncode}).",
            "",
            f"`st run --checks all --seed {SEED} -n {args.examples}` against `bdf serve` with a region of "
            f"data: `{cli_summary}`; each finding (in RELIABILITY.md with why the answer is right):",
            "",
            *(f"- {f}" for f in findings),
            "",
        ],
        not args.no_append,
    )
    sys.exit(done.returncode)


if __name__ == "__main__":
    main()
