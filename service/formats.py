"""Bodies in and out: JSON, Arrow IPC stream and Parquet in; JSON, Arrow, npz, GeoJSON out.

Positions arrive in the region's ENU frame (``x, y, z`` metres) or in WGS84 (``lat, lon``
degrees, ``alt_m`` metres above the ellipsoid). Velocities arrive as ``ve, vn, vu`` m/s in
the local east/north/up axes of each point (what ADS-B reports); for WGS84 input they are
rotated into the region's axes. Every velocity the service returns is in the region's
ENU axes. Missing or non-finite values are kept as NaN so the upload counts and rejects
their rows.
"""

from __future__ import annotations

import functools
import io
import json
import struct
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
import orjson
import pyarrow as pa
import pyarrow.ipc
import pyarrow.parquet as pq
import pydantic_core
from fastapi import Response
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from bdf import ingest
from bdf.region.route import MAX_ROUTE_SPEED_MPS, MIN_TUBE_STD_MPS, VEHICLES, Vehicle, checked, vehicle
from bdf.region.spec import RegionSpec
from bdf.validation import rows_all
from service import slices, webmap
from service.problems import Problem
from service.wire import (
    ARROW,
    ENU_COLUMNS,
    GEOJSON,
    JSON,
    NPZ,
    PARQUET,
    PARQUET_ALIASES,
    PNG,
    QUERY_COLUMNS,
    UPLOAD_COLUMNS,
    VELOCITY_COLUMNS,
    WGS84_COLUMNS,
)

#: a JSON number, never a string, a bool, NaN or an infinity (1e400 parses as one)
FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Value = FiniteFloat | None  # null -> NaN: the row is rejected and counted, not the request
Row3 = Annotated[list[Value], Field(min_length=3, max_length=3)]
Frame = Literal["enu", "wgs84"]
TrackId = Annotated[str, Field(max_length=256)] | Annotated[int, Field(strict=True)] | None


@dataclass(frozen=True)
class Limits:
    """What one request body may decode into, checked before it is decoded."""

    rows: int
    decoded_bytes: int
    json_bytes: int


class ObservationsBody(BaseModel):
    """Observations for ``/observations`` and ``/fit`` (JSON form)."""

    model_config = ConfigDict(extra="forbid")
    frame: Frame = "enu"
    points: list[Row3] = Field(min_length=1, description="[x, y, z] ENU metres, or [lat, lon, alt_m]")
    velocities: list[Row3] = Field(
        min_length=1, description="[ve, vn, vu] m/s in each point's local ENU axes"
    )
    input_noise_std: float | list[Value] | list[Row3] | None = Field(
        None, description="position noise std in metres: one number, one per point, or one per axis"
    )
    sample_weight: list[Value] | None = Field(
        None,
        description="weight per observation (>= 0): how much to trust the row; with track, it "
        "multiplies the row's track weight",
    )
    track: list[TrackId] | None = Field(
        None,
        description="the track (aircraft, flight or radar track id: string or integer) of each row; "
        "with t, the service weighs a track's correlated rows itself (about one observation per "
        'kernel width flown). Rows without one (null or "") count as independent observations',
    )
    t: list[Value] | None = Field(None, description="time of each row, seconds (with track)")


class QueryBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: Frame = "enu"
    points: list[Row3]
    modes: bool = Field(False, strict=True, description="add every traffic class's share, mean and std")
    heading_deg: FiniteFloat | list[FiniteFloat] | None = Field(
        None,
        description="degrees from north, clockwise (one, or one per point): mean and std become "
        "the mode of traffic flying that heading: the two nearest sectors' modes pooled, the sector's "
        "own at its centre (a region of one direction has one mode)",
    )


class VehicleBody(BaseModel):
    """A vehicle's envelope (:class:`bdf.region.route.Vehicle`)."""

    model_config = ConfigDict(extra="forbid")
    cruise_mps: Annotated[float, Field(gt=0, le=MAX_ROUTE_SPEED_MPS, allow_inf_nan=False)]
    min_turn_radius_m: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    max_climb_deg: Annotated[float, Field(gt=0, lt=90)]
    max_descent_deg: Annotated[float, Field(gt=0, lt=90)]
    floor_m: FiniteFloat
    ceiling_m: FiniteFloat


