"""City-scale builds with Dask: observation files of any size, one exactly-once upload.

The client plans **slices** from the files' metadata: runs of Parquet row groups, row
ranges of an Arrow IPC file or stream, byte ranges of a CSV file (cut at line ends), a
gzipped CSV whole. One task per slice reads it in batches of at most ``batch_rows``
rows, turns each batch into tile increments (:func:`accepted_increments`, the same
function uploads use) and sums them, so a worker's memory is set by the batch and the
region, never by the file. The slices' sums are added pairwise in a tree on the workers
(statistics are additive, so the sum is the batch's) and one ``store.apply`` commits the
total: the build is one ledger entry, replayable like any upload, and a failure anywhere
stores nothing. Every task is a pure function of its slice, so Dask recomputes the work
of a lost worker and the sum is the same. Service replicas see the new version at once.

Columns: those an upload takes (``x, y, z`` or ``lat, lon, alt_m``; ``ve, vn, vu``;
optionally ``input_noise_std``, ``sample_weight``, ``track`` and ``t``), or ADS-B state
vectors in either schema of :data:`bdf.ingest.ADSB_SCHEMAS` (converted with the region's
frame on the worker, tracks by icao24 and callsign; rows on the ground are rejected and
counted). A track's rows are weighed within each batch (:func:`bdf.ingest.track_weights`:
a track cut between batches weighs the same where it is sampled regularly). Workers read files by path, so on
a cluster every worker must see the paths (a shared volume, see the README).

The upload id defaults to a digest of the files' bytes (read by the workers), so
re-running a build of the same files is a replay whatever the slicing.
"""

from __future__ import annotations

import gzip
import hashlib
import os
import sys
import time
from collections.abc import Iterator
from concurrent.futures import CancelledError
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.ipc
import pyarrow.parquet as pq
from distributed.comm import CommClosedError
from tqdm import tqdm

from bdf import ingest
from bdf.region.evidence import REJECTED, UNTRACKED_WARNING, Increment, accepted_increments, region_total
from bdf.region.map import compute_posterior
from bdf.region.spec import RegionSpec, TileKey
from service import formats, wire
from service.maps import require_accepted
from service.problems import Problem
from service.refresh import fitted
from service.store import MapStore

SUFFIXES = (".parquet", ".arrow", ".csv", ".csv.gz", *ingest.JSON_SUFFIXES)
#: Rows a task reads at most (whole Parquet row groups may exceed it: they are the unit).
ROWS_PER_TASK = 500_000
#: Rows turned into evidence at once: with the window factors, about 1 kB of memory each.
BATCH_ROWS = 200_000
#: CSV bytes per task per row of ``rows_per_task`` (a line of the upload columns, about).
CSV_BYTES_PER_ROW = 64
#: Numeric columns: float64 from CSV (type inference per block could differ), numpy from ADS-B.
_NUMERIC_COLUMNS = (
    *wire.ENU_COLUMNS,
    *wire.WGS84_COLUMNS,
    *wire.VELOCITY_COLUMNS,
    "input_noise_std",
    "sample_weight",
    "t",
    *{c for cols, *_ in ingest.ADSB_SCHEMAS.values() for c in cols},
    "baroaltitude",
)
#: ADS-B columns read as numpy (the rest stay Arrow, never read): the numbers, the ground
#: flag and what names and times a track
_READ_COLUMNS = {*_NUMERIC_COLUMNS, "onground", "icao24", "callsign", "timestamp", "time"}


#: Dask starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Setting either threshold
#: turns off glibc's adaptive mmap threshold, which then stays at 128 kB: every larger
#: temporary of the evidence kernels is a fresh mapping that page-faults (slower slices in
#: ``bench/bench_build.py``). A worker's memory is bounded by its batch, so builds start workers
#: with these instead (give them to ``dask worker`` on a cluster too).
WORKER_ENV = {"MALLOC_TRIM_THRESHOLD_": str(128 * 2**20), "MALLOC_MMAP_THRESHOLD_": str(32 * 2**20)}


