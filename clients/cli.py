"""The ``bdf`` command line. Errors are one line on stderr and a non-zero exit code.

Exit codes: 0 success, 1 runtime failure (download, I/O), 2 bad usage or bad input.
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
from pathlib import Path


def _data_fetch(args) -> int:
    from bdf import ingest

    print(ingest.fetch_sample(args.name, args.cache))
    return 0


def _demo(args) -> int:
    from clients.demo import run

    run(Path(args.out))
    return 0


def build_parser() -> argparse.ArgumentParser:
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

    demo = sub.add_parser("demo", help="learn the Paris map, print its accuracy, write plots")
    demo.add_argument("--out", default="demo-output", help="folder for the plots (default: demo-output)")
    demo.set_defaults(run=_demo)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return args.run(args)
    except ValueError as exc:
        print(f"bdf: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, RuntimeError, subprocess.CalledProcessError) as exc:
        print(f"bdf: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
