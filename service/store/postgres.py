"""PostgreSQL backend (psycopg 3): one map shared by several service replicas.

Writes lock the region's row (``SELECT ... FOR UPDATE``), so uploads to one region apply
one after another in every replica and a replayed upload id waits for, then sees, the
first. Reads run in a ``REPEATABLE READ READ ONLY`` transaction: one snapshot.
Tables live in the schema named by ``schema`` (default ``bdf``), created on first use.
"""

from __future__ import annotations

import contextlib
from contextlib import contextmanager

import psycopg

from service.store.base import MapStore, StoreFull, StoreUnavailable

#: seconds to wait for a connection before answering 503 (a dead host must not hang requests)
CONNECT_TIMEOUT_S = 5


class PostgresStore(MapStore):
    def __init__(self, url: str, *, schema: str = "bdf"):
        if not schema.isidentifier():
            raise ValueError(f"schema must be an identifier, got {schema!r}")
        self.url, self.schema = url, schema
        self._init_connections()
        with self._write() as q:
            q("SELECT pg_advisory_xact_lock(hashtext('bdf-maps schema'))")  # concurrent first opens
            q(f"CREATE SCHEMA IF NOT EXISTS {schema}")
            for statement in self._schema("BYTEA"):
                q(statement)
            # statistics are dense floats: pglz gains little and costs most of an upload's time
            q("ALTER TABLE tiles ALTER COLUMN stats SET STORAGE EXTERNAL")
            self._init_schema(q)

    def _connection(self) -> psycopg.Connection:
        """This thread's connection; a new one where the last was lost (the server restarted
        or the network cut it), so service resumes without a restart of ours."""
        conn = getattr(self._local, "conn", None)
        if conn is None or conn.closed:
            if conn is not None:
                self._forget(conn)
            conn = self._remember(
                psycopg.connect(
                    self.url, options=f"-c search_path={self.schema}", connect_timeout=CONNECT_TIMEOUT_S
                )
            )
        return conn

    @contextmanager
    def _transaction(self, first: str | None):
        try:
            with contextlib.ExitStack() as stack:
                conn = self._begin(stack)
                cur = stack.enter_context(conn.cursor(binary=True))
                if first:
                    cur.execute(first)

                def q(sql, params=()):
                    cur.execute(sql.replace("?", "%s"), params)
                    return cur.fetchall() if cur.description else []

                q.many = lambda sql, rows: cur.executemany(sql.replace("?", "%s"), rows)
                yield q
        except psycopg.errors.DiskFull as exc:
            raise StoreFull(f"PostgreSQL is out of disk space ({exc}); nothing was stored") from exc
        except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
            raise StoreUnavailable(f"PostgreSQL cannot be reached ({type(exc).__name__}: {exc})") from exc

    def _begin(self, stack: contextlib.ExitStack) -> psycopg.Connection:
        """This thread's connection in a new transaction. A connection found lost at BEGIN
        (nothing sent yet) is replaced once, so the first request after the database comes
        back does not fail on a stale connection."""
        for attempt in range(2):
            conn = self._connection()
            try:
                stack.enter_context(conn.transaction())
                return conn
            except psycopg.OperationalError:
                if attempt or not conn.closed:
                    raise
        raise AssertionError("unreachable")

    def _write(self):
        return self._transaction(None)

    def _read(self):
        return self._transaction("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY")

    def _lock_region(self) -> str:
        return " FOR UPDATE"