class RouteBody(BaseModel):
    """A route to assess (JSON form; GeoJSON: a LineString Feature whose properties hold the
    other fields)."""

    model_config = ConfigDict(extra="forbid")
    frame: Frame = "enu"
    points: list[Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]] = Field(
        description="the polyline: [x, y, z] ENU metres, or [lat, lon, alt_m]"
    )
    times_s: list[FiniteFloat] | None = Field(
        None, description="seconds from departure at each point (default: at the vehicle's cruise airspeed)"
    )
    heading_deg: list[FiniteFloat] | None = Field(
        None, description="heading flown on each segment, degrees from north (default: its own direction)"
    )
    max_std_mps: Annotated[float, Field(ge=MIN_TUBE_STD_MPS, allow_inf_nan=False)] = Field(
        description="the tube bound on the predictive std, m/s"
    )
    vehicle: Literal[tuple(VEHICLES)] | VehicleBody = "evtol"


class AssessResult(BaseModel):
    segments: dict[str, list[float]] = Field(
        description="per segment: length_m, duration_s, max_std_mps, mean_std_mps, in_tube_fraction, "
        "integrated_risk_m, conflict_exposure, flow_mismatch_mps, flow_heading_offset_deg, "
        "traffic_speed_mps"
    )
    total: dict[str, float] = Field(description="the same over the whole route")
    envelope: dict[str, float | bool | None] = Field(
        description="least turn radius (null: it never turns), steepest climb and descent, lowest and "
        "highest altitude, each limit's verdict and flyable"
    )
    region_version: int


@dataclass
class RouteQuery:
    P: np.ndarray  # (n, 3) region ENU
    times_s: np.ndarray  # (n,) seconds from departure
    heading_deg: np.ndarray  # (n - 1,) heading flown per segment
    max_std_mps: float
    vehicle: Vehicle


def read_route(spec: RegionSpec, body: bytes, media: str, limits: Limits) -> RouteQuery:
    """Decode a route (JSON :class:`RouteBody`, or a GeoJSON LineString Feature or a
    FeatureCollection of one, [lon, lat, alt_m], its other fields in ``properties``) into
    region ENU points inside the region."""
    if media not in (JSON, GEOJSON):
        raise Problem(415, f"send {JSON} or {GEOJSON}, not {media or 'no Content-Type'}")
    raw = json_document(body, limits, "the route")
    if media == GEOJSON:
        raw = _geojson_route(raw)
    route = RouteBody.model_validate(raw)
    _check_size(len(route.points), 0, limits)
    given = _array(route.points)
    P = _to_region(spec, route.frame, given, None)[0]
    if len(P) < 2:
        raise Problem(422, f"a route needs at least 2 points, got {len(P)}")
    _inside(spec, P, "route point(s)", route.frame, given)
    try:
        craft = vehicle(route.vehicle if isinstance(route.vehicle, str) else route.vehicle.model_dump())
        P, times, heading = checked(P, craft, route.times_s, route.heading_deg)
    except ValueError as exc:
        raise Problem(422, str(exc)) from None
    return RouteQuery(P, times, heading, route.max_std_mps, craft)


def _geojson_route(doc) -> dict:
    """A GeoJSON route as :class:`RouteBody`'s fields (frame wgs84)."""
    if isinstance(doc, dict) and doc.get("type") == "FeatureCollection":
        features = doc.get("features")
        if not isinstance(features, list):
            raise Problem(422, "a FeatureCollection's features are a list of Features")
        lines = [f for f in features if _member(f, "geometry").get("type") == "LineString"]
        if len(lines) != 1:
            raise Problem(422, f"a FeatureCollection to assess holds one LineString, not {len(lines)}")
        doc = lines[0]
    geometry = doc.get("geometry") if isinstance(doc, dict) and doc.get("type") == "Feature" else None
    if not isinstance(geometry, dict) or geometry.get("type") != "LineString":
        raise Problem(
            422, "send a GeoJSON Feature with a LineString geometry ([lon, lat, alt_m] coordinates)"
        )
    coordinates = geometry.get("coordinates")
    if not isinstance(coordinates, list) or not all(isinstance(c, list) and len(c) == 3 for c in coordinates):
        raise Problem(422, "a route's coordinates are [lon, lat, alt_m] triples")
    properties = doc.get("properties") or {}
    if not isinstance(properties, dict):
        raise Problem(422, "a Feature's properties are an object: times_s, heading_deg, max_std_mps, vehicle")
    fields = {
        k: properties[k] for k in ("times_s", "heading_deg", "max_std_mps", "vehicle") if k in properties
    }
    return {"frame": "wgs84", "points": [[lat, lon, alt] for lon, lat, alt in coordinates], **fields}


class ModesResult(BaseModel):
    heading_deg: list[float | None] = Field(description="centre heading per class; null: the slow class")
    share: list[list[float]] = Field(description="(n, classes): fraction of traffic, summing to 1")
    share_std: list[float] = Field(description="(n,): epistemic std of each share")
    mean: list[list[list[float]]] = Field(description="(n, classes, 3) m/s")
    std: list[list[list[float]]] = Field(description="(n, classes, 3) predictive std, m/s")


