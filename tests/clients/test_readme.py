"""The README walked top to bottom as a newcomer would: its service commands, its curl
session, and its Python examples (library, regions, SDK, planner), in order, on temporary
stores. A command that exits non-zero, an HTTP answer of 5xx (or any error the README does
not expect) or an example that raises fails the walk.

What the README leaves to the reader is given here, and only that: the data of the
examples (synthetic 1 Hz tracks near the Paris origin), the port (a free one for 8000) and
the PostgreSQL schema. ``make demo`` and ``make test`` are CI's own commands; ``docker``
steps are checked in tests/docker; the command-line synopsis is checked against the
parser in tests/clients/test_cli.py.
"""

import os
import re
import shlex
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from clients.local import free_port

pytestmark = pytest.mark.slow  # services, a planner

README = Path(__file__).parents[2] / "README.md"
BIN = Path(sys.executable).parent


def blocks() -> list[tuple[str, str]]:
    """Every fenced block of the README: (language, text), in order."""
    return re.findall(r"^```(\w*)\n(.*?)^```", README.read_text(), re.M | re.S)


def block(starts: str, language: str = "") -> str:
    """The one block whose text starts with ``starts``."""
    found = [text for lang, text in blocks() if lang == language and text.lstrip().startswith(starts)]
    assert len(found) == 1, f"README: {len(found)} blocks start with {starts!r}"
    return found[0]


#: what the examples leave to the reader: 1 Hz tracks of 40 flights near the origin,
#: eastbound at 1,000 to 2,500 m and 120 to 220 m/s
PRELUDE = """
import numpy as np
rng = np.random.default_rng(0)
rows = []
for flight in range(40):
    n, speed = 120, rng.uniform(120, 220)
    x = np.linspace(-9000, 9000, n)
    y, z = np.full(n, rng.uniform(-8000, 8000)), np.full(n, 1000 + 500 * (flight % 4))
    v = np.tile([speed, 0.0, 0.0], (n, 1))
    rows.append((np.column_stack([x, y, z]), v, flight, np.arange(n, dtype=float)))
X = np.vstack([r[0] for r in rows]); V = np.vstack([r[1] for r in rows]) + rng.normal(0, 3, (len(X), 3))
track = np.concatenate([np.full(len(r[0]), r[2]) for r in rows]); t = np.concatenate([r[3] for r in rows])
ids = track
X2, V2 = X[::7] + 10.0, V[::7]
Xq = rng.uniform([-8000, -8000, 1000], [8000, 8000, 2500], (200, 3))
lower, upper = np.array([-10000, -10000, 0.0]), np.array([10000, 10000, 3000.0])
spacing, gamma = np.array([2000, 2000, 500.0]), np.array([1 / 2000**2, 1 / 2000**2, 1 / 500**2])
x0, y0, z0, x1, y1, z1 = -5000, -5000, 1000, 5000, 5000, 2000
start, goal = np.array([-7000.0, 0.0, 1500.0]), np.array([7000.0, 2000.0, 1500.0])
"""


def serve(line: str, cwd: Path, env: dict) -> tuple[subprocess.Popen, str]:
    """A README ``bdf serve`` line run as printed (its port given by BDF_PORT or replaced)."""
    port = free_port()
    line = line.replace("--port 8000", f"--port {port}")
    argv = shlex.split(line, comments=True)
    assignments = dict(a.split("=", 1) for a in argv if re.match(r"^[A-Z_]+=", a))
    argv = [a for a in argv if not re.match(r"^[A-Z_]+=", a)]
    argv[0] = str(BIN / argv[0])
    full = {k: v for k, v in os.environ.items() if not k.startswith("BDF_")} | env | assignments
    full["BDF_PORT"] = str(port)
    log = open(cwd / f"serve-{port}.log", "wb")
    proc = subprocess.Popen(argv, cwd=cwd, env=full, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        assert proc.poll() is None, (cwd / f"serve-{port}.log").read_text()[-3000:]
        assert time.monotonic() < deadline, "the README's service did not start"
        time.sleep(0.2)


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM: a graceful stop (uvicorn re-raises the signal once it has shut down)."""
    proc.terminate()
    assert proc.wait(60) in (0, -signal.SIGTERM)


def test_the_readme_walked_top_to_bottom(tmp_path, monkeypatch):
    postgres = os.environ.get("BDF_TEST_POSTGRES_URL")
    namespace: dict = {}
    exec(PRELUDE, namespace)

    # the library's examples, in order
    monkeypatch.chdir(tmp_path)  # the examples write files where they run
    for starts in ("from bdf import BayesianDynamicField", "f = BayesianDynamicField("):
        exec(block(starts, "python"), namespace)
    assert (tmp_path / "paris.bdf").exists()
    region_example = block("from bdf.region.spec import RegionSpec", "python")
    exec(region_example, namespace)
    assert namespace["p"].version >= 2 and np.all(np.isfinite(namespace["p"].mean))
    namespace["store"].close()

    # the service: open on loopback, and with tokens on PostgreSQL
    lines = [line for line in block("bdf serve").replace("\\\n", " ").splitlines() if line.strip()]
    assert len(lines) == 2
    open_proc, open_url = serve(lines[0], tmp_path, {})
    try:
        assert httpx.get(f"{open_url}/readyz").status_code == 200
        if postgres:
            schema = f"readme_{os.getpid()}"
            line = lines[1].replace(
                "postgresql://postgres@127.0.0.1:5432/test?schema=bdf", f"{postgres}?schema={schema}"
            )
            assert line != lines[1], "the README's PostgreSQL URL changed: update the walk"
            line = line.replace("--host 0.0.0.0", "--host 127.0.0.1")  # no other machine needs it here
            token_proc, token_url = serve(line, tmp_path, {})
            try:
                curl_session(block("S=http://127.0.0.1:8000"), token_url, tmp_path)
            finally:
                stop(token_proc)
                import psycopg

                with psycopg.connect(postgres, autocommit=True) as conn:
                    conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")
        else:  # the same session on the open server, the token header dropped as the README says
            session = block("S=http://127.0.0.1:8000").replace(' -H "$H"', "").replace('-sH "$H"', "-s")
            curl_session(session, open_url, tmp_path)

        # the SDK's and the planner's examples on the open server
        sdk = block("from clients.sdk import BDFClient", "python").replace("http://127.0.0.1:8000", open_url)
        namespace["spec"] = namespace["spec"].model_dump(mode="json")
        exec(sdk, namespace)
        assert namespace["pred"].mean.shape == (len(namespace["Xq"]), 3)
        assert namespace["png"][:8] == b"\x89PNG\r\n\x1a\n"
        from clients.sdk import BDFClient

        with BDFClient(open_url) as client:
            namespace["bdf"] = client
            exec(block("from planner.costmap import CostWeights", "python"), namespace)
        assert (tmp_path / "route.png").exists()
    finally:
        stop(open_proc)


def curl_session(text: str, url: str, cwd: Path) -> None:
    """The README's curl session in bash, each curl failing on an HTTP error (4xx or 5xx:
    on a fresh store every step of it succeeds)."""
    script = 'set -euo pipefail\ncurl() { command curl --fail-with-body --show-error "$@"; echo; }\n'
    script += textwrap.dedent(text).replace("http://127.0.0.1:8000", url)
    done = subprocess.run(["bash", "-c", script], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert '"accepted":2' in done.stdout.replace(" ", "")
    assert (cwd / "grid.npz").stat().st_size > 1000
