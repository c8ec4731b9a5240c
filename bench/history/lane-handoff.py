"""Where a small query's CPU went when light reads ran in a lane's threads (2026-11-29):
reproduces the RESULTS row "the fixed cost of a query" (its per-thread figures).

    python bench/history/lane-handoff.py

The paper's model of the demo's map (the Paris flight split's training rows), served by one
uvicorn worker on SQLite, its light reads on the event loop (``Lanes.inline``, as served)
and in the light lane's threads (as before); wrk sends 1-point Arrow queries on 4
connections. Per thread of the server: CPU and voluntary context switches per request
(/proc). With threads, each request's step passes the GIL back and forth with the event
loop, which parses and answers the other connections meanwhile.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from bench_service import arrow_points, build, wrk_load  # noqa: E402

from bdf import ingest  # noqa: E402
from clients.local import LocalService, free_port  # noqa: E402
from clients.samples import load_paris, paris_demo_region  # noqa: E402
from service.wire import ARROW  # noqa: E402

#: ``bdf serve`` with one worker in this process's image, its lanes inline or not
SERVE = """
import sys
import service.lanes
from service import server
from service.settings import Settings
inline = sys.argv[1] == "inline"
init = service.lanes.Lanes.__init__
def lanes(self, *args, **kwargs):
    init(self, *args, **{**kwargs, "inline": inline})
service.lanes.Lanes.__init__ = lanes
server.run(Settings())
"""


def threads(pid: int) -> dict[int, tuple[float, int]]:
    """CPU seconds and voluntary context switches of each thread of ``pid``."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
            status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        except FileNotFoundError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        switches = int(status.split("voluntary_ctxt_switches:")[1].split()[0])
        out[int(tid)] = ((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), switches)
    return out


def main() -> None:
    obs, lower, upper = load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    spec = paris_demo_region(lower, upper, directions=1, model_directions=1)
    one = (arrow_points(obs.X[test][:1]), ARROW)
    with tempfile.TemporaryDirectory() as tmp:
        env = {"BDF_WORKERS": "1", "BDF_LOG_LEVEL": "warning", "BDF_REQUEST_TIMEOUT_S": "600"}
        with LocalService(Path(tmp), env) as svc:
            build(svc.url, spec.model_dump(mode="json"), obs, test)
        for mode in ("threads", "inline", "threads", "inline"):
            port = free_port()
            run_env = {
                **os.environ,
                "BDF_PORT": str(port),
                "BDF_DATA_DIR": tmp,
                "BDF_WORKERS": "1",
                "BDF_LOG_LEVEL": "warning",
                "OPENBLAS_NUM_THREADS": "1",
            }
            proc = subprocess.Popen([sys.executable, "-c", SERVE, mode], env=run_env, cwd=ROOT)
            url = f"http://127.0.0.1:{port}"
            try:
                for _ in range(600):
                    try:
                        if httpx.get(f"{url}/healthz").status_code == 200:
                            break
                    except httpx.HTTPError:
                        time.sleep(0.1)
                headers = {"Content-Type": ARROW, "Accept": ARROW}
                httpx.post(f"{url}/v1/regions/paris/query?min_version=1", content=one[0], headers=headers)
                before = threads(proc.pid)
                load = wrk_load(url, proc.pid, one, 4, 6)
                after = threads(proc.pid)
            finally:
                proc.terminate()
                proc.wait()
            n = load["requests"]
            busy = [
                (1e3 * (cpu - before.get(tid, (0.0, 0))[0]) / n, (cs - before.get(tid, (0.0, 0))[1]) / n)
                for tid, (cpu, cs) in sorted(after.items())
                if cpu - before.get(tid, (0.0, 0))[0] > 0.02
            ]
            print(
                f"{mode}: {load['server CPU ms/req']:.3f} ms per request, p50 {load['p50 ms']:.2f} ms; "
                "busy threads (ms, voluntary switches per request): "
                + ", ".join(f"{ms:.3f} / {cs:.1f}" for ms, cs in busy),
                flush=True,
            )


if __name__ == "__main__":
    main()
