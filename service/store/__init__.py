"""Map storage: one interface, an embedded SQLite default and PostgreSQL for replicas."""

from __future__ import annotations

from service.store.base import (
    CorruptTile,
    MapStore,
    RegionChanged,
    RegionExists,
    RegionInfo,
    RegionNotFound,
    Snapshot,
    StoreError,
    StoreFull,
    StoreUnavailable,
    TileInfo,
    UploadConflict,
    UploadNotFound,
    payload_digest,
)


def open_store(url: str, timeout_s: float = 5.0) -> MapStore:
    """``sqlite:///path/to/dir-or-file`` or ``postgresql://user@host:port/db[?schema=name]``.
    ``timeout_s``: the longest wait for the database (a connection, a statement, a lock;
    :class:`StoreUnavailable` past it)."""
    if url.startswith("sqlite:///"):
        from service.store.sqlite import SqliteStore

        return SqliteStore(url.removeprefix("sqlite:///") or ".", busy_timeout_s=timeout_s)
    if url.startswith(("postgresql://", "postgres://")):
        from service.store.postgres import PostgresStore

        base, _, query = url.partition("?")
        options = dict(part.split("=", 1) for part in query.split("&") if "=" in part)
        schema = options.pop("schema", "bdf")
        rest = "&".join(f"{k}={v}" for k, v in options.items())
        return PostgresStore(base + (f"?{rest}" if rest else ""), schema=schema, timeout_s=timeout_s)
    raise ValueError(f"a store URL starts with sqlite:/// or postgresql://, got {url!r}")


__all__ = [
    "CorruptTile",
    "MapStore",
    "RegionChanged",
    "RegionExists",
    "RegionInfo",
    "RegionNotFound",
    "Snapshot",
    "StoreError",
    "StoreFull",
    "StoreUnavailable",
    "TileInfo",
    "UploadConflict",
    "UploadNotFound",
    "open_store",
    "payload_digest",
]
