"""The suite's fuzzing, longer: schemathesis over every route and hypothesis over the body
decoders (tests/service/test_fuzz.py) with ``--examples`` per route instead of the suite's 12.

    .venv/bin/python bench/bench_fuzz.py [--examples 200] [--no-append]
"""

from __future__ import annotations

import datetime
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import arguments, publish  # bench/ is on the path as a script


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
    publish(
        [
            f"## Fuzzing, {datetime.date.today().isoformat()} (issue 19)",
            "",
            f"`python bench/bench_fuzz.py --examples {args.examples}`: schemathesis, up to {args.examples} "
            "examples per operation (every route, admin token; checks: no 5xx, status code, content type, "
            f"headers and body as documented), and hypothesis, up to {8 * args.examples} bad bodies "
            "(JSON, Arrow, Parquet: random, truncated, bytes flipped, NaN/inf, wrong columns) each "
            "uploaded and queried.",
            "",
            f"Outcome: `{outcome}` in {time.perf_counter() - started:.0f} s (exit {done.returncode}).",
            "",
        ],
        not args.no_append,
    )
    sys.exit(done.returncode)


if __name__ == "__main__":
    main()
