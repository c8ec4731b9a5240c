"""The ``bdf`` command line. Errors are one line on stderr and a non-zero exit code.

Exit codes: 0 success, 1 runtime failure (download, I/O), 2 bad usage or bad input.
"""

from __future__ import annotations

import argparse
import logging
import os
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


def _serve(args) -> int:
    """Settings: flags over environment (BDF_*) over the TOML file (--config / BDF_CONFIG).

    Flags travel as environment variables so that every uvicorn worker process builds the
    same settings.
    """
    # Requests are the unit of parallelism: one BLAS thread each (set before numpy loads;
    # worker processes inherit it), so BLAS threads do not compete with request threads.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import uvicorn

    from service.settings import Settings

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
    log.info("store: %s", settings.store.split("@")[-1] if "@" in settings.store else settings.store)
    uvicorn.run(
        "service.app:create_app",
        factory=True,
        host=settings.host,
        port=settings.port,
        workers=settings.workers,
        access_log=False,  # one structured line per request comes from the app
        log_level=settings.log_level,
        timeout_graceful_shutdown=60,
    )
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
