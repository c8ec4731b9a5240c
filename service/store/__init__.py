"""Map storage: one interface, an embedded SQLite default and PostgreSQL for replicas."""

from __future__ import annotations

import urllib.parse

from service.store.base import (
    CorruptTile,
    Lease,
    MapStore,
    RegionChanged,
    RegionExists,
    RegionInfo,
    RegionNotFound,
    ResolutionChanged,
    Snapshot,
    StoredMap,
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
    raise ValueError(f"a store URL starts with sqlite:/// or postgresql://, got {redacted(url)!r}")


#: query parameters of a PostgreSQL URL that hold a secret (libpq's connection parameters)
SECRET_PARAMETERS = ("password", "sslpassword", "passfile", "sslkey")


def redacted(url: str) -> str:
    """``url`` as it may be logged or shown: a password before ``@`` and every secret
    parameter of its query string (:data:`SECRET_PARAMETERS`) replaced by ``***``."""
    if url.startswith("sqlite:///"):
        return url  # a path holds no secret
    parts = urllib.parse.urlsplit(url)
    netloc = parts.netloc
    if "@" in netloc:
        user, _, host = netloc.rpartition("@")
        netloc = f"{user.partition(':')[0]}{':***' if ':' in user else ''}@{host}"
    query = "&".join(
        f"{key}=***" if key.lower() in SECRET_PARAMETERS else f"{key}={value}" if sep else key
        for key, sep, value in (part.partition("=") for part in parts.query.split("&") if part)
    )
    return urllib.parse.urlunsplit(parts._replace(netloc=netloc, query=query))


__all__ = [
    "CorruptTile",
    "Lease",
    "MapStore",
    "RegionChanged",
    "RegionExists",
    "RegionInfo",
    "RegionNotFound",
    "ResolutionChanged",
    "Snapshot",
    "StoreError",
    "StoreFull",
    "StoreUnavailable",
    "StoredMap",
    "TileInfo",
    "UploadConflict",
    "UploadNotFound",
    "open_store",
    "payload_digest",
    "redacted",
]