class QueryResult(BaseModel):
    mean: list[list[float] | None] = Field(
        description="[ve, vn, vu] m/s, region ENU axes; null for a point outside the region"
    )
    std: list[list[float] | None] = Field(description="predictive std per component, m/s; null outside")
    known: list[bool] = Field(
        description="false where no tile has data (the answer is the prior), or outside"
    )
    outside: int = Field(
        0, description="points outside the region: their rows are null (also X-Points-Outside)"
    )
    region_version: int
    modes: ModesResult | None = None


@dataclass
class PointQuery:
    X: np.ndarray  # (n, 3) region ENU
    heading_deg: np.ndarray | None  # (n,) or None
    modes: bool
    outside: np.ndarray  # (n,) the points outside the region: answered null (:func:`encode_points`)

    @property
    def inside(self) -> PointQuery:
        """The query of the points inside the region (itself when none is outside)."""
        if not self.outside.any():
            return self
        keep = ~self.outside
        heading = self.heading_deg[keep] if self.heading_deg is not None else None
        return PointQuery(self.X[keep], heading, self.modes, self.outside[keep])


def class_headings(spec: RegionSpec) -> list[float | None]:
    """The centre heading of each traffic class of ``spec`` (None: the slow class)."""
    if spec.one_class:
        return [None]
    return [*spec.sectors.centres_deg.tolist(), None]


@dataclass
class UploadRows:
    X: np.ndarray  # (n, 3) region ENU
    V: np.ndarray  # (n, 3) region ENU axes
    input_noise_std: np.ndarray | None
    sample_weight: np.ndarray | None
    track: np.ndarray | None = None  # (n,) int64 codes, -1: no track (:func:`bdf.ingest.track_codes`)
    time: np.ndarray | None = None  # (n,) seconds, with ``track``


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


def _table(body: bytes, media: str, allowed: frozenset, limits: Limits) -> pa.Table:
    """The body's table: its schema, row count and decoded size checked before any column
    is decoded (a few hundred kB of zstd can hold gigabytes)."""
    try:
        return (
            _arrow_table(body, allowed, limits) if media == ARROW else _parquet_table(body, allowed, limits)
        )
    except (pa.ArrowInvalid, OSError, struct.error, StopIteration) as exc:
        kind = "an Arrow IPC stream" if media == ARROW else "a Parquet file"
        raise Problem(400, f"the body is not {kind}: {exc or 'it is empty'}") from exc


def _check_schema(schema: pa.Schema, allowed: frozenset) -> None:
    """Documented columns only, each once, each a number (float or integer; ``track`` may
    also be a string)."""
    names = schema.names
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise Problem(422, f"the table has the column(s) {repeated} more than once")
    unknown = sorted(set(names) - allowed)
    if unknown:
        raise Problem(422, f"unknown column(s) {unknown}; this body takes {sorted(allowed)}")
    for field in schema:
        if field.name == "track":
            _track_type(field.type)
        else:
            _numeric(field.name, field.type)


def _track_type(type_: pa.DataType) -> None:
    if not (pa.types.is_integer(type_) or pa.types.is_string(type_) or pa.types.is_large_string(type_)):
        raise Problem(422, f"column 'track' has type {type_}; it must be a string or an integer")


def _numeric(name: str, type_: pa.DataType) -> None:
    if not (pa.types.is_floating(type_) or pa.types.is_integer(type_)):
        raise Problem(422, f"column {name!r} has type {type_}; it must be a number (float or integer)")


def _check_size(rows: int, decoded_bytes: int, limits: Limits) -> None:
    if rows > limits.rows:
        raise Problem(422, f"{rows} rows in one request; the limit is {limits.rows}: split it")
    if decoded_bytes > limits.decoded_bytes:
        raise Problem(
            413,
            f"the body decodes into {decoded_bytes / 2**20:.1f} MiB; the limit is "
            f"{limits.decoded_bytes / 2**20:g} MiB: split it",
        )


def _arrow_table(body: bytes, allowed: frozenset, limits: Limits) -> pa.Table:
    reader = pa.ipc.MessageReader.open_stream(pa.py_buffer(body))
    schema = pa.ipc.read_schema(reader.read_next_message())
    _check_schema(schema, allowed)
    batches, rows, decoded = [], 0, 0
    for message in reader:
        if message.type != "record batch":
            raise Problem(422, f"a stream of numeric columns holds record batches, not a {message.type}")
        n, size = _batch_size(message)
        rows, decoded = rows + n, decoded + size
        _check_size(rows, decoded, limits)
        batch = pa.ipc.read_record_batch(message, schema)
        batch.validate(full=True)  # the buffers agree with the declared lengths
        batches.append(batch)
    return pa.Table.from_batches(batches, schema)


