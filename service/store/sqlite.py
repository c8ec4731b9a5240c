"""SQLite backend: the embedded default, one database file, no server.

WAL journal (readers never block the writer and read one snapshot), ``synchronous=FULL``
(a committed upload survives a power cut, not only a killed process), and
``BEGIN IMMEDIATE`` for writes, so concurrent writers queue on the database lock (up to
``busy_timeout_s``) instead of failing on a lock upgrade.
"""

from __future__ import annotations

import os
import sqlite3
import threading
from contextlib import contextmanager
from pathlib import Path

from service.store.base import (
    SCHEMA_VERSION,
    MapStore,
    RegionInfo,
    StoreDamaged,
    StoreError,
    StoreFull,
    StoreUnavailable,
)

FILE_NAME = "maps.sqlite3"


class SqliteStore(MapStore):
    local_reads = True

    def __init__(self, path, *, busy_timeout_s: float = 5.0):
        """``path``: the database file, or a data directory to hold ``maps.sqlite3``."""
        path = Path(path)
        if path.is_dir() or path.suffix == "":
            path.mkdir(parents=True, exist_ok=True)
            path = path / FILE_NAME
        self.path = path.absolute()
        self._timeout = busy_timeout_s
        # this process's writers queue here, woken as the lock frees, not in SQLite's busy
        # handler, whose sleeps let a stream of writers starve one past the timeout
        self._writer = threading.Lock()
        self._writes = 0  # this store's write transactions (region(): what it may have changed)
        self._init_connections()
        if self._current():
            return  # nothing to write: a store on read-only media opens, and serves reads
        with self._write() as q:
            for statement in self._schema("BLOB"):
                q(statement)
            self._init_schema(q)

    def _current(self) -> bool:
        """The database exists at this code's schema version."""
        with self._read() as q:
            if not q("SELECT 1 FROM sqlite_master WHERE name = 'meta'"):
                return False
            return q("SELECT value FROM meta WHERE key = 'schema_version'") == [(str(SCHEMA_VERSION),)]

    def _connection(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            # on read-only media SQLite cannot make the WAL's shared-memory file, so the
            # database opens immutable: reads are served, writes fail as SQLITE_READONLY
            writable = os.access(self.path.parent, os.W_OK)
            conn = sqlite3.connect(
                self.path.as_uri() + ("" if writable else "?immutable=1"),
                uri=True,
                timeout=self._timeout,
                isolation_level=None,
                check_same_thread=False,
            )
            if writable:
                conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("PRAGMA foreign_keys=ON")
            self._remember(conn)
        return conn

    @contextmanager
    def _transaction(self, begin: str):
        try:
            conn = self._connection()
            conn.execute(begin)

            def q(sql, params=()):
                return conn.execute(sql, params).fetchall()

            q.many = conn.executemany
            try:
                yield q
            except BaseException:
                if conn.in_transaction:  # SQLite rolls back by itself on some errors (disk full)
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")
        except sqlite3.Error as exc:
            mapped = _unavailable(exc)
            if mapped is None:
                raise
            raise mapped from exc

    @contextmanager
    def _write(self):
        if not self._writer.acquire(timeout=self._timeout):
            raise StoreUnavailable(f"other writes held the store for {self._timeout:g} s")
        try:
            with self._transaction("BEGIN IMMEDIATE") as q:
                yield q
        finally:
            self._writes += 1  # committed or not: the regions read before are read again
            self._writer.release()

    def region(self, name: str) -> RegionInfo:
        """:meth:`MapStore.region`, kept per thread while the database is unchanged: every
        request reads its region, and a read that finds nothing new costs one pragma
        (``data_version`` changes with another connection's commit; this store's own writes
        count in ``_writes``)."""
        changed = (self._connection().execute("PRAGMA data_version").fetchone()[0], self._writes)
        held = self._local.__dict__.setdefault("regions", {})
        if name in held and held[name][0] == changed:
            return held[name][1]
        info = super().region(name)  # read after the mark: a commit between is seen next time
        held[name] = (changed, info)
        return info

    def _read(self):
        return self._transaction("BEGIN")

    def _lock_region(self) -> str:
        return ""  # BEGIN IMMEDIATE already holds the database's write lock


#: SQLite result codes (``sqlite_errorname`` prefixes) of a database that cannot be used now
#: but may be later; any other error is ours (a 500).
UNAVAILABLE = ("SQLITE_BUSY", "SQLITE_LOCKED", "SQLITE_READONLY", "SQLITE_IOERR", "SQLITE_CANTOPEN")


def _unavailable(exc: sqlite3.Error) -> StoreError | None:
    """The store error a SQLite error means, or None for an error of ours."""
    name = getattr(exc, "sqlite_errorname", "")
    if name.startswith(("SQLITE_NOTADB", "SQLITE_CORRUPT")):
        return StoreDamaged(f"the SQLite file is not a bdf store, or is damaged ({name}: {exc})")
    if name.startswith("SQLITE_FULL"):
        return StoreFull(f"the SQLite database's disk is full ({exc}); nothing was stored")
    if name.startswith(UNAVAILABLE):
        return StoreUnavailable(f"the SQLite database cannot be used now ({name}: {exc})")
    return None
