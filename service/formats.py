"""Bodies in and out: JSON, Arrow IPC stream and Parquet in; JSON, Arrow, npz, GeoJSON out.

Positions arrive in the region's ENU frame (``x, y, z`` metres) or in WGS84 (``lat, lon``
degrees, ``alt_m`` metres above the ellipsoid). Velocities arrive as ``ve, vn, vu`` m/s in
the local east/north/up axes of each point (what ADS-B reports); for WGS84 input they are
rotated into the region's axes. Every velocity the service returns is in the region's
ENU axes. Missing or non-finite values are kept as NaN so the upload counts and rejects
their rows.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
import pyarrow as pa
import pyarrow.ipc
import pyarrow.parquet as pq
from pydantic import BaseModel, ConfigDict, Field

from bdf.tiles import RegionSpec
from service.problems import Problem

JSON = "application/json"
ARROW = "application/vnd.apache.arrow.stream"
PARQUET = "application/vnd.apache.parquet"
NPZ = "application/x-npz"
GEOJSON = "application/geo+json"
PARQUET_ALIASES = (PARQUET, "application/x-parquet")

Value = float | None  # null -> NaN: the row is rejected and counted, not the request
Row3 = Annotated[list[Value], Field(min_length=3, max_length=3)]
Frame = Literal["enu", "wgs84"]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
ENU_COLUMNS = ("x", "y", "z")
WGS84_COLUMNS = ("lat", "lon", "alt_m")
VELOCITY_COLUMNS = ("ve", "vn", "vu")


class ObservationsBody(BaseModel):
    """Observations for ``/observations`` and ``/fit`` (JSON form)."""

    model_config = ConfigDict(extra="forbid")
    frame: Frame = "enu"
    points: list[Row3] = Field(description="[x, y, z] ENU metres, or [lat, lon, alt_m]")
    velocities: list[Row3] = Field(description="[ve, vn, vu] m/s in each point's local ENU axes")
    input_noise_std: float | list[Value] | list[Row3] | None = Field(
        None, description="position noise std in metres: one number, one per point, or one per axis"
    )
    sample_weight: list[Value] | None = Field(
        None,
        description="weight per observation (>= 0), e.g. 1 / samples of a track per cell: "
        "correlated 1 Hz samples of one flight should not count as independent",
    )


class QueryBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: Frame = "enu"
    points: list[Row3]
    modes: bool = Field(False, description="add every traffic class's share, mean and std")
    heading_deg: FiniteFloat | list[FiniteFloat] | None = Field(
        None,
        description="degrees from north, clockwise (one, or one per point): mean and std become "
        "the mode of traffic flying that heading (a region of one direction has one mode)",
    )


class ModesResult(BaseModel):
    heading_deg: list[float | None] = Field(description="centre heading per class; null: the slow class")
    share: list[list[float]] = Field(description="(n, classes): fraction of traffic, summing to 1")
    share_std: list[float] = Field(description="(n,): epistemic std of each share")
    mean: list[list[list[float]]] = Field(description="(n, classes, 3) m/s")
    std: list[list[list[float]]] = Field(description="(n, classes, 3) predictive std, m/s")


class QueryResult(BaseModel):
    mean: list[list[float]] = Field(description="[ve, vn, vu] m/s, region ENU axes")
    std: list[list[float]] = Field(description="predictive std per component, m/s")
    known: list[bool] = Field(description="false where no tile has data (the answer is the prior)")
    region_version: int
    modes: ModesResult | None = None


@dataclass
class PointQuery:
    X: np.ndarray  # (n, 3) region ENU
    heading_deg: np.ndarray | None  # (n,) or None
    modes: bool


def class_headings(spec: RegionSpec) -> list[float | None]:
    """The centre heading of each traffic class of ``spec`` (None: the slow class)."""
    if spec.directions == 1:
        return [None]
    return [*spec.sectors.centres_deg.tolist(), None]


@dataclass
class Observations:
    X: np.ndarray  # (n, 3) region ENU
    V: np.ndarray  # (n, 3) region ENU axes
    input_noise_std: np.ndarray | None
    sample_weight: np.ndarray | None


def _array(rows, n_cols: int = 3) -> np.ndarray:
    out = np.array(rows, dtype=float) if len(rows) else np.empty((0, n_cols))
    return out.reshape(len(rows), n_cols) if n_cols > 1 else out


def _to_region(spec: RegionSpec, frame: str, P: np.ndarray, V: np.ndarray | None):
    if frame == "enu":
        return P, V
    with np.errstate(invalid="ignore"):
        X = spec.frame().to_enu(P[:, 0], P[:, 1], P[:, 2])
        X[~np.isfinite(P).all(1)] = np.nan
        if V is not None:
            V = spec.frame().rotate_velocity(P[:, 0], P[:, 1], V)
    return X, V


def _table(body: bytes, media: str) -> pa.Table:
    try:
        if media == ARROW:
            return pa.ipc.open_stream(body).read_all()
        return pq.read_table(io.BytesIO(body))
    except (pa.ArrowInvalid, OSError) as exc:
        kind = "an Arrow IPC stream" if media == ARROW else "a Parquet file"
        raise Problem(400, f"the body is not {kind}: {exc}") from exc


def _columns(table: pa.Table | pa.RecordBatch, names) -> np.ndarray:
    out = np.empty((table.num_rows, len(names)))
    for i, name in enumerate(names):
        try:
            out[:, i] = np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)
        except (pa.ArrowInvalid, TypeError, ValueError) as exc:
            raise Problem(422, f"column {name!r} is not numeric: {exc}") from exc
    return out


def _table_positions(table: pa.Table | pa.RecordBatch) -> tuple[str, np.ndarray]:
    names = set(table.column_names)
    has_enu, has_wgs = set(ENU_COLUMNS) <= names, set(WGS84_COLUMNS) <= names
    if has_enu == has_wgs:
        raise Problem(
            422,
            f"the table needs the columns {list(ENU_COLUMNS)} (ENU) or {list(WGS84_COLUMNS)} (WGS84),"
            f" exactly one of them; it has {sorted(names)}",
        )
    return ("enu", _columns(table, ENU_COLUMNS)) if has_enu else ("wgs84", _columns(table, WGS84_COLUMNS))


def read_observations(spec: RegionSpec, body: bytes, media: str, max_points: int) -> Observations:
    """Decode an upload or fit body (JSON, Arrow or Parquet) into region ENU arrays."""
    if media == JSON:
        obs = ObservationsBody.model_validate_json(body or b"{}")
        if len(obs.points) != len(obs.velocities):
            raise Problem(422, f"{len(obs.points)} points but {len(obs.velocities)} velocities")
        frame, P, V = obs.frame, _array(obs.points), _array(obs.velocities)
        noise, weight = obs.input_noise_std, obs.sample_weight
        if isinstance(noise, list):
            noise = _array(noise, 3 if noise and isinstance(noise[0], list) else 1)
    elif media == ARROW or media in PARQUET_ALIASES:
        table = _table(body, ARROW if media == ARROW else PARQUET)
        _check_count(table.num_rows, max_points)
        return table_observations(spec, table)
    else:
        raise Problem(415, f"send {JSON}, {ARROW} or {PARQUET}, not {media or 'no Content-Type'}")
    _check_count(len(P), max_points)
    return _observations(spec, frame, P, V, noise, weight)


def _check_count(n: int, max_points: int) -> None:
    if n > max_points:
        raise Problem(422, f"{n} observations in one request; the limit is {max_points}: split it")


def table_observations(spec: RegionSpec, table: pa.Table | pa.RecordBatch) -> Observations:
    """The observations of a table with the upload columns (an Arrow or Parquet body, or a
    slice of a build's file)."""
    missing = [c for c in VELOCITY_COLUMNS if c not in table.column_names]
    if missing:
        raise Problem(422, f"the table lacks the velocity columns {missing}")
    frame, P = _table_positions(table)
    V = _columns(table, VELOCITY_COLUMNS)
    noise, weight = (
        _columns(table, [c])[:, 0] if c in table.column_names else None
        for c in ("input_noise_std", "sample_weight")
    )
    return _observations(spec, frame, P, V, noise, weight)


def _observations(spec: RegionSpec, frame: str, P, V, noise, weight) -> Observations:
    if len(P) == 0:
        raise Problem(422, "the body holds no observations")
    X, V = _to_region(spec, frame, P, V)
    return Observations(
        X,
        V,
        None if noise is None else np.asarray(noise, float),
        None if weight is None else np.asarray(weight, float),
    )


def read_query(spec: RegionSpec, body: bytes, media: str, max_points: int, modes: bool = False) -> PointQuery:
    """Decode a query (JSON, or Arrow with an optional ``heading_deg`` column) into region
    ENU points (n, 3), the headings asked and whether the modes are (``modes``: the
    request's query parameter, or the JSON body's field)."""
    if media == JSON:
        query = QueryBody.model_validate_json(body or b"{}")
        frame, P, heading, modes = query.frame, _array(query.points), query.heading_deg, modes or query.modes
    elif media == ARROW:
        table = _table(body, ARROW)
        frame, P = _table_positions(table)
        heading = _columns(table, ("heading_deg",))[:, 0] if "heading_deg" in table.column_names else None
    else:
        raise Problem(415, f"send {JSON} or {ARROW}, not {media or 'no Content-Type'}")
    if len(P) > max_points:
        raise Problem(422, f"{len(P)} points in one query; the limit is {max_points}")
    X = _to_region(spec, frame, P, None)[0]  # the map rejects non-finite rows by number
    return PointQuery(X, None if heading is None else np.asarray(heading, float), modes)


def media_type(content_type: str | None) -> str:
    return (content_type or "").split(";")[0].strip().lower()


def negotiate(accept: str | None, offered: list[str]) -> str:
    """The first of ``offered`` the Accept header admits (``offered[0]`` for none or ``*/*``)."""
    if not accept:
        return offered[0]
    wanted = []
    for part in accept.split(","):
        media, *params = (p.strip() for p in part.split(";"))
        if any(p.replace(" ", "") in ("q=0", "q=0.0") for p in params):
            continue
        wanted.append(media.lower())
    for media in wanted:
        if media in ("*/*", "application/*"):
            return offered[0]
        if media in offered:
            return media
    raise Problem(406, f"this resource is available as {', '.join(offered)}; Accept asked for {accept!r}")


def arrow_body(columns: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> memoryview:
    """An Arrow IPC stream of ``columns`` in one buffer sized by a dry run, as a memoryview a
    response sends without a copy: half the time of a growing stream copied into ``bytes``
    for a 20 MB grid (bench/bench_kernels.py)."""
    table = pa.table(columns, metadata=metadata)
    size = pa.MockOutputStream()
    with pa.ipc.new_stream(size, table.schema) as writer:
        writer.write_table(table)
    buffer = pa.allocate_buffer(size.size())
    with pa.ipc.new_stream(pa.FixedSizeBufferWriter(buffer), table.schema) as writer:
        writer.write_table(table)
    return memoryview(buffer)


def arrow_bytes(columns: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> bytes:
    """:func:`arrow_body` as ``bytes`` (request bodies: HTTP clients take bytes)."""
    return arrow_body(columns, metadata).tobytes()


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """``np.savez`` into a buffer sized once: grown write by write, a 14 MB grid spent half
    its encoding in reallocations (bench/RESULTS.md, issue 20)."""
    buf = io.BytesIO()
    buf.seek(sum(np.asarray(a).nbytes for a in arrays.values()) + 4096 * (len(arrays) + 1))
    buf.write(b"\0")  # members and headers usually fit before this byte (if not, it grows)
    buf.seek(0)
    np.savez(buf, **arrays)
    buf.truncate(buf.tell())
    return buf.getvalue()


def vector_columns(prefix: str, values: np.ndarray, names=("e", "n", "u")) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": np.ascontiguousarray(values[:, i]) for i, n in enumerate(names)}
