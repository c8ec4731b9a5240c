"""docker/: the Dockerfile passes hadolint, and the command lines of the image and of every
compose service work outside Docker (no engine runs here): the service as the image starts
it, its healthcheck, a Dask scheduler and worker as compose starts them, and a build
through them that the running service then serves."""

import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml

from bdf.region.spec import RegionSpec
from clients.local import LocalService, free_port
from tests.service.test_api import enu_columns, library
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # the image's command lines and the nginx edge

DOCKER = Path(__file__).parents[2] / "docker"
BIN = Path(sys.executable).parent
TOKENS = '{"tok-0123456789abcdef": ["read", "write", "admin"]}'


def dockerfile() -> dict:
    """ENV (merged), ENTRYPOINT, CMD, HEALTHCHECK CMD and EXPOSE of the final stage."""
    text = re.sub(r"\\\n\s*", " ", (DOCKER / "Dockerfile").read_text())
    final = text[text.rindex("\nFROM ") :]
    out = {"ENV": {}}
    for line in final.splitlines():
        word, _, rest = line.strip().partition(" ")
        if word == "ENV":
            out["ENV"].update(kv.split("=", 1) for kv in shlex.split(rest))
        elif word in ("ENTRYPOINT", "CMD", "EXPOSE"):
            out[word] = json.loads(rest) if rest.startswith("[") else rest
        elif word == "HEALTHCHECK":
            out[word] = json.loads(rest[rest.index(" CMD ") + 5 :])
    return out


def compose() -> dict:
    """compose.yaml with its ``${VAR:?message}`` values filled in (as compose does, after parsing)."""
    values = {"BDF_TOKENS": TOKENS, "POSTGRES_PASSWORD": "pw"}

    def fill(node):
        if isinstance(node, dict):
            return {k: fill(v) for k, v in node.items()}
        if isinstance(node, list):
            return [fill(v) for v in node]
        if isinstance(node, str):
            return re.sub(r"\$\{(\w+):\?[^}]*\}", lambda m: values[m[1]], node)
        return node

    return fill(yaml.safe_load((DOCKER / "compose.yaml").read_text()))


def local(argv: list[str]) -> list[str]:
    """A container's argv run here: its programs from this virtual environment."""
    return [str(BIN / argv[0]), *argv[1:]]


def wait_until(check, what: str, procs, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        for p in procs:
            assert p.poll() is None, f"{what}: {p.args[:2]} exited with {p.returncode}"
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.2)