def _batch_size(message) -> tuple[int, int]:
    """Rows and decoded bytes of an Arrow record batch message, read from its flatbuffer
    metadata (``Message.header: RecordBatch {length, nodes, buffers, compression}``) and, for
    a compressed body, each buffer's uncompressed length (its first 8 bytes), before decoding."""
    meta, body = message.metadata.to_pybytes(), message.body

    def table(pos: int):
        vtable = pos - struct.unpack_from("<i", meta, pos)[0]
        size = struct.unpack_from("<H", meta, vtable)[0]

        def field(i: int) -> int | None:
            offset = struct.unpack_from("<H", meta, vtable + 4 + 2 * i)[0] if 4 + 2 * i < size else 0
            return pos + offset if offset else None

        return field

    def target(pos: int) -> int:
        return pos + struct.unpack_from("<I", meta, pos)[0]

    header = table(struct.unpack_from("<I", meta, 0)[0])(2)
    if header is None:
        raise Problem(400, "the body is not an Arrow IPC stream: a record batch without its header")
    batch = table(target(header))
    rows = struct.unpack_from("<q", meta, batch(0))[0] if batch(0) else 0
    compressed = batch(3) is not None
    decoded = 0
    if batch(2):
        vector = target(batch(2))
        for i in range(struct.unpack_from("<I", meta, vector)[0]):
            offset, length = struct.unpack_from("<qq", meta, vector + 4 + 16 * i)
            if length and compressed:
                raw = struct.unpack_from("<q", body, offset)[0] if 0 <= offset <= body.size - 8 else None
                if raw is None:
                    raise Problem(400, "the body is not an Arrow IPC stream: a buffer lies outside its batch")
                length = length - 8 if raw == -1 else raw
            decoded += max(length, 0)
    if rows < 0:
        raise Problem(400, f"the body is not an Arrow IPC stream: a batch of {rows} rows")
    return rows, decoded


def _parquet_table(body: bytes, allowed: frozenset, limits: Limits) -> pa.Table:
    file = pq.ParquetFile(pa.BufferReader(body))
    schema = file.schema_arrow
    _check_schema(schema, allowed)
    meta = file.metadata
    rows = meta.num_rows
    fixed = sum(f.type.bit_width + 1 for f in schema if pa.types.is_primitive(f.type)) * rows // 8
    strings = [i for i, f in enumerate(schema) if not pa.types.is_primitive(f.type)]
    # a string column's size is its chunks' uncompressed size (values and offsets), as declared
    variable = sum(
        meta.row_group(g).column(i).total_uncompressed_size + 9 * meta.row_group(g).num_rows
        for g in range(meta.num_row_groups)
        for i in strings
    )
    _check_size(rows, fixed + variable, limits)
    return file.read()


def _columns(table: pa.Table | pa.RecordBatch, names) -> np.ndarray:
    """Numeric columns (:func:`_check_schema`, or a build's file columns) as float64, nulls NaN."""
    out = np.empty((table.num_rows, len(names)))
    for i, name in enumerate(names):
        column = table.column(name)
        _numeric(name, column.type)
        out[:, i] = np.asarray(column.to_numpy(zero_copy_only=False), dtype=float)
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


def _member(doc, key: str) -> dict:
    """``doc[key]`` where both are JSON objects, else an empty one."""
    value = doc.get(key) if isinstance(doc, dict) else None
    return value if isinstance(value, dict) else {}


def json_document(body: bytes, limits: Limits, what: str):
    """A JSON body as Python objects, by the rules every JSON body follows: bounded in size
    (:func:`json_body`) and nesting, UTF-8; 422 naming what is wrong. (Bodies with a model
    are read by its ``model_validate_json``, which applies the same parser.)"""
    try:
        return pydantic_core.from_json(json_body(body, limits), allow_inf_nan=False)
    except ValueError as exc:
        raise Problem(422, f"{what} is not JSON: {exc}") from None


def json_body(body: bytes, limits: Limits) -> bytes:
    """JSON parses into Python objects of about ten times its size: bounded by its length."""
    if len(body) > limits.json_bytes:
        raise Problem(
            413,
            f"a JSON body may hold {limits.json_bytes / 2**20:g} MiB; this one has {len(body) / 2**20:.1f}: "
            f"send {ARROW} or {PARQUET}",
        )
    return body or b"{}"