def local_cluster(workers: int, memory_limit: str = "auto"):
    """A ``LocalCluster`` of ``workers`` single-threaded worker processes for builds."""
    from distributed import LocalCluster

    saved = {k: os.environ.get(k) for k in WORKER_ENV}
    os.environ.update(WORKER_ENV)  # the nanny passes the parent's value on at spawn
    try:
        return LocalCluster(
            n_workers=workers, threads_per_worker=1, memory_limit=memory_limit, dashboard_address=None
        )
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k)
            else:
                os.environ[k] = v


class ClusterLost(RuntimeError):
    """The scheduler went away before the build finished (a lost worker is recomputed)."""


@dataclass(frozen=True)
class Slice:
    """Part of one file: rows ``[start, stop)`` (Parquet: row groups; CSV: bytes)."""

    path: str
    start: int
    stop: int


@dataclass
class Part:
    """The evidence of some slices: tile increments and the ledger summary."""

    increments: dict[TileKey, Increment]
    summary: dict


def suffix(path: Path) -> str:
    name = path.name.lower()
    return next((s for s in sorted(SUFFIXES, key=len, reverse=True) if name.endswith(s)), path.suffix)


def plan(paths, rows_per_task: int = ROWS_PER_TASK) -> list[Slice]:
    """The slices of ``paths``, from their metadata (nothing but Arrow stream headers is read)."""
    out = []
    for path in paths:
        kind = suffix(path)
        if kind == ".parquet":
            meta = pq.ParquetFile(path).metadata
            sizes = [meta.row_group(i).num_rows for i in range(meta.num_row_groups)]
            out += [Slice(str(path), a, b) for a, b in _runs(sizes, rows_per_task)]
        elif kind == ".arrow":
            rows = sum(batch.num_rows for batch in _arrow_batches(path))
            out += [Slice(str(path), a, min(a + rows_per_task, rows)) for a in range(0, rows, rows_per_task)]
        elif kind == ".csv":
            size = path.stat().st_size
            step = rows_per_task * CSV_BYTES_PER_ROW
            out += [Slice(str(path), a, min(a + step, size)) for a in range(0, size, step)]
        else:  # .csv.gz, JSON: one stream
            out.append(Slice(str(path), 0, -1))
    return out


def _runs(sizes: list[int], target: int) -> list[tuple[int, int]]:
    """Consecutive groups of items whose sizes add up to about ``target`` (at least one each)."""
    runs, start, rows = [], 0, 0
    for i, n in enumerate(sizes):
        if rows and rows + n > target:
            runs.append((start, i))
            start, rows = i, 0
        rows += n
    return [*runs, (start, len(sizes))] if sizes else []


def _arrow_batches(path) -> Iterator[pa.RecordBatch]:
    """The record batches of an Arrow IPC file or stream, memory-mapped (zero copy)."""
    source = pa.memory_map(str(path))
    try:
        reader = pa.ipc.open_file(source)
    except pa.ArrowInvalid:  # no file footer: a stream
        source.seek(0)
        yield from pa.ipc.open_stream(source)
        return
    yield from (reader.get_batch(i) for i in range(reader.num_record_batches))


def read_slice(piece: Slice, batch_rows: int = BATCH_ROWS) -> Iterator[pa.RecordBatch | pa.Table]:
    """The rows of ``piece`` in batches of at most ``batch_rows`` rows."""
    path = Path(piece.path)
    kind = suffix(path)
    if kind == ".parquet":
        with pq.ParquetFile(path) as pf:
            yield from pf.iter_batches(batch_rows, row_groups=range(piece.start, piece.stop))
    elif kind == ".arrow":
        at = 0
        for batch in _arrow_batches(path):
            a, b = max(piece.start - at, 0), min(piece.stop - at, batch.num_rows)
            at += batch.num_rows
            for c in range(a, b, batch_rows):
                yield batch.slice(c, min(batch_rows, b - c))
            if at >= piece.stop:
                return
    elif kind in ingest.JSON_SUFFIXES:  # one slice, read whole (traffic's samples are JSON)
        yield from pa.Table.from_pylist(ingest.json_records(path)).to_batches(batch_rows)
    else:
        yield from _csv_batches(path, piece, batch_rows)


