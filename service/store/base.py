"""The MapStore interface, shared by the SQLite and PostgreSQL backends.

What is stored (schema version 5; both backends, same tables):

    meta     key, value                          schema_version
    regions  name, region_id, spec (JSON), version, observations, hyper (JSON or NULL),
             created_at, updated_at
    tiles    region_id, key "i_j_k", version, count, points, stats (blob), format_version, updated_at,
             checksum (CRC-32 of stats, "crc32:" and 8 hex digits; sha256 hex before)
    uploads  region_id, upload_id, kind, digest, result (JSON), applied_at     (the ledger)
    versions region_id, version, committed_at                                 (when each was written)
    maps     region_id, version, settled, computed_at, seconds, checksum, posterior (blob)
    leases   region_id, holder, version, since, expires_at

``tiles.stats`` is :func:`bdf.region.evidence.encode_tile`: the tile's statistics and their
rounding residual, each :meth:`bdf.statistics.SectorEvidence.to_bytes` (little-endian
float64, layout in :mod:`bdf.statistics`, ``format_version`` there); uploads and retractions
add to them in double-double arithmetic (:func:`bdf.statistics.compensated_sum`), so a
retraction is exact whatever the weight ratio of what it removes to what remains. A tile row
exists only once data reached the tile. Versions: every applied upload, fit or retraction
bumps the region's version by one and stamps every tile it touched with the new version, so
``(region_id, key, version)`` names one state of a tile's statistics (``region_id`` is new
for every created region, so a deleted and re-created name never reuses cache entries);
``versions`` says when each version was committed (how stale a map is,
:meth:`MapStore.committed_at`).

``regions.hyper`` records the hyperparameters last found for a spec with "auto" ones:
``{"alpha", "beta", "log_evidence", "fitted_at": t, "evidence_version": v, "settled": s,
"evidence_gap": nats}``, found on the region's data at version ``v``: their evidence maximum
(``settled``), or within ``evidence_gap`` (under a nat) of it while a refresh in the
background settles it (:mod:`service.maps`). It is a record, not an input: a fit writes it
with its tiles and a refresh after it (:meth:`MapStore.record_hyperparameters`, never older
over newer, nor unsettled over settled). Schema 1 stored tiles that overlapped (each
observation in up to 8 tiles), which a region-wide field cannot use: such a store is
refused with that reason. Schemas 2 and 3 are upgraded in place when opened.

Integrity: every read of ``stats`` checks its checksum first, so bytes damaged on disk are
reported (:class:`CorruptTile`, naming the tile) and never decoded into a map;
:meth:`MapStore.verify` checks a whole store. Schema 2 had no checksums: its blobs are
trusted once and checksummed; schema 3 had no ``versions`` (its versions' times are
unknown: ``committed_at`` is None for them).

``maps`` holds each region's newest computed map (:func:`bdf.region.map.encode_posterior`,
CRC-32 checked like the tiles): derived data, computed once by the process that holds the
region's ``leases`` row and loaded by every other process, replica and restart
(:mod:`service.refresh`); a newer version's map replaces it (never older over newer, nor
unsettled over settled). A lease expires unless renewed, so a crashed holder's work is
taken over; its times are the holders' clocks (replicas' clocks agree to well within a lease).

Exactly once: ``apply`` adds the increments of all tiles, bumps the version and writes
the ledger row in one transaction, under the region's row lock. A replay of an upload id
with the same digest returns the first result; another digest raises :class:`UploadConflict`.
Every write names the region instance it read (``region_id``): a region deleted or
re-created meanwhile makes it fail (:class:`RegionChanged`) and store nothing. Readers
read in one snapshot (``snapshot``), so they never see half an upload.

Retraction: the statistics are additive, so ``retract`` subtracts an upload's increments,
recomputed from the same rows (their digest must be the ledger's: nothing else is kept,
and no upload costs storage for a retraction it may never need). The ledger row's ``kind``
becomes ``retracted`` and its result keeps the retraction's (a retried retraction replays
it; a replay of the upload id still applies nothing).
"""

from __future__ import annotations

import functools
import hashlib
import json
import threading
import time
import uuid
import zlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field

import numpy as np

from bdf.region.evidence import Increment, decode_tile, decode_tile_parts, encode_tile
from bdf.region.spec import RegionSpec, TileKey, key_str, parse_key
from bdf.statistics import FORMAT_VERSION, READABLE_FORMATS, SectorEvidence, compensated_sum

SCHEMA_VERSION = 6
#: Tile rows written per statement batch inside ``apply`` (fewer round trips to a server).
WRITE_CHUNK = 16
#: Upload ids are client idempotency keys: printable, bounded.
MAX_UPLOAD_ID = 200


class StoreError(Exception):
    """Base of the store's errors."""