def read_observations(spec: RegionSpec, body: bytes, media: str, limits: Limits) -> UploadRows:
    """Decode an upload or fit body (JSON, Arrow or Parquet) into region ENU arrays."""
    if media == JSON:
        obs = ObservationsBody.model_validate_json(json_body(body, limits))
        if len(obs.points) != len(obs.velocities):
            raise Problem(422, f"{len(obs.points)} points but {len(obs.velocities)} velocities")
        _check_size(len(obs.points), 0, limits)
        frame, P, V = obs.frame, _array(obs.points), _array(obs.velocities)
        noise, weight = obs.input_noise_std, obs.sample_weight
        if isinstance(noise, list):
            noise = _array(noise, 3 if noise and isinstance(noise[0], list) else 1)
            if len(noise) != len(P):
                raise Problem(422, f"input_noise_std has {len(noise)} rows for {len(P)} points")
        for name, values in (("sample_weight", weight), ("track", obs.track), ("t", obs.t)):
            if values is not None and len(values) != len(P):
                raise Problem(422, f"{name} has {len(values)} values for {len(P)} points")
        return _observations(spec, frame, P, V, noise, weight, obs.track, obs.t)
    if media == ARROW or media in PARQUET_ALIASES:
        return table_observations(
            spec, _table(body, ARROW if media == ARROW else PARQUET, UPLOAD_COLUMNS, limits)
        )
    raise Problem(415, f"send {JSON}, {ARROW} or {PARQUET}, not {media or 'no Content-Type'}")


def table_observations(spec: RegionSpec, table: pa.Table | pa.RecordBatch) -> UploadRows:
    """The observations of a table with the upload columns (an Arrow or Parquet body, or a
    slice of a build's file)."""
    missing = [c for c in VELOCITY_COLUMNS if c not in table.column_names]
    if missing:
        raise Problem(422, f"the table lacks the velocity columns {missing}")
    frame, P = _table_positions(table)
    V = _columns(table, VELOCITY_COLUMNS)
    noise, weight, time = (
        _columns(table, [c])[:, 0] if c in table.column_names else None
        for c in ("input_noise_std", "sample_weight", "t")
    )
    track = None
    if "track" in table.column_names:
        column = table.column("track")
        _track_type(column.type)
        track = column.to_numpy(zero_copy_only=False)
    return _observations(spec, frame, P, V, noise, weight, track, time)


def _observations(spec: RegionSpec, frame: str, P, V, noise, weight, track=None, time=None) -> UploadRows:
    if len(P) == 0:
        raise Problem(422, "the body holds no observations")
    if (track is None) != (time is None):
        raise Problem(422, "track and t go together: a track's rows are weighed by their times")
    X, V = _to_region(spec, frame, P, V)
    return UploadRows(
        X,
        V,
        None if noise is None else np.asarray(noise, float),
        None if weight is None else np.asarray(weight, float),
        None if track is None else ingest.track_codes(track),
        None if time is None else np.array(time, dtype=float),  # JSON null: NaN
    )


def read_query(spec: RegionSpec, body: bytes, media: str, limits: Limits, modes: bool = False) -> PointQuery:
    """Decode a query (JSON, or Arrow with an optional ``heading_deg`` column) into region
    ENU points (n, 3), the headings asked and whether the modes are (``modes``: the
    request's query parameter, or the JSON body's field). Points outside the region are
    answered null (a fleet's batch may stray past its edge); a point not finite, or every
    point outside, is a 422."""
    if media == JSON:
        query = QueryBody.model_validate_json(json_body(body, limits))
        _check_size(len(query.points), 0, limits)
        frame, P, heading, modes = query.frame, _array(query.points), query.heading_deg, modes or query.modes
    elif media == ARROW:
        table = _table(body, ARROW, QUERY_COLUMNS, limits)
        frame, P = _table_positions(table)
        heading = _columns(table, ("heading_deg",))[:, 0] if "heading_deg" in table.column_names else None
    else:
        raise Problem(415, f"send {JSON} or {ARROW}, not {media or 'no Content-Type'}")
    X = _to_region(spec, frame, P, None)[0]
    outside = ~spec.inside(X)
    # a row not finite is an error, and so is a query with no point inside
    _inside(spec, X, "point(s)", frame, P, outside if outside.all() else ~rows_all(np.isfinite(X)))
    if heading is not None:
        heading = np.asarray(heading, float)
        if heading.ndim == 0:
            heading = np.full(len(X), float(heading))
        if heading.shape != (len(X),) or not np.isfinite(heading).all():
            raise Problem(422, f"heading_deg must be one finite number or {len(X)} (one per point)")
    return PointQuery(X, heading, modes, outside)


