"""PostgreSQL backend (psycopg 3): one map shared by several service replicas.

Writes lock the region's row (``SELECT ... FOR UPDATE``), so uploads to one region apply
one after another in every replica and a replayed upload id waits for, then sees, the
first. Reads run in a ``REPEATABLE READ READ ONLY`` transaction: one snapshot.
Tables live in the schema named by ``schema`` (default ``bdf``), created on first use.

The database cannot hold the service hostage: connecting, each statement and each lock
wait are bounded by ``timeout_s`` (the server's ``statement_timeout`` and
``lock_timeout``; and, for a server or network that stops answering altogether, where the
server's own timeouts cannot fire, a watchdog that cuts a connection silent for that
long). Each is :class:`StoreUnavailable` (503). The store opens with the database down:
it creates its schema on the first connection that succeeds, and again on the first one
after it found its tables gone (the database dropped, or restored from an empty dump): the
request that found them gone is a 503, never a 500, and no restart is needed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import time
from contextlib import contextmanager

import psycopg

from service.store.base import MapStore, StoreFull, StoreUnavailable

log = logging.getLogger(__name__)


class PostgresStore(MapStore):
    def __init__(self, url: str, *, schema: str = "bdf", timeout_s: float = 5.0):
        if not schema.isidentifier():
            raise ValueError(f"schema must be an identifier, got {schema!r}")
        self.url, self.schema, self.timeout_s = url, schema, timeout_s
        self._init_connections()
        self._watchdog = _Watchdog()
        self._schema_lock, self._schema_ready = threading.Lock(), False
        try:
            self._ensure_schema()
        except StoreUnavailable as exc:
            log.warning("%s; the service starts not ready and connects again on each request", exc)

    def _ensure_schema(self) -> None:
        """Create the schema and tables (once per process, under an advisory lock across
        processes) on the first connection that succeeds."""
        with self._schema_lock:
            if self._schema_ready:
                return
            with self._transaction(None, schema=False) as q:
                q("SELECT pg_advisory_xact_lock(hashtext('bdf-maps schema'))")  # concurrent first opens
                q(f"CREATE SCHEMA IF NOT EXISTS {self.schema}")
                blobs = {"tiles": "stats", "maps": "posterior"}
                new = [t for t in blobs if q("SELECT to_regclass(?)", (f"{self.schema}.{t}",))[0][0] is None]
                for statement in self._schema("BYTEA"):
                    q(statement)
                # statistics are dense floats: pglz gains little and costs most of an upload's time.
                # Only on a table just created: ALTER TABLE waits for every transaction on it, and
                # a process opening a store in use would deadlock with its writers
                for table in new:
                    q(f"ALTER TABLE {table} ALTER COLUMN {blobs[table]} SET STORAGE EXTERNAL")
                self._init_schema(q)
            self._schema_ready = True

    def _connection(self) -> psycopg.Connection:
        """This thread's connection; a new one where the last was lost (the server restarted,
        the network or the watchdog cut it), so service resumes without a restart of ours."""
        conn = getattr(self._local, "conn", None)
        if conn is None or conn.closed or conn.broken:
            if conn is not None:
                self._forget(conn)
                conn.close()
            ms = int(self.timeout_s * 1000)
            options = f"-c search_path={self.schema} -c statement_timeout={ms} -c lock_timeout={ms}"
            timeout = max(round(self.timeout_s), 2)  # libpq takes whole seconds, at least 2
            conn = self._remember(psycopg.connect(self.url, options=options, connect_timeout=timeout))
        return conn

    @contextmanager
    def _transaction(self, first: str | None, schema: bool = True):
        if schema and not self._schema_ready:
            self._ensure_schema()
        conn = watch = None
        try:
            with contextlib.ExitStack() as stack:
                conn = self._begin(stack)
                cur = stack.enter_context(conn.cursor(binary=True))
                watch = self._watchdog.watch(conn, self.timeout_s)
                if first:
                    with watch.armed():
                        cur.execute(first)

                def q(sql, params=()):
                    with watch.armed():
                        cur.execute(sql.replace("?", "%s"), params)
                        return cur.fetchall() if cur.description else []

                def many(sql, rows):
                    rows = list(rows)
                    with watch.armed(1 + len(rows) // 64):
                        cur.executemany(sql.replace("?", "%s"), rows)

                q.many = many
                yield q
                watch.arm()  # the commit, at the exit of the transaction
        except (psycopg.errors.UndefinedTable, psycopg.errors.InvalidSchemaName) as exc:
            self._schema_ready = False  # created again by the next transaction, as at startup
            raise StoreUnavailable(
                f"the store's tables are gone (the database or schema {self.schema!r} was dropped, or "
                f"restored empty: {type(exc).__name__}); they are created again on the next connection"
            ) from exc
        except psycopg.errors.DiskFull as exc:
            raise StoreFull(f"PostgreSQL is out of disk space ({exc}); nothing was stored") from exc
        except (psycopg.errors.QueryCanceled, psycopg.errors.LockNotAvailable) as exc:
            raise StoreUnavailable(
                f"PostgreSQL did not finish a statement within {self.timeout_s:g} s ({type(exc).__name__})"
            ) from exc
        except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
            if conn is not None and self._watchdog.was_cut(conn):
                raise StoreUnavailable(
                    f"PostgreSQL did not answer within {self.timeout_s:g} s; the connection was dropped"
                ) from exc
            raise StoreUnavailable(f"PostgreSQL cannot be reached ({type(exc).__name__}: {exc})") from exc
        finally:
            if watch is not None:
                watch.disarm()

    def _begin(self, stack: contextlib.ExitStack) -> psycopg.Connection:
        """This thread's connection in a new transaction. A connection found lost at BEGIN
        (nothing sent yet) is replaced once, so the first request after the database comes
        back does not fail on a stale connection."""
        for attempt in range(2):
            conn = self._connection()
            try:
                with self._watchdog.watch(conn, self.timeout_s).armed():
                    stack.enter_context(conn.transaction())
                return conn
            except psycopg.OperationalError:
                # lost while idle, it is replaced once; cut by the watchdog, the server is silent
                if attempt or self._watchdog.was_cut(conn) or not (conn.closed or conn.broken):
                    raise
        raise AssertionError("unreachable")

    def _write(self):
        return self._transaction(None)

    def _read(self):
        return self._transaction("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY")

    def _lock_region(self) -> str:
        return " FOR UPDATE"


class _Watchdog:
    """Cuts connections that wait on the server longer than their deadline. A server that
    is paused, or a network path that drops packets, answers nothing, so its own timeouts
    never fire and a blocked read would wait for TCP to give up (minutes): shutting the
    socket down wakes that read at once with an error."""

    #: how often deadlines are checked (s)
    TICK_S = 0.1

    def __init__(self):
        self._lock = threading.Lock()
        self._deadlines: dict[int, tuple[float, psycopg.Connection]] = {}
        self._cut: set[int] = set()
        self._thread: threading.Thread | None = None

    #: past the server's own timeouts, which answer first when the server can
    GRACE_S = 1.0

    def watch(self, conn: psycopg.Connection, seconds: float) -> _Watch:
        return _Watch(self, conn, seconds + self.GRACE_S)

    def was_cut(self, conn: psycopg.Connection) -> bool:
        with self._lock:
            return id(conn) in self._cut

    def _arm(self, conn, deadline: float) -> None:
        with self._lock:
            self._deadlines[id(conn)] = (deadline, conn)
            self._cut.discard(id(conn))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="postgres-watchdog", daemon=True)
                self._thread.start()

    def _disarm(self, conn) -> None:
        with self._lock:
            self._deadlines.pop(id(conn), None)

    def _run(self) -> None:
        while True:
            time.sleep(self.TICK_S)
            now = time.monotonic()
            with self._lock:
                if not self._deadlines:  # nothing to watch: the next arm starts another
                    self._thread = None
                    return
                late = [conn for deadline, conn in self._deadlines.values() if deadline < now]
                for conn in late:
                    del self._deadlines[id(conn)]
                    self._cut.add(id(conn))
            for conn in late:
                _shut_down(conn)


class _Watch:
    """One connection's deadline: :meth:`arm` before each wait on the server."""

    def __init__(self, dog: _Watchdog, conn, seconds: float):
        self.dog, self.conn, self.seconds = dog, conn, seconds

    def arm(self, scale: float = 1.0) -> None:
        self.dog._arm(self.conn, time.monotonic() + self.seconds * scale)

    def disarm(self) -> None:
        self.dog._disarm(self.conn)

    @contextmanager
    def armed(self, scale: float = 1.0):
        self.arm(scale)
        try:
            yield
        finally:
            self.disarm()


def _shut_down(conn: psycopg.Connection) -> None:
    """Shut the connection's socket down (its blocked reads return at once; the connection
    is broken and replaced on its next use)."""
    with contextlib.suppress(Exception):
        fd = conn.pgconn.socket
        sock = socket.socket(fileno=os.dup(fd))
        try:
            sock.shutdown(socket.SHUT_RDWR)
        finally:
            sock.close()
    log.warning("PostgreSQL did not answer in time: connection dropped")