def test_dockerfile_passes_hadolint():
    run = subprocess.run([BIN / "hadolint", DOCKER / "Dockerfile"], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr


def test_the_compose_file_is_valid_by_the_compose_specifications_own_schema(tmp_path):
    """What ``docker compose config`` checks, with neither a Docker engine nor Compose v2
    (neither installs here): compose.yaml against the Compose Specification's JSON schema
    (check-jsonschema's copy), as written and interpolated (a broken file fails), and the
    references it resolves across the file."""
    check = [str(BIN / "check-jsonschema"), "--builtin-schema", "vendor.compose-spec"]
    filled, broken = tmp_path / "filled.yaml", tmp_path / "broken.yaml"
    filled.write_text(yaml.safe_dump(compose()))
    services = compose()["services"]
    services["service"]["ports"] = 8000  # a list of ports, not a number
    broken.write_text(yaml.safe_dump({**compose(), "services": services}))
    for path, valid in ((DOCKER / "compose.yaml", True), (filled, True), (broken, False)):
        run = subprocess.run([*check, str(path)], capture_output=True, text=True)
        assert (run.returncode == 0) == valid, run.stdout + run.stderr
    # and what compose resolves across the file: services depended on exist (with a
    # healthcheck where their health is awaited), named volumes are declared, bind mounts
    # and build contexts exist beside the file
    body = compose()
    for name, service in body["services"].items():
        needs = service.get("depends_on", [])
        for other in needs:
            assert other in body["services"], (name, other)
            if isinstance(needs, dict) and needs[other].get("condition") == "service_healthy":
                assert "healthcheck" in body["services"][other], (name, other)
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith("."):
                assert (DOCKER / source).exists(), (name, volume)
            else:
                assert source in body["volumes"], (name, volume)
        if "build" in service:
            context = DOCKER / service["build"]["context"]
            assert (context / service["build"]["dockerfile"]).is_file(), (name, service["build"])


def test_image_and_compose_command_lines_work_outside_docker(tmp_path):
    image, services = dockerfile(), compose()["services"]
    assert image["ENTRYPOINT"] == ["bdf"] and image["CMD"] == ["serve"] and image["EXPOSE"] == "8000"
    assert set(services) == {"postgres", "service", "proxy", "dask-scheduler", "dask-worker", "builder"}
    store_url = os.environ.get("BDF_TEST_POSTGRES_URL")  # compose's store is PostgreSQL
    if store_url:
        store_url += f"?schema=bdf_docker_{os.getpid()}"
    else:
        store_url = f"sqlite:///{tmp_path / 'data'}"
    port, scheduler_port, dashboard = free_port(), free_port(), free_port()

    env = {k: v for k, v in os.environ.items() if not k.startswith("BDF_")}
    env.update({k: v for k, v in image["ENV"].items() if k != "PATH"})
    env.update(services["service"]["environment"])  # tokens (required on 0.0.0.0) and store
    assert env["BDF_HOST"] == "0.0.0.0" and json.loads(env["BDF_TOKENS"]) == json.loads(TOKENS)
    env.update(BDF_PORT=str(port), BDF_DATA_DIR=str(tmp_path / "data"), BDF_STORE_URL=store_url)

    observations = tmp_path / "observations"
    observations.mkdir()
    X, V = data(0, n=600)
    for i in range(3):
        pq.write_table(pa.table(enu_columns(X[i::3], V[i::3])), observations / f"part{i}.parquet")

    def container(svc: str, **replace) -> list[str]:
        spec = services[svc]
        argv = [*spec.get("entrypoint", image["ENTRYPOINT"]), *spec.get("command", image["CMD"])]
        text = shlex.join(argv)
        for old, new in replace.items():
            text = text.replace(old, new)
        return local(shlex.split(text))

    scheduler_address = f"tcp://127.0.0.1:{scheduler_port}"
    procs = []
    try:
        logs = tmp_path / "logs"
        logs.mkdir()

        def start(name, argv):
            with open(logs / f"{name}.log", "wb") as log:
                procs.append(subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT))

        start("service", container("service"))
        start(
            "scheduler",
            container("dask-scheduler", **{"8786": str(scheduler_port), ":8787": f"127.0.0.1:{dashboard}"}),
        )
        start("worker", container("dask-worker", **{"tcp://dask-scheduler:8786": scheduler_address}))

        health = local(image["HEALTHCHECK"])
        wait_until(
            lambda: subprocess.run(health, env=env, capture_output=True).returncode == 0, "health", procs
        )

        def dashboard_up():
            try:
                return httpx.get(f"http://127.0.0.1:{dashboard}/health", timeout=1).text == "ok"
            except httpx.TransportError:
                return False

        wait_until(dashboard_up, "dask scheduler", procs)

        auth = {"Authorization": "Bearer tok-0123456789abcdef"}
        base = f"http://127.0.0.1:{port}"
        assert httpx.post(f"{base}/v1/regions", json=SPEC, headers=auth).status_code == 201
        assert httpx.get(f"{base}/v1/regions", timeout=5).status_code == 401  # tokens are on

        files = [str(p) for p in sorted(observations.glob("*.parquet"))]
        build = container("builder", **{"--help": ""})
        build += ["build", "--region", SPEC["name"], "--scheduler", scheduler_address, *files]
        run = subprocess.run(build, env=env, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-3000:]
        assert "600 accepted" in run.stdout and "version 1" in run.stdout

        body = {"points": X[:50].tolist()}
        got = httpx.post(f"{base}/v1/regions/{SPEC['name']}/query", json=body, headers=auth).json()
        spec = RegionSpec.model_validate(SPEC)
        mean, std, _ = library(spec, X, V, X[:50])
        np.testing.assert_allclose(got["mean"], mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(got["std"], std, rtol=1e-6)
        assert got["region_version"] == 1
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        codes = [p.wait(60) for p in procs]
        if store_url.startswith("postgresql"):
            import psycopg

            with psycopg.connect(os.environ["BDF_TEST_POSTGRES_URL"], autocommit=True) as conn:
                conn.execute(f"DROP SCHEMA IF EXISTS bdf_docker_{os.getpid()} CASCADE")
    assert codes[0] == 0, (logs / "service.log").read_text()[-3000:]  # graceful stop


@pytest.fixture
def nginx():
    """Debian's nginx. Skipped where it is missing, unless ``BDF_TEST_NGINX=required`` (CI),
    where its absence fails."""
    path = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx",) if os.path.exists(p)), None)
    if path is None:
        if os.environ.get("BDF_TEST_NGINX") == "required":
            pytest.fail("BDF_TEST_NGINX=required but no nginx (apt-get install nginx-light)")
        pytest.skip("no nginx: `make nginx` installs Debian's package")
    return path


def test_the_nginx_edge_serves_the_replicas_while_half_open_clients_hold_connections(tmp_path, nginx):
    """docker/nginx.conf as compose mounts it, its upstream pointed at a local service:
    nginx accepts it, and authorised requests pass while 200 half-open connections (twice
    the service's cap behind it) are held at the edge."""
    with LocalService(tmp_path / "data", {"BDF_MAX_CONNECTIONS": "100"}) as svc:
        port = free_port()
        conf = (DOCKER / "nginx.conf").read_text()
        conf = conf.replace("server service:8000;", f"server 127.0.0.1:{svc.port};")
        conf = conf.replace("listen 8080;", f"listen 127.0.0.1:{port};")
        (tmp_path / "logs").mkdir()
        (tmp_path / "nginx.conf").write_text(conf)
        argv = [nginx, "-p", str(tmp_path), "-c", str(tmp_path / "nginx.conf")]
        extra = f"daemon off; pid {tmp_path}/nginx.pid; error_log {tmp_path}/logs/error.log;"
        check = subprocess.run([*argv, "-t", "-g", extra], capture_output=True, text=True)
        assert check.returncode == 0, check.stderr
        proc = subprocess.Popen([*argv, "-g", extra], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        held = []
        try:
            url = f"http://127.0.0.1:{port}"
            wait_until(lambda: _answers(url), "nginx", [proc])
            for _ in range(200):
                sock = socket.create_connection(("127.0.0.1", port))
                sock.sendall(b"GET /v1/regions HTTP/1.1\r\nHost: x\r\n")  # no end of headers
                held.append(sock)
            statuses = [httpx.get(f"{url}/v1/regions", timeout=10).status_code for _ in range(20)]
            assert statuses == [200] * 20
        finally:
            for sock in held:
                sock.close()
            proc.terminate()
            proc.wait(30)


def _answers(url: str) -> bool:
    try:
        return httpx.get(f"{url}/healthz", timeout=1).status_code == 200
    except httpx.TransportError:
        return False


def readme_docker_commands() -> list[list[str]]:
    """The README's Docker block, one argv per command (continued lines joined)."""
    text = (DOCKER.parent / "README.md").read_text()
    block = text[text.index("- **Docker.**") :]
    block = block[block.index("```") + 3 :]
    block = block[: block.index("```")].replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in block.splitlines() if line.strip()]


def test_the_readmes_docker_steps_name_what_exists_and_parse():
    """Each command of the README's Docker block: compose on the compose file, services it
    defines, bdf arguments our command line accepts, files under /observations that ship in
    docker/observations or that an earlier step makes there, the edge's address."""
    from clients.cli import build_parser
    from clients.samples import SAMPLES

    services = compose()["services"]
    proxy_port = services["proxy"]["ports"][0].split(":")[0]
    made, ran = set(), []
    for argv in readme_docker_commands():
        if argv[0] == "export":
            assert {kv.split("=", 1)[0] for kv in argv[1:]} == {"BDF_TOKENS", "POSTGRES_PASSWORD"}
            continue
        if argv[0] == "curl":
            assert argv[-1].startswith(f"http://127.0.0.1:{proxy_port}/"), argv
            ran.append("curl")
            continue
        if argv[0] == ".venv/bin/bdf":
            args = build_parser().parse_args(argv[1:])
            assert (args.command, args.action) == ("data", "fetch")
            made.add(f"{argv[3]}-{Path(SAMPLES[argv[3]][1]).name}")
            assert Path(argv[argv.index("--cache") + 1]) == Path("docker/observations")
            continue
        assert argv[:4] == ["docker", "compose", "-f", "docker/compose.yaml"], argv
        assert (DOCKER.parent / argv[3]).exists()
        verb, rest = argv[4], argv[5:]
        if verb == "up":
            scale = rest[rest.index("--scale") + 1].split("=")[0]
            assert scale in services
            ran.append("up")
            continue
        assert verb == "run" and rest[0] == "--rm" and rest[1] in services, argv
        bdf_args = rest[2:]
        build_parser().parse_args(bdf_args)  # exits (SystemExit) on arguments it does not take
        for arg in bdf_args:
            if arg.startswith("/observations/"):
                name = arg.removeprefix("/observations/")
                assert (DOCKER / "observations" / name).exists() or name in made, arg
        if "--url" in bdf_args:
            host, port = bdf_args[bdf_args.index("--url") + 1].removeprefix("http://").split(":")
            assert host == "proxy" and port == "8080" == services["proxy"]["ports"][0].split(":")[1]
        ran.append(bdf_args[0])
    assert ran == ["up", "region", "build", "curl"]
    spec = json.loads((DOCKER / "observations" / "paris-region.json").read_text())
    RegionSpec.model_validate(spec)