def _csv_batches(path: Path, piece: Slice, batch_rows: int) -> Iterator[pa.RecordBatch]:
    """A CSV slice owns the lines that start in its byte range (the header is line one);
    a gzipped file is one slice, decompressed as it is read."""
    with (gzip.open if piece.stop < 0 else open)(path, "rb") as fh:
        header = fh.readline()
        if piece.stop < 0:
            source = pa.input_stream(str(path), compression="gzip")
        else:
            begin = max(_line_start(fh, piece.start), len(header))
            end = max(_line_start(fh, piece.stop), begin)
            fh.seek(begin)
            source = pa.BufferReader(header + fh.read(end - begin))
    names = header.decode().strip().split(",")
    types = {n: pa.float64() for n in names if n in _NUMERIC_COLUMNS}
    if not ingest.adsb_schema(names) and "track" in names:  # an upload's track id, not a heading
        types["track"] = pa.string()
    reader = pacsv.open_csv(
        source,
        read_options=pacsv.ReadOptions(block_size=max(batch_rows * 64, 1 << 20)),
        convert_options=pacsv.ConvertOptions(column_types=types),
    )
    for batch in reader:
        for c in range(0, batch.num_rows, batch_rows):
            yield batch.slice(c, batch_rows)


def _line_start(fh, offset: int) -> int:
    """The offset of the first line that starts at or after ``offset``."""
    if offset == 0:
        return 0
    fh.seek(offset - 1)
    fh.readline()
    return fh.tell()


def batch_evidence(spec: RegionSpec, batch: pa.RecordBatch | pa.Table) -> Part:
    """The evidence of one batch of rows (upload columns or ADS-B state vectors)."""
    if ingest.adsb_schema(batch.column_names):
        # the numbers and the ground flag as numpy; the strings stay Arrow (never read here)
        table = {
            n: col.to_numpy(zero_copy_only=False) if n in _READ_COLUMNS else col
            for n, col in zip(batch.column_names, batch.columns, strict=True)
        }
        X, V, keep, dropped = ingest.adsb_state(table, spec.frame())
        track, time = ingest.adsb_tracks(table)
        increments, summary = accepted_increments(spec, X, V, track=track[keep], time=time[keep])
        summary["rejected"]["non_finite"] += dropped["incomplete"]
        summary["rejected"]["on_ground"] = dropped["on_ground"]
        return Part(increments, summary)
    obs = formats.table_observations(spec, batch)
    return Part(
        *accepted_increments(
            spec, obs.X, obs.V, obs.input_noise_std, obs.sample_weight, track=obs.track, time=obs.time
        )
    )


def slice_evidence(spec_json: str, piece: Slice, batch_rows: int = BATCH_ROWS) -> Part:
    """The evidence of one slice (runs on a worker)."""
    spec = RegionSpec.model_validate_json(spec_json)
    total = Part({}, {"accepted": 0, "rejected": dict.fromkeys(REJECTED, 0), "untracked": 0})
    try:
        for batch in read_slice(piece, batch_rows):
            if batch.num_rows:
                total = merge(total, batch_evidence(spec, batch))
    except Problem as exc:
        raise ValueError(f"{piece.path}: {exc.detail}") from None
    except ValueError as exc:  # pyarrow's ArrowInvalid among them
        raise ValueError(f"{piece.path}: {exc}") from None
    return total