def _inside(spec: RegionSpec, X: np.ndarray, what: str, frame: str = "enu", given=None, refused=None) -> None:
    """422 naming the rows of ``X`` not finite or outside the region (``spec.inside`` is never
    true for a row that is not finite; ``refused``: these rows instead), in the frame they were
    sent in: for WGS84 points the region's latitude, longitude and altitude ranges and the
    first row as sent."""
    outside = ~spec.inside(X) if refused is None else refused
    if not outside.any():
        return
    rows = np.flatnonzero(outside)
    listed = f"rows {rows[:5].tolist()}{' ...' if rows.size > 5 else ''}"
    if frame == "wgs84":
        (lat0, lat1), (lon0, lon1) = webmap.geodetic_bounds(spec)
        first = np.round(np.asarray(given, float)[rows[0]], 6).tolist()
        where = (
            f"latitude {lat0:.5f} .. {lat1:.5f}, longitude {lon0:.5f} .. {lon1:.5f}, altitude "
            f"{spec.lower[2]:g} .. {spec.upper[2]:g} m near its origin; row {rows[0]} is {first} "
            "(lat, lon, alt_m)"
        )
    else:
        where = f"{spec.bounds_m.min} .. {spec.bounds_m.max} ENU metres"
    raise Problem(422, f"{rows.size} {what} not finite or outside region {spec.name!r} ({where}): {listed}")


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


#: what ends an Arrow IPC stream: a continuation marker and a length of zero
ARROW_END_BYTES = 8


def arrow_body(columns: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> memoryview:
    """An Arrow IPC stream of ``columns`` written once into a buffer of its exact size, as a
    memoryview a response sends without a copy (a growing stream copied into ``bytes`` takes
    about twice as long on large grids: ``bench/bench_kernels.py``)."""
    batch = pa.record_batch(columns, metadata=metadata)
    size = batch.schema.serialize().size + pa.ipc.get_record_batch_size(batch) + ARROW_END_BYTES
    buffer = pa.allocate_buffer(size)
    with pa.ipc.new_stream(pa.FixedSizeBufferWriter(buffer), batch.schema) as writer:
        writer.write_batch(batch)
    return memoryview(buffer)


def arrow_bytes(columns: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> bytes:
    """:func:`arrow_body` as ``bytes`` (request bodies: HTTP clients take bytes)."""
    return arrow_body(columns, metadata).tobytes()


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """``np.savez`` into a buffer sized once: grown write by write, a large grid spends
    much of its encoding in reallocations."""
    buf = io.BytesIO()
    buf.seek(sum(np.asarray(a).nbytes for a in arrays.values()) + 4096 * (len(arrays) + 1))
    buf.write(b"\0")  # members and headers usually fit before this byte (if not, it grows)
    buf.seek(0)
    np.savez(buf, **arrays)
    buf.truncate(buf.tell())
    return buf.getvalue()


#: rows of an array encoded at once in a JSON answer: each chunk holds the GIL for a few ms
#: (list conversion and encoding are C loops that never let other threads in), so the
#: event loop and the other requests run between chunks of a large answer
JSON_CHUNK_ROWS = 500


def json_chunks(content, size: int = 1 << 16):
    """``content`` (dicts, lists, numbers, strings, numpy arrays) as compact JSON, in pieces
    of about ``size`` bytes, each array encoded :data:`JSON_CHUNK_ROWS` rows at a time (a
    streamed answer: its text never lies in memory whole)."""
    buffered, length = [], 0
    for part in _json_parts(content):
        buffered.append(part)
        length += len(part)
        if length >= size:
            yield b"".join(buffered)
            buffered, length = [], 0
    yield b"".join(buffered)


def _json_parts(content):
    dumps = functools.partial(json.dumps, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    if isinstance(content, dict):
        yield b"{"
        for i, (key, value) in enumerate(content.items()):
            yield (("," if i else "") + dumps(key) + ":").encode()
            yield from _json_parts(value)
        yield b"}"
    elif isinstance(content, np.ndarray) and content.ndim:
        yield b"["
        for lo in range(0, len(content), JSON_CHUNK_ROWS):
            yield (b"," if lo else b"") + _json_array(content[lo : lo + JSON_CHUNK_ROWS])[1:-1]
        yield b"]"
    else:
        yield dumps(content.tolist() if isinstance(content, np.generic | np.ndarray) else content).encode()


def _json_array(values: np.ndarray) -> bytes:
    """A numeric array as a JSON array: orjson writes numpy's numbers without making Python
    objects of them (an order of magnitude faster than ``json.dumps(values.tolist())``, the
    same shortest round-trip floats); not finite is an error, as ``allow_nan=False``."""
    values = np.ascontiguousarray(values)
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        raise ValueError("Out of range float values are not JSON compliant")
    return orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)


#: peak memory per number an answer holds, bytes, with room over what
#: ``bench/bench_isolation.py --parts memory`` measures: the arrays, the classes'
#: intermediates of a chunk, the encoded body (JSON: a chunk of it at a time)
BYTES_PER_NUMBER = {JSON: 60, GEOJSON: 60, NPZ: 40, ARROW: 40, PNG: 40}


def answer_bytes(rows: int, classes: int, modes: bool, media: str) -> float:
    """What answering ``rows`` points or voxels takes in memory, estimated before any work:
    mean, std and known per row, with ``modes`` each class's share, mean, std and prior
    flag, and the shares' std."""
    numbers = 7 + (8 * classes + 1 if modes else 0)
    return float(rows) * numbers * BYTES_PER_NUMBER[media]


def vector_columns(prefix: str, values: np.ndarray, names=("e", "n", "u")) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": np.ascontiguousarray(values[:, i]) for i, n in enumerate(names)}


# -- encoders: a map's answer in the media type negotiated -------------------------------------


def mesh(axes) -> np.ndarray:
    """The grid ``axes[0] x axes[1] x axes[2]`` as points (C order)."""
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grids], axis=1)