class RegionNotFound(StoreError, LookupError):
    pass


class RegionExists(StoreError):
    pass


class UploadConflict(StoreError):
    """An upload id already used for a different payload, or a retraction whose rows are
    not the upload's, or of an upload a later fit replaced."""


class UploadNotFound(StoreError, LookupError):
    """A retraction of an upload id the region's ledger does not hold."""


class RegionChanged(StoreError):
    """The region a write read was deleted (or re-created) before the write committed."""


class ResolutionChanged(RegionChanged):
    """A fit chose another heading resolution (``directions: "auto"``) after a write's
    evidence was split into the sectors before it: the write is computed again."""


class CorruptTile(StoreError):
    """A tile's stored statistics do not match their checksum (or cannot be decoded)."""


class StoreDamaged(StoreError):
    """The database is not a store, or its file is damaged: an operator's to restore."""


class StoreUnavailable(StoreError):
    """The database cannot be reached or written right now (down, connection lost, locked,
    read-only): nothing was stored, and the same request may succeed later."""

    retry_after_s = 5


class StoreFull(StoreUnavailable):
    """The database is out of disk space: nothing was stored."""

    retry_after_s = 60


@dataclass(frozen=True)
class RegionInfo:
    spec: RegionSpec
    region_id: str
    version: int
    observations: int
    tiles: int
    created_at: float
    updated_at: float
    hyper: dict | None = None  # the record of the hyperparameters last found (module doc)

    def hyperparameters(self) -> tuple:
        """``(alpha, beta)``: the spec's fixed values, else the ones last found (recorded
        at ``hyper["evidence_version"]``; "auto" where none are found yet)."""
        spec, fitted = self.spec, self.hyper or {}
        alpha = fitted.get("alpha", "auto") if spec.alpha == "auto" else spec.alpha
        beta = fitted.get("beta", "auto") if spec.beta == "auto" else spec.beta
        return alpha, beta


@dataclass(frozen=True)
class TileInfo:
    key: TileKey
    version: int
    count: float  # sum of sample weights
    points: int  # observations that reached the tile
    nbytes: int  # size of the stored statistics
    updated_at: float


@dataclass(frozen=True)
class Snapshot:
    """One consistent read of a region: its tiles and the statistics asked for."""

    region: RegionInfo
    tiles: dict[TileKey, TileInfo]
    evidence: dict[TileKey, SectorEvidence] = field(default_factory=dict)


@dataclass(frozen=True)
class StoredMap:
    """A region's stored map, as :meth:`MapStore.stored_map` reads it."""

    version: int
    settled: bool
    computed_at: float
    seconds: float  # how long it took to compute


@dataclass(frozen=True)
class Lease:
    """Who computes a region's map now (:meth:`MapStore.take_lease`)."""

    holder: str
    version: int
    since: float
    expires_at: float