def file_digest(path: str) -> str:
    """SHA-256 of a file's bytes (runs on a worker): ``hashlib.file_digest`` reads into one
    reused buffer, faster than fresh reads (``bench/bench_kernels.py``)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def merge(a: Part, b: Part) -> Part:
    """The evidence of both parts."""
    increments = dict(a.increments)
    for key, inc in b.increments.items():
        old = increments.get(key)
        increments[key] = (
            inc if old is None else Increment(old.evidence + inc.evidence, old.points + inc.points)
        )
    reasons = a.summary["rejected"].keys() | b.summary["rejected"].keys()
    untracked = a.summary.get("untracked", 0) + b.summary.get("untracked", 0)
    summary = {
        "accepted": a.summary["accepted"] + b.summary["accepted"],
        "rejected": {
            k: a.summary["rejected"].get(k, 0) + b.summary["rejected"].get(k, 0) for k in sorted(reasons)
        },
        "untracked": untracked,
    }
    if untracked:
        summary["warnings"] = [UNTRACKED_WARNING]
    return Part(increments, summary)


def build(
    store: MapStore,
    region: str,
    paths,
    client,
    *,
    replace: bool = True,
    upload_id: str | None = None,
    progress: bool | None = None,
    rows_per_task: int = ROWS_PER_TASK,
    batch_rows: int = BATCH_ROWS,
) -> dict:
    """Learn ``region`` from observation files on the Dask ``client``'s workers.

    ``replace``: the map becomes these files alone (a fit); otherwise they are added.
    ``upload_id`` defaults to one derived from the files' bytes, so re-running the same
    build is a replay. Returns the ledger result, like an upload's.
    ``progress``: a bar over the slices (default: on a terminal). ``rows_per_task`` and
    ``batch_rows`` set the slices and the rows a worker holds at once.
    The result also says how long the evidence and the commit (a fit's posterior, then
    the store's transaction) took: ``seconds``.
    """
    paths = [Path(p).resolve() for p in paths]
    if not paths:
        raise ValueError("a build needs at least one observation file")
    for p in paths:
        if suffix(p) not in SUFFIXES:
            raise ValueError(f"{p}: a build reads {', '.join(SUFFIXES)} files")
        if not p.is_file():
            raise ValueError(f"{p}: no such file")
    if rows_per_task < 1 or batch_rows < 1:
        raise ValueError(f"rows_per_task and batch_rows must be positive, got {rows_per_task}, {batch_rows}")
    try:
        pieces = plan(paths, rows_per_task)
    except (pa.ArrowInvalid, OSError) as exc:
        raise ValueError(f"cannot read the files' metadata: {exc}") from None
    info = store.region(region)
    spec_id, spec_json = info.region_id, info.spec.model_dump_json()
    digests = client.map(file_digest, [str(p) for p in paths], pure=False)
    leaves = client.map(
        slice_evidence, [spec_json] * len(pieces), pieces, [batch_rows] * len(pieces), pure=False
    )
    parts = list(leaves)
    while len(parts) > 1:  # pairwise tree sum, on the workers, as the slices finish
        pairs = [parts[i : i + 2] for i in range(0, len(parts), 2)]
        parts = [client.submit(merge, *pair, pure=False) if len(pair) == 2 else pair[0] for pair in pairs]
    root = parts[0]
    del parts
    start = time.perf_counter()
    try:
        _follow(leaves, progress)
        total, digests = root.result(), client.gather(digests)
    except (CommClosedError, CancelledError) as exc:
        raise ClusterLost(
            f"the Dask scheduler was lost mid-build ({type(exc).__name__}); nothing was stored: "
            "run the build again"
        ) from exc
    digest = hashlib.sha256(f"build:{replace}:{','.join(digests)}".encode()).hexdigest()
    evidence_s, start = time.perf_counter() - start, time.perf_counter()
    require_accepted(total.summary, "build")
    info = store.region(region)  # apply refuses it if the region was re-created meanwhile
    post = None  # a fit's map is computed first: one that cannot be solved stores nothing
    if replace:
        evidence = region_total(info.spec, {k: i.evidence for k, i in total.increments.items()})
        post = compute_posterior(info.spec, evidence, stored=False)
    result = store.apply(
        region,
        spec_id,
        upload_id or f"build-{digest[:40]}",
        digest,
        total.increments,
        observations=total.summary["accepted"],
        replace=replace,
        summary=total.summary,
        hyper=None if post is None else fitted(post),
    )
    return result | {"seconds": {"evidence": evidence_s, "commit": time.perf_counter() - start}}


def _follow(futures: list, progress: bool | None) -> None:
    """Wait for ``futures`` (emptied: finished results are then the tree's alone) with a
    bar; the first failure raises here."""
    from distributed import as_completed

    disable = not sys.stderr.isatty() if progress is None else not progress
    with tqdm(total=len(futures), unit="slice", desc="evidence", disable=disable) as bar:
        pending = as_completed(futures)
        futures.clear()
        for future in pending:
            future.result()
            bar.update()