def check_json_size(voxels: int, max_json_voxels: int) -> None:
    """422 for a grid answer too large for JSON."""
    if voxels > max_json_voxels:
        raise Problem(
            422,
            f"{voxels} voxels is too many for JSON (limit {max_json_voxels}): "
            f"ask for Accept: {NPZ} or {ARROW}",
        )


def encode_points(out: str, spec: RegionSpec, pred, headers: dict, outside: np.ndarray) -> Response:
    """A point query's answer: Arrow columns, or JSON streamed in chunks. ``pred`` holds the
    points inside the region; the rows of the points ``outside`` it (n,) are null (Arrow
    nulls, JSON null; ``known`` false), counted in ``X-Points-Outside`` and JSON's ``outside``."""
    m = pred.modes
    headers = {**headers, "X-Points-Outside": str(int(outside.sum()))}
    if out == ARROW:
        columns = {
            **vector_columns("v", pred.mean),
            **vector_columns("std_", pred.std),
            "known": pred.known,
        }
        if m is not None:
            for c in range(m.share.shape[1]):
                columns[f"share{c}"] = np.ascontiguousarray(m.share[:, c])
                columns |= vector_columns(f"mode{c}_v", m.mean[:, c])
                columns |= vector_columns(f"mode{c}_std_", m.std[:, c])
                columns[f"prior_only{c}"] = np.ascontiguousarray(m.prior_only[:, c])
            columns["share_std"] = m.share_std
        columns = {
            name: _rows_outside(values, outside, False if name == "known" else None, arrow=True)
            for name, values in columns.items()
        }
        return Response(arrow_body(columns), media_type=ARROW, headers=headers)
    content = {
        "mean": _rows_outside(pred.mean, outside),
        "std": _rows_outside(pred.std, outside),
        "known": _rows_outside(pred.known, outside, fill=False),
        "outside": int(outside.sum()),
        "region_version": pred.version,
    }
    if m is not None:
        content["modes"] = {
            "heading_deg": class_headings(spec),
            **{
                name: _rows_outside(values, outside)
                for name, values in (
                    ("share", m.share),
                    ("share_std", m.share_std),
                    ("mean", m.mean),
                    ("std", m.std),
                    ("prior_only", m.prior_only),
                )
            },
        }
    return StreamingResponse(json_chunks(content), media_type=JSON, headers=headers)


def _rows_outside(values: np.ndarray, outside: np.ndarray, fill=None, arrow: bool = False):
    """The answer's rows (of the points inside) with a row for every point: ``fill`` outside,
    or null (an Arrow array with nulls, or for JSON a list with None rows)."""
    if not outside.any():
        return values
    if fill is not None:
        full = np.full((len(outside), *values.shape[1:]), fill, values.dtype)
        full[~outside] = values
        return full
    if arrow:
        full = np.zeros(len(outside), values.dtype)
        full[~outside] = values
        return pa.array(full, mask=outside)
    rows = iter(values.tolist())
    return [None if out else next(rows) for out in outside.tolist()]