def payload_digest(kind: str, *arrays: np.ndarray | None) -> str:
    """sha256 of an upload's content (dtype, shape and bytes of each array, None marked)."""
    h = hashlib.sha256(kind.encode())
    for arr in arrays:
        if arr is None:
            h.update(b"\x00none")
            continue
        arr = np.ascontiguousarray(arr)
        h.update(f"\x00{arr.dtype.str}{arr.shape}".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def check_upload_id(upload_id: str) -> str:
    if (
        not isinstance(upload_id, str)
        or not 0 < len(upload_id) <= MAX_UPLOAD_ID
        or not upload_id.isprintable()
    ):
        raise ValueError(f"an upload id must be 1 to {MAX_UPLOAD_ID} printable characters, got {upload_id!r}")
    return upload_id


class MapStore(ABC):
    """Regions, their tiles' statistics, and the upload ledger. Thread-safe; every method
    is one transaction."""

    #: reads never wait on a network or on a writer (a local file, WAL): the service runs
    #: light reads on its event loop (:mod:`service.lanes`)
    local_reads = False
    #: a test hook called inside ``apply`` after each batch of tile rows (fault injection)
    after_tile_write: Callable[[TileKey], None] | None = None
    #: called as the last step of every write transaction, its lock won and its rows
    #: written: raising rolls it back (the service: the request's deadline, so a write that
    #: waited past it stores nothing)
    before_commit: Callable[[], None] | None = None

    # -- backend primitives ------------------------------------------------------------------
    @abstractmethod
    def _write(self) -> AbstractContextManager:
        """A write transaction; yields ``q(sql, params) -> rows`` (``?`` placeholders), with
        ``q.many(sql, rows)`` for a batch of one statement."""

    @abstractmethod
    def _read(self) -> AbstractContextManager:
        """A read-only transaction on one snapshot; yields ``q`` as :meth:`_write`."""

    @abstractmethod
    def _lock_region(self) -> str:
        """SQL suffix that locks the selected region row for the transaction ('' if the
        transaction already holds the database write lock)."""

    def _init_connections(self) -> None:
        """One connection per thread (connections are not shared across threads)."""
        self._local = threading.local()
        self._connections: list = []
        self._lock = threading.Lock()
        self._before_close: list[Callable[[], None]] = []

    def on_close(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` first when the store closes (background users stop before it)."""
        self._before_close.append(fn)

    def _remember(self, conn):
        self._local.conn = conn
        with self._lock:
            self._connections.append(conn)
        return conn

    def _forget(self, conn) -> None:
        with self._lock:
            if conn in self._connections:
                self._connections.remove(conn)

    def close(self) -> None:
        """Close every connection this store opened, in all threads."""
        for fn in self._before_close:
            fn()
        with self._lock:
            for conn in self._connections:
                conn.close()
            self._connections.clear()
        self._local = threading.local()

    def _schema(self, blob_type: str) -> list[str]:
        return [
            "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
            """CREATE TABLE IF NOT EXISTS regions (
                name TEXT PRIMARY KEY, region_id TEXT NOT NULL UNIQUE, spec TEXT NOT NULL,
                version BIGINT NOT NULL, observations BIGINT NOT NULL, hyper TEXT,
                created_at DOUBLE PRECISION NOT NULL, updated_at DOUBLE PRECISION NOT NULL)""",
            f"""CREATE TABLE IF NOT EXISTS tiles (
                region_id TEXT NOT NULL REFERENCES regions (region_id) ON DELETE CASCADE,
                key TEXT NOT NULL, version BIGINT NOT NULL, count DOUBLE PRECISION NOT NULL,
                points BIGINT NOT NULL, stats {blob_type} NOT NULL, format_version INTEGER NOT NULL,
                updated_at DOUBLE PRECISION NOT NULL, checksum TEXT, PRIMARY KEY (region_id, key))""",
            """CREATE TABLE IF NOT EXISTS uploads (
                region_id TEXT NOT NULL REFERENCES regions (region_id) ON DELETE CASCADE,
                upload_id TEXT NOT NULL, kind TEXT NOT NULL, digest TEXT NOT NULL,
                result TEXT NOT NULL, applied_at DOUBLE PRECISION NOT NULL,
                PRIMARY KEY (region_id, upload_id))""",
            """CREATE TABLE IF NOT EXISTS versions (
                region_id TEXT NOT NULL REFERENCES regions (region_id) ON DELETE CASCADE,
                version BIGINT NOT NULL, committed_at DOUBLE PRECISION NOT NULL,
                PRIMARY KEY (region_id, version))""",
            f"""CREATE TABLE IF NOT EXISTS maps (
                region_id TEXT PRIMARY KEY REFERENCES regions (region_id) ON DELETE CASCADE,
                version BIGINT NOT NULL, settled INTEGER NOT NULL, computed_at DOUBLE PRECISION NOT NULL,
                seconds DOUBLE PRECISION NOT NULL, checksum TEXT NOT NULL, posterior {blob_type} NOT NULL)""",
            """CREATE TABLE IF NOT EXISTS leases (
                region_id TEXT PRIMARY KEY REFERENCES regions (region_id) ON DELETE CASCADE,
                holder TEXT NOT NULL, version BIGINT NOT NULL, since DOUBLE PRECISION NOT NULL,
                expires_at DOUBLE PRECISION NOT NULL)""",
        ]

    def _init_schema(self, q) -> None:
        rows = q("SELECT value FROM meta WHERE key = 'schema_version'")
        if not rows:
            q("INSERT INTO meta (key, value) VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        elif int(rows[0][0]) in (2, 3, 4, 5):  # 4 adds versions, 5 maps and leases, 6 model sectors
            if int(rows[0][0]) == 2:  # 3 added checksums: computed once over the stored blobs
                q("ALTER TABLE tiles ADD COLUMN checksum TEXT")
                for region_id, key, blob in q("SELECT region_id, key, stats FROM tiles"):
                    q(
                        "UPDATE tiles SET checksum = ? WHERE region_id = ? AND key = ?",
                        (checksum(blob), region_id, key),
                    )
            # 6 names the model's sectors: a region stored before holds evidence of its own
            # directions (one class: the paper's model), which a new spec's default would not read
            for name, text in q("SELECT name, spec FROM regions"):
                body = json.loads(text)
                if body.get("model_directions") is None:
                    body["model_directions"] = body.get("directions", 1)
                    q("UPDATE regions SET spec = ? WHERE name = ?", (json.dumps(body), name))
            q("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION),))
        elif int(rows[0][0]) != SCHEMA_VERSION:
            raise StoreError(
                f"store schema version {rows[0][0]}, this code reads {SCHEMA_VERSION}: schema 1 kept "
                "overlapping tiles a region-wide map cannot use; start a new store (data directory "
                "or PostgreSQL schema) and fit the regions again"
            )

    def ping(self) -> None:
        """One round trip to the database and its tables (readiness); raises if either is
        unreachable."""
        with self._read() as q:
            q("SELECT value FROM meta WHERE key = 'schema_version'")

    # -- regions -------------------------------------------------------------------------------
    def create_region(self, spec: RegionSpec) -> RegionInfo:
        now = time.time()
        with self._write() as q:  # one statement: concurrent creates of a name cannot both pass a check
            created = q(
                "INSERT INTO regions (name, region_id, spec, version, observations, created_at, updated_at)"
                " VALUES (?, ?, ?, 0, 0, ?, ?) ON CONFLICT (name) DO NOTHING RETURNING region_id",
                (spec.name, uuid.uuid4().hex, spec.model_dump_json(), now, now),
            )
            if not created:
                raise RegionExists(f"region {spec.name!r} exists")
            self._committed(q, created[0][0], 0)
        return self.region(spec.name)

    def _committed(self, q, region_id: str, version: int) -> None:
        """Record when ``version`` was written: at the end of its transaction (the time a
        version's lag counts from: no refresh could read it before); then
        :attr:`before_commit`."""
        q(
            "INSERT INTO versions (region_id, version, committed_at) VALUES (?, ?, ?)",
            (region_id, version, time.time()),
        )
        if self.before_commit is not None:
            self.before_commit()

    def committed_at(self, region_id: str, version: int) -> float | None:
        """When the region instance's ``version`` was committed (None if unknown: written
        before schema 4, or not a version of it)."""
        with self._read() as q:
            rows = q(
                "SELECT committed_at FROM versions WHERE region_id = ? AND version = ?", (region_id, version)
            )
        return float(rows[0][0]) if rows else None

    def region(self, name: str) -> RegionInfo:
        with self._read() as q:
            return self._region(q, name)

    def list_regions(self) -> list[RegionInfo]:
        with self._read() as q:
            names = [r[0] for r in q("SELECT name FROM regions ORDER BY name")]
            return [self._region(q, n) for n in names]

    def delete_region(self, name: str) -> None:
        with self._write() as q:
            rows = q(f"SELECT region_id FROM regions WHERE name = ?{self._lock_region()}", (name,))
            if not rows:
                raise RegionNotFound(f"no region {name!r}")
            for table in ("tiles", "uploads", "versions", "maps", "leases"):
                q(f"DELETE FROM {table} WHERE region_id = ?", (rows[0][0],))
            q("DELETE FROM regions WHERE name = ?", (name,))

    def _region(self, q, name: str) -> RegionInfo:
        rows = q(
            "SELECT r.spec, r.region_id, r.version, r.observations, r.created_at, r.updated_at, r.hyper,"
            " (SELECT COUNT(*) FROM tiles t WHERE t.region_id = r.region_id)"
            " FROM regions r WHERE r.name = ?",
            (name,),
        )
        if not rows:
            raise RegionNotFound(f"no region {name!r}")
        spec, region_id, version, observations, created, updated, hyper, tiles = rows[0]
        return RegionInfo(
            _spec(spec),
            region_id,
            int(version),
            int(observations),
            int(tiles),
            float(created),
            float(updated),
            None if hyper is None else json.loads(hyper),
        )

    # -- tiles -----------------------------------------------------------------------------------
    def tiles(self, name: str) -> list[TileInfo]:
        return list(self.snapshot(name, keys=()).tiles.values())

    def snapshot(
        self,
        name: str,
        keys: Iterable[TileKey] | None = None,
        need: Callable[[str, TileKey, int], bool] | None = None,
    ) -> Snapshot:
        """The region, all its tile rows, and the statistics of ``keys`` (all if None) for
        which ``need(region_id, key, version)`` is true (a cache says what it holds)."""
        with self._read() as q:
            region = self._region(q, name)
            tiles = {}
            for key, version, count, points, nbytes, updated in q(
                "SELECT key, version, count, points, length(stats), updated_at"
                " FROM tiles WHERE region_id = ?",
                (region.region_id,),
            ):
                k = parse_key(key)
                tiles[k] = TileInfo(k, int(version), float(count), int(points), int(nbytes), float(updated))
            wanted = tiles if keys is None else [k for k in keys if k in tiles]
            wanted = [k for k in wanted if need is None or need(region.region_id, k, tiles[k].version)]
            evidence = {}
            if wanted:
                marks = ",".join("?" * len(wanted))
                for key, blob, fmt, stored_checksum in q(
                    "SELECT key, stats, format_version, checksum FROM tiles"
                    f" WHERE region_id = ? AND key IN ({marks})",
                    (region.region_id, *[key_str(k) for k in wanted]),
                ):
                    k = parse_key(key)
                    evidence[k] = _decode(region.spec, k, blob, fmt, stored_checksum)
        return Snapshot(region, dict(sorted(tiles.items())), evidence)

    # -- uploads ---------------------------------------------------------------------------------
    def upload_result(self, name: str, upload_id: str, digest: str) -> dict | None:
        """The stored result of an applied upload id, None if unused; a different digest
        raises :class:`UploadConflict`."""
        with self._read() as q:
            region = self._region(q, name)
            return self._ledger(q, region.region_id, upload_id, digest)

    def _ledger(self, q, region_id: str, upload_id: str, digest: str) -> dict | None:
        rows = q(
            "SELECT digest, result FROM uploads WHERE region_id = ? AND upload_id = ?",
            (region_id, upload_id),
        )
        if not rows:
            return None
        if rows[0][0] != digest:
            raise UploadConflict(f"upload id {upload_id!r} was already used for different data")
        return {**json.loads(rows[0][1]), "replayed": True}

    def _locked(self, q, name: str, region_id: str, columns: str = "version") -> tuple:
        """The region row's ``columns``, locked for the transaction, if it is still the
        instance ``region_id`` the caller read; else :class:`RegionChanged` (or not found)."""
        rows = q(f"SELECT region_id, {columns} FROM regions WHERE name = ?{self._lock_region()}", (name,))
        if not rows:
            raise RegionNotFound(f"no region {name!r}")
        if rows[0][0] != region_id:
            raise RegionChanged(
                f"region {name!r} was deleted or re-created while this request ran; nothing was stored"
            )
        return rows[0][1:]

    def apply(
        self,
        name: str,
        region_id: str,
        upload_id: str,
        digest: str,
        increments: Mapping[TileKey, Increment],
        *,
        observations: int,
        replace: bool = False,
        summary: Mapping | None = None,
        hyper: Mapping | None = None,
        spec: RegionSpec | None = None,
    ) -> dict:
        """Add ``increments`` to their tiles (``replace``: drop every tile first, a fit),
        bump the version and record ``upload_id`` in the ledger, all in one transaction, if
        the region is still the instance ``region_id`` (else :class:`RegionChanged`).
        ``hyper``: the hyperparameters a fit found (module doc; ``evidence_version`` is
        filled in); a fit without them clears the record. ``spec``: the region's spec with
        the heading resolution a fit chose (``directions: "auto"``); increments split into
        other sectors than the spec's raise :class:`ResolutionChanged`.

        Returns the result recorded in the ledger (``summary`` plus upload_id,
        region_version, tiles_updated, replayed); a replay returns the first one.
        """
        check_upload_id(upload_id)
        with self._write() as q:
            version, stored, hyper_text = self._locked(q, name, region_id, "version, spec, hyper")
            now = time.time()  # with the write lock won: a writer that waited is not older
            version, stored = int(version) + 1, _spec(stored)
            first = self._ledger(q, region_id, upload_id, digest)
            if first is not None:
                return first
            if spec is not None and not replace:
                raise ValueError("only a fit chooses the region's heading resolution")
            spec = stored if spec is None else spec
            classes = spec.model_sectors.classes
            if any(len(inc.evidence.classes) != classes for inc in increments.values()):
                raise ResolutionChanged(
                    f"region {name!r} now splits its evidence into {spec.model_directions} heading sectors"
                )
            if replace:
                q("DELETE FROM tiles WHERE region_id = ?", (region_id,))
            keys = sorted(increments)
            old = {} if replace else self._tiles(q, spec, region_id, keys)
            for start in range(0, len(keys), WRITE_CHUNK):
                rows = []
                for key in keys[start : start + WRITE_CHUNK]:
                    total, points = increments[key]
                    residual = None
                    if key in old:
                        (stored, rounding), before = old[key]
                        (total, residual), points = compensated_sum(stored, rounding, total), before + points
                    rows.append(self._tile_row(region_id, key, version, total, residual, points, now))
                q.many(UPSERT_TILE, rows)
                if self.after_tile_write is not None:
                    self.after_tile_write(keys[start + len(rows) - 1])
            result = {
                **(summary or {}),
                "upload_id": upload_id,
                "kind": "fit" if replace else "observations",
                "region_version": version,
                "tiles_updated": len(increments),
            }
            if replace:
                hyper_text = None if hyper is None else json.dumps({**hyper, "evidence_version": version})
            q(
                "UPDATE regions SET version = ?, updated_at = ?, hyper = ?,"
                f" observations = {'' if replace else 'observations + '}? WHERE region_id = ?",
                (version, now, hyper_text, int(observations), region_id),
            )
            if spec is not stored:
                q("UPDATE regions SET spec = ? WHERE region_id = ?", (spec.model_dump_json(), region_id))
            q(
                "INSERT INTO uploads (region_id, upload_id, kind, digest, result, applied_at)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (region_id, upload_id, result["kind"], digest, json.dumps(result), now),
            )
            self._committed(q, region_id, version)
        return {**result, "replayed": False}

    @staticmethod
    def _tiles(q, spec: RegionSpec, region_id: str, keys: list[TileKey]) -> dict:
        """``key -> ((statistics, rounding residual), points)`` of the stored tiles among
        ``keys``."""
        out = {}
        if keys:
            marks = ",".join("?" * len(keys))
            for k, blob, fmt, stored_checksum, points in q(
                "SELECT key, stats, format_version, checksum, points FROM tiles"
                f" WHERE region_id = ? AND key IN ({marks})",
                (region_id, *map(key_str, keys)),
            ):
                key = parse_key(k)
                out[key] = (_decode(spec, key, blob, fmt, stored_checksum, parts=True), int(points))
        return out

    @staticmethod
    def _tile_row(
        region_id: str,
        key: TileKey,
        version: int,
        total: SectorEvidence,
        residual: SectorEvidence | None,
        points: int,
        now: float,
    ):
        blob = encode_tile(total, total.scaled(0.0) if residual is None else residual)
        return (
            region_id,
            key_str(key),
            version,
            total.count,
            points,
            blob,
            FORMAT_VERSION,
            now,
            checksum(blob),
        )

    def record_hyperparameters(
        self, name: str, region_id: str, hyper: Mapping, evidence_version: int
    ) -> None:
        """Record ``hyper``, found on the data of the region instance ``region_id`` at
        ``evidence_version`` (module doc), unless the record is of a newer version already,
        or of this one and settled. The map does not change (no new version)."""
        with self._write() as q:
            (stored,) = self._locked(q, name, region_id, "hyper")
            old = {} if stored is None else json.loads(stored)
            rank = (old.get("evidence_version", -1), old.get("settled", True))
            if rank < (evidence_version, hyper.get("settled", True)):
                q(
                    "UPDATE regions SET hyper = ? WHERE region_id = ?",
                    (json.dumps({**hyper, "evidence_version": int(evidence_version)}), region_id),
                )

    def retract(
        self,
        name: str,
        region_id: str,
        upload_id: str,
        digest: str,
        increments: Mapping[TileKey, Increment],
        *,
        observations: int,
    ) -> dict:
        """Subtract an applied upload's ``increments`` (recomputed from its rows, whose
        ``digest`` must be the ledger's) from its tiles, in one transaction: the map becomes
        the map without that upload. A tile left with no observation is dropped. The ledger
        row turns ``retracted`` and keeps the retraction's result, so a retried retraction
        returns it (``replayed``). A fit cannot be retracted, nor an upload a later fit
        replaced (:class:`UploadConflict`)."""
        with self._write() as q:
            version, spec = self._locked(q, name, region_id, "version, spec")
            now = time.time()  # with the write lock won: a writer that waited is not older
            version, spec = int(version) + 1, _spec(spec)
            rows = q(
                "SELECT kind, digest, result FROM uploads WHERE region_id = ? AND upload_id = ?",
                (region_id, upload_id),
            )
            if not rows:
                raise UploadNotFound(f"region {name!r} has no upload {upload_id!r} to retract")
            kind, stored_digest, applied = rows[0][0], rows[0][1], json.loads(rows[0][2])
            if kind == "fit":
                raise UploadConflict(f"{upload_id!r} is a fit, which replaced the map: fit again instead")
            if stored_digest != digest:
                raise UploadConflict(
                    f"these rows are not those of upload {upload_id!r}: send exactly the rows it sent"
                )
            if kind == "retracted":
                return {**applied["retraction"], "replayed": True}
            fits = [
                json.loads(r[0])["region_version"]
                for r in q("SELECT result FROM uploads WHERE region_id = ? AND kind = 'fit'", (region_id,))
            ]
            if fits and max(fits) > applied["region_version"]:
                raise UploadConflict(
                    f"upload {upload_id!r} (version {applied['region_version']}) was replaced by the fit "
                    f"at version {max(fits)}: its rows are no longer in the map"
                )
            keys = sorted(increments)
            old = self._tiles(q, spec, region_id, keys)
            kept, dropped = [], []
            for key in keys:
                (stored, rounding), before = old[key]
                total, residual = compensated_sum(stored, rounding, increments[key].evidence.scaled(-1.0))
                points = before - increments[key].points
                if points <= 0:
                    dropped.append((region_id, key_str(key)))
                else:
                    kept.append(self._tile_row(region_id, key, version, total, residual, points, now))
            if dropped:
                q.many("DELETE FROM tiles WHERE region_id = ? AND key = ?", dropped)
            for start in range(0, len(kept), WRITE_CHUNK):
                q.many(UPSERT_TILE, kept[start : start + WRITE_CHUNK])
            result = {
                "upload_id": upload_id,
                "kind": "retraction",
                "accepted": int(observations),
                "rejected": applied.get("rejected", {}),
                "region_version": version,
                "tiles_updated": len(keys),
            }
            q(
                "UPDATE regions SET version = ?, updated_at = ?, observations = observations - ?"
                " WHERE region_id = ?",
                (version, now, int(observations), region_id),
            )
            q(
                "UPDATE uploads SET kind = 'retracted', result = ? WHERE region_id = ? AND upload_id = ?",
                (json.dumps({**applied, "retraction": result}), region_id, upload_id),
            )
            self._committed(q, region_id, version)
        return {**result, "replayed": False}

    # -- computed maps and their leases -------------------------------------------------------
    def save_map(self, region_id: str, version: int, settled: bool, seconds: float, blob: bytes) -> bool:
        """Store the map of the region instance's ``version`` (``blob``: its encoded posterior)
        unless a newer one, or this version's settled, is stored; returns whether it was."""
        with self._write() as q:
            if not q("SELECT 1 FROM regions WHERE region_id = ?", (region_id,)):
                return False  # deleted meanwhile: its map goes with it
            rows = q(
                "INSERT INTO maps (region_id, version, settled, computed_at, seconds, checksum, posterior)"
                " VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (region_id) DO UPDATE SET"
                " version = excluded.version, settled = excluded.settled, computed_at = excluded.computed_at,"
                " seconds = excluded.seconds, checksum = excluded.checksum, posterior = excluded.posterior"
                " WHERE maps.version < excluded.version"
                " OR (maps.version = excluded.version AND maps.settled < excluded.settled)"
                " RETURNING version",
                (region_id, int(version), int(settled), time.time(), float(seconds), checksum(blob), blob),
            )
        return bool(rows)

    def stored_map(self, region_id: str) -> StoredMap | None:
        """What the region instance's stored map is (version, settled, when, how long it
        took), without its bytes; None if none is."""
        with self._read() as q:
            rows = q(
                "SELECT version, settled, computed_at, seconds FROM maps WHERE region_id = ?", (region_id,)
            )
        return (
            StoredMap(int(rows[0][0]), bool(rows[0][1]), float(rows[0][2]), float(rows[0][3]))
            if rows
            else None
        )

    def load_map(self, region_id: str) -> tuple[StoredMap, bytes] | None:
        """The region instance's stored map and its bytes, checked against their checksum
        (:class:`CorruptTile` if they fail); None if none is stored."""
        with self._read() as q:
            rows = q(
                "SELECT version, settled, computed_at, seconds, checksum, posterior FROM maps"
                " WHERE region_id = ?",
                (region_id,),
            )
        if not rows:
            return None
        version, settled, computed_at, seconds, stored_checksum, blob = rows[0]
        blob = bytes(blob)
        if not checks_out(blob, stored_checksum):
            raise CorruptTile(f"the stored map of version {version} fails its checksum (damaged on disk)")
        return StoredMap(int(version), bool(settled), float(computed_at), float(seconds)), blob

    def drop_map(self, region_id: str, version: int) -> None:
        """Drop the stored map of ``version`` (one that cannot be read: the next refresh
        computes it again)."""
        with self._write() as q:
            q("DELETE FROM maps WHERE region_id = ? AND version = ?", (region_id, int(version)))

    def take_lease(self, region_id: str, holder: str, version: int, seconds: float) -> Lease:
        """Hold the region instance's refresh lease for ``seconds`` (to compute ``version``)
        if it is free, expired or ``holder``'s own (then renewed); returns the lease as it
        is now: ``holder``'s if taken. :class:`RegionChanged` if the region is gone."""
        now = time.time()
        with self._write() as q:
            if not q("SELECT 1 FROM regions WHERE region_id = ?", (region_id,)):
                raise RegionChanged("the region was deleted or re-created meanwhile")
            q(
                "INSERT INTO leases (region_id, holder, version, since, expires_at) VALUES (?, ?, ?, ?, ?)"
                " ON CONFLICT (region_id) DO UPDATE SET holder = excluded.holder, version = excluded.version,"
                " since = CASE WHEN leases.holder = excluded.holder AND leases.version = excluded.version"
                " THEN leases.since ELSE excluded.since END, expires_at = excluded.expires_at"
                " WHERE leases.expires_at < ? OR leases.holder = excluded.holder",
                (region_id, holder, int(version), now, now + seconds, now),
            )
            rows = q(
                "SELECT holder, version, since, expires_at FROM leases WHERE region_id = ?", (region_id,)
            )
        holder_now, version_now, since, expires = rows[0]
        return Lease(holder_now, int(version_now), float(since), float(expires))

    def release_lease(self, region_id: str, holder: str) -> None:
        """Free the lease if ``holder`` holds it."""
        with self._write() as q:
            q("DELETE FROM leases WHERE region_id = ? AND holder = ?", (region_id, holder))

    def verify(self) -> dict[str, list[str]]:
        """Check every region's spec, its stored map's checksum, and every stored tile: its
        checksum, that it decodes, that its statistics are finite and within the region's
        envelope, and that they can be trusted after retractions; returns, per region, the
        problems found (empty lists: the store is sound)."""
        report = {}
        with self._read() as q:
            names = [r[0] for r in q("SELECT name FROM regions ORDER BY name")]
        for name in names:
            problems = report.setdefault(name, [])
            try:
                info = self.region(name)
            except (StoreError, ValueError) as exc:  # a spec this code cannot read
                problems.append(f"region {name!r} does not decode: {exc}".splitlines()[0])
                continue
            with self._read() as q:
                keys = [r[0] for r in q("SELECT key FROM tiles WHERE region_id = ?", (info.region_id,))]
                retracted = bool(
                    q("SELECT 1 FROM uploads WHERE region_id = ? AND kind = 'retracted'", (info.region_id,))
                )
            try:
                self.load_map(info.region_id)
            except CorruptTile as exc:
                problems.append(f"region {name!r}: {exc}; the next refresh computes it again")
            for key in keys:  # one tile in memory at a time
                with self._read() as q:
                    rows = q(
                        "SELECT stats, format_version, checksum, points FROM tiles"
                        " WHERE region_id = ? AND key = ?",
                        (info.region_id, key),
                    )
                if rows:
                    try:
                        evidence = _decode(info.spec, parse_key(key), *rows[0][:3])
                    except StoreError as exc:
                        problems.append(str(exc))
                        continue
                    found = info.spec.envelope.problems(evidence, int(rows[0][3]))
                    if retracted and int(rows[0][1]) < COMPENSATED_FORMAT:
                        found.append(
                            f"statistics format {rows[0][1]}, stored before retractions were exact, in a "
                            "region with retractions: an upload retracted from a tile it outweighed left "
                            "cancellation error, so these statistics cannot be trusted: fit the region again"
                        )
                    problems.extend(f"tile {key} of region {name!r}: {problem}" for problem in found)
        return report


#: The first statistics format whose tiles keep their rounding residual (exact retractions).
COMPENSATED_FORMAT = 5

UPSERT_TILE = (
    "INSERT INTO tiles"
    " (region_id, key, version, count, points, stats, format_version, updated_at, checksum)"
    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (region_id, key) DO UPDATE SET"
    " version = excluded.version, count = excluded.count, points = excluded.points,"
    " stats = excluded.stats, format_version = excluded.format_version,"
    " updated_at = excluded.updated_at, checksum = excluded.checksum"
)


def checksum(blob) -> str:
    """A tile blob's checksum: CRC-32, against damage on disk, not tampering (a tenth of
    sha256's time on a tile's megabytes, read and written inside the write lock)."""
    return f"crc32:{zlib.crc32(blob):08x}"


def checks_out(blob, stored: str) -> bool:
    """The blob matches its stored checksum (:func:`checksum`, or the sha256 hex of tiles
    written before)."""
    if stored is not None and stored.startswith("crc32:"):
        return stored == checksum(blob)
    return stored == hashlib.sha256(blob).hexdigest()


def _decode(spec: RegionSpec, key: TileKey, blob, format_version, stored_checksum, parts: bool = False):
    """A tile's statistics, after checking them against their checksum (``parts``: the
    statistics and their rounding residual, :func:`bdf.region.evidence.decode_tile_parts`)."""
    where = f"tile {key_str(key)} of region {spec.name!r}"
    if int(format_version) not in READABLE_FORMATS:
        raise StoreError(f"{where} has statistics format {format_version}; readable: {READABLE_FORMATS}")
    blob = bytes(blob)
    if not checks_out(blob, stored_checksum):
        raise CorruptTile(
            f"{where}: its stored statistics fail their checksum (damaged on disk); "
            "`bdf verify` lists every such tile; restore the store from a backup or fit the region again"
        )
    try:
        return (decode_tile_parts if parts else decode_tile)(spec, key, blob, int(format_version))
    except ValueError as exc:
        raise CorruptTile(f"{where}: its stored statistics cannot be decoded ({exc})") from exc


@functools.lru_cache(maxsize=256)
def _spec(text: str) -> RegionSpec:
    """A stored spec, parsed once per text: validating a spec costs a millisecond, and every
    request reads its region's (specs are frozen, so sharing them is safe)."""
    return RegionSpec.model_validate_json(text)
