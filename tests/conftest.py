import pytest


@pytest.fixture
def live_server(tmp_path):
    """A factory: ``live_server(env={...}, args=[...])`` starts ``bdf serve`` on 127.0.0.1
    (data in ``tmp_path/data``, logging at info), stopped at teardown."""
    from clients.local import LocalService

    servers = []

    def start(env=None, args=()):
        log = tmp_path / f"server-{len(servers)}.log"
        servers.append(LocalService(tmp_path / "data", {"BDF_LOG_LEVEL": "info", **(env or {})}, args, log))
        return servers[-1]

    yield start
    for server in servers:
        server.stop()