def encode_grid(out: str, spec: RegionSpec, axes, pred, headers: dict, max_json_voxels: int) -> Response:
    """A grid's answer: npz (with the modes), Arrow (one row per voxel, ``shape`` in the
    schema's metadata) or JSON."""
    if out == NPZ:
        extra = {}
        if pred.modes is not None:
            m = pred.modes
            headings = [np.nan if h is None else h for h in class_headings(spec)]
            extra = dict(
                share=m.share,
                share_std=m.share_std,
                mode_mean=m.mean,
                mode_std=m.std,
                mode_heading_noise=m.heading_noise,
                mode_prior_only=m.prior_only,
                heading_deg=np.array(headings),
            )
        body = npz_bytes(
            mean=pred.mean, std=pred.std, known=pred.known, x=axes[0], y=axes[1], z=axes[2], **extra
        )
        return Response(body, media_type=NPZ, headers=headers)
    if out == ARROW:
        columns = {
            **vector_columns("", mesh(axes), ENU_COLUMNS),
            **vector_columns("v", pred.mean.reshape(-1, 3)),
            **vector_columns("std_", pred.std.reshape(-1, 3)),
            "known": pred.known.ravel(),
        }
        shape = ",".join(map(str, pred.known.shape))
        return Response(arrow_body(columns, {"shape": shape}), media_type=ARROW, headers=headers)
    check_json_size(pred.known.size, max_json_voxels)
    content = {
        "x": axes[0].tolist(),
        "y": axes[1].tolist(),
        "z": axes[2].tolist(),
        "mean": pred.mean.tolist(),
        "std": pred.std.tolist(),
        "known": pred.known.tolist(),
        "region_version": pred.version,
    }
    return JSONResponse(content, headers=headers)


@dataclass(frozen=True)
class TubeBound:
    """What bounds a tube: the std (all components or one), and with ``heading_deg`` the
    mode of that heading, whose share must be at least ``min_share``."""

    max_std_mps: float
    component: str
    heading_deg: float | None
    min_share: float


def encode_tube(
    out: str, spec: RegionSpec, axes, pred, tube: TubeBound, headers: dict, max_json_voxels: int
) -> Response:
    """The voxels of a grid inside the tube, with their mean and std: npz (with the mask),
    Arrow or GeoJSON points."""
    mean_grid, std_grid, wide = pred.mean, pred.std, pred.known
    if tube.heading_deg is not None:  # the mode of the heading (the one mode of a map of one class)
        mean_grid, std_grid = pred.modes.answer(spec.sectors, tube.heading_deg)
        wide = wide & (pred.modes.heading_share(spec.sectors, tube.heading_deg) >= tube.min_share)
    component = tube.component
    bounded = std_grid if component == "all" else std_grid[..., ["e", "n", "u"].index(component), None]
    inside = wide & (bounded < tube.max_std_mps).all(axis=-1)
    idx = np.flatnonzero(inside)
    X, mean, std = mesh(axes)[idx], mean_grid.reshape(-1, 3)[idx], std_grid.reshape(-1, 3)[idx]
    if out == NPZ:
        body = npz_bytes(points=X, mean=mean, std=std, mask=inside, x=axes[0], y=axes[1], z=axes[2])
        return Response(body, media_type=NPZ, headers=headers)
    if out == ARROW:
        columns = {
            **vector_columns("", X, ENU_COLUMNS),
            **vector_columns("v", mean),
            **vector_columns("std_", std),
        }
        return Response(arrow_body(columns), media_type=ARROW, headers=headers)
    check_json_size(len(idx), max_json_voxels)
    geo = spec.frame().to_geodetic(X)
    features = [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [lon, lat, alt]},
            "properties": {"enu": x, "mean": m, "std": s},
        }
        for (lat, lon, alt), x, m, s in zip(
            geo.tolist(), X.tolist(), mean.tolist(), std.tolist(), strict=True
        )
    ]
    properties = {"max_std_mps": tube.max_std_mps, "component": component, "region_version": pred.version}
    if not features:  # say why, and what bound would hold some
        worst = bounded.max(axis=-1)[wide]
        properties["note"] = (
            f"no voxel is inside the tube: the least std among the grid's known voxels is "
            f"{worst.min():.3g} m/s; raise max_std_mps above it"
            if worst.size
            else "no voxel of the grid is known (data within the kernel's reach) for this tube"
        )
    content = {"type": "FeatureCollection", "features": features, "properties": properties}
    return JSONResponse(content, media_type=GEOJSON, headers=headers)


def encode_slice(name: str, axes, pred, view: slices.SliceView, headers: dict, origin=None) -> Response:
    """One horizontal slice as a PNG with its colour scale (:func:`service.slices.render_slice`)."""
    x, y, z = axes
    per_class = {}
    if pred.modes is not None:
        per_class = dict(
            share=pred.modes.share[:, :, 0],
            share_std=pred.modes.share_std[:, :, 0],
            mode_mean=pred.modes.mean[:, :, 0],
            mode_known=~pred.modes.prior_only[:, :, 0],
            min_share=view.min_share,
        )
    png = slices.render_slice(
        x,
        y,
        pred.mean[:, :, 0],
        pred.std[:, :, 0],
        pred.known[:, :, 0],
        alt_m=float(z[0]),
        layer=view.layer,
        component=view.component,
        max_std_mps=view.max_std_mps,
        title=f"{name} v{pred.version}",
        origin=origin,
        **per_class,
    )
    return Response(png, media_type=PNG, headers=headers)
