"""Real data in: ADS-B state vectors (OpenSky / ``traffic`` schema), radar point clouds, samples.

ADS-B units are aviation units: altitude in ft, groundspeed in kt, track in degrees
clockwise from north, vertical_rate in ft/min. They come out as ENU metres and m/s.
"""

from __future__ import annotations

import gzip
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bdf.frames import ENUFrame

log = logging.getLogger(__name__)

FT = 0.3048
KT = 1852.0 / 3600.0
FT_PER_MIN = FT / 60.0

RADAR_COLUMNS = ("x", "y", "z", "vx", "vy", "vz")
#: A track's rows count as if it flew at least this fast (m/s, the slow class's bound): a
#: hovering vehicle's samples are as correlated in time as a cruising one's in space.
MIN_TRACK_SPEED_MPS = 5.0
#: The longest time a row stands for: the sampling interval of ADS-B state vectors and of
#: most radars (a region's ``track_interval_s``).
MAX_ROW_INTERVAL_S = 1.0


@dataclass
class Observations:
    """Positions ``X`` (N, 3, ENU m), velocities ``V`` (N, 3, m/s) and per-row metadata."""

    X: np.ndarray
    V: np.ndarray
    time: np.ndarray  # seconds (ADS-B: Unix time)
    flight: np.ndarray  # integer flight id per row (ADS-B: per icao24 + callsign)
    dropped: dict[str, int] = field(default_factory=dict)  # reason -> rows dropped

    def __len__(self) -> int:
        return len(self.X)

    def track_weights(self, gamma, max_interval_s: float = MAX_ROW_INTERVAL_S) -> np.ndarray:
        """:func:`track_weights` of these rows, a track per flight, for a kernel ``gamma``."""
        return track_weights(self.flight, self.time, self.V, gamma, max_interval_s=max_interval_s)

    def subset(self, mask) -> Observations:
        return Observations(
            self.X[mask], self.V[mask], self.time[mask], self.flight[mask], dict(self.dropped)
        )


#: file names read as JSON records
JSON_SUFFIXES = (".json", ".json.gz", ".jsonl", ".jsonl.gz")


def json_records(path) -> list[dict]:
    """The records of a JSON(.gz) file: a JSON list of objects, or JSON lines (the whole
    file in memory: for large data, Parquet)."""
    opener = gzip.open if str(path).lower().endswith(".gz") else open
    with opener(path, "rt") as fh:
        text = fh.read()
    if text.lstrip().startswith("["):
        return json.loads(text)
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def read_table(path) -> dict[str, np.ndarray]:
    """Columns of a CSV, Parquet or JSON(.gz) file (a JSON list of records, or JSON lines)."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith(JSON_SUFFIXES):
        records = json_records(path)
        keys = {k for r in records[:1000] for k in r}
        return {k: np.array([r.get(k) for r in records], dtype=object) for k in keys}
    if name.endswith((".parquet", ".pq")):
        import pyarrow.parquet as pq

        table = pq.read_table(path)
    elif name.endswith((".csv", ".csv.gz")):
        import pyarrow.csv as pacsv

        table = pacsv.read_csv(path)
    else:
        raise ValueError(f"{path}: unknown format; use .csv, .parquet or .json(.gz)")
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in table.column_names}


def float_column(table, name, path) -> np.ndarray:
    """Column ``name`` of ``table`` as floats (missing values NaN); ``ValueError`` names the
    column and the first row that is not a number."""
    if name not in table:
        raise ValueError(f"{path}: missing column {name!r} (have {sorted(table)})")
    col = table[name]
    try:
        return (
            np.array([np.nan if v is None else v for v in col], dtype=float)
            if col.dtype == object
            else np.asarray(col, dtype=float)
        )
    except (TypeError, ValueError):
        row = next(i for i, v in enumerate(col) if not _is_number(v))
        raise ValueError(
            f"{path}: column {name!r}, data row {row + 1}: {str(col[row])!r} is not a number"
        ) from None


def _is_number(value) -> bool:
    if value is None:
        return True
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


#: ADS-B state-vector schemas, by the columns that name them: latitude, longitude, altitude,
#: horizontal speed, track and vertical rate, with the factor of each to degrees, metres
#: and m/s. ``traffic``: OpenSky's Impala and the traffic library (ft, kt, ft/min);
#: ``opensky``: OpenSky's state-vector files (m, m/s; geometric height, else barometric).
ADSB_SCHEMAS = {
    "traffic": (
        ("latitude", "longitude", "altitude", "groundspeed", "track", "vertical_rate"),
        FT,
        KT,
        FT_PER_MIN,
    ),
    "opensky": (("lat", "lon", "geoaltitude", "velocity", "heading", "vertrate"), 1.0, 1.0, 1.0),
}


def adsb_schema(names) -> str | None:
    """The ADS-B schema of a table with these column names, or None."""
    names = set(names)
    for schema, (columns, *_) in ADSB_SCHEMAS.items():
        if {"icao24", *columns[:2], *columns[3:]} <= names:
            return schema
    return None


def adsb_state(
    table: dict, frame: ENUFrame, *, source="table"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """ADS-B state vectors -> ENU positions and velocities of the rows kept, the mask of
    those rows, and the rows dropped per reason (on the ground, or missing a value)."""
    schema = adsb_schema(table)
    if schema is None:
        raise ValueError(
            f"{source}: ADS-B state vectors need the columns icao24 and "
            f"{' or '.join(', '.join(cols) for cols, *_ in ADSB_SCHEMAS.values())}; found {sorted(table)}"
        )
    (lat, lon, alt, speed, track, vrate), to_m, to_mps, to_vmps = ADSB_SCHEMAS[schema]
    if alt not in table:  # OpenSky files without the geometric height
        alt = "baroaltitude"
    cols = [float_column(table, c, source) for c in (lat, lon, alt, speed, track, vrate)]
    onground = np.zeros(len(cols[0]), bool)
    if "onground" in table:
        flag = np.asarray(table["onground"])
        onground = (
            flag.astype(bool)
            if flag.dtype == bool
            else np.isin(np.char.lower(flag.astype(str)), ["true", "1"])
        )
    complete = np.isfinite(np.stack(cols)).all(axis=0)
    keep = complete & ~onground
    dropped = {"on_ground": int(onground.sum()), "incomplete": int((~complete & ~onground).sum())}
    lat, lon, alt, speed, track, vrate = (c[keep] for c in cols)
    X = frame.to_enu(lat, lon, alt * to_m)
    speed, track = speed * to_mps, np.radians(track)
    v_local = np.stack([speed * np.sin(track), speed * np.cos(track), vrate * to_vmps], 1)
    return X, frame.rotate_velocity(lat, lon, v_local), keep, dropped


def adsb_observations(table: dict, frame: ENUFrame, *, source="table") -> Observations:
    """ADS-B state vectors -> ENU observations, one flight per icao24 and callsign; on-ground
    and incomplete rows are dropped."""
    X, V, keep, dropped = adsb_state(table, frame, source=source)
    log.info("%s: %d state vectors, dropped %s", source, len(keep), dropped)
    flight, time = adsb_tracks(table, source)
    flight = np.unique(flight[keep], return_inverse=True)[1].ravel()  # 0, 1, ... over the kept rows
    return Observations(X, V, time[keep], flight.astype(np.int64), dropped)


def adsb_tracks(table: dict, source="table") -> tuple[np.ndarray, np.ndarray]:
    """The track of each state vector (a code per icao24 and callsign) and its time in
    seconds (``timestamp`` or ``time``: Unix seconds, milliseconds or a date-time column)."""
    n = len(table["icao24"])
    callsign = table.get("callsign", np.full(n, ""))
    keys = np.char.add(
        np.char.add(np.asarray(table["icao24"]).astype(str), "/"), np.asarray(callsign).astype(str)
    )
    name = "timestamp" if "timestamp" in table else "time"
    column = np.asarray(table[name]) if name in table else None
    if column is not None and column.dtype.kind == "M":
        time = column.astype("datetime64[ns]").astype(np.int64) / 1e9
    else:
        time = float_column(table, name, source)
        if np.nanmax(np.abs(time), initial=0) > 1e11:  # milliseconds, as in the traffic samples
            time = time / 1000.0
    return track_codes(keys), time


def read_adsb(path, frame: ENUFrame) -> Observations:
    return adsb_observations(read_table(path), frame, source=str(path))


def read_radar(path) -> Observations:
    """Radar point cloud CSV with columns x, y, z, vx, vy, vz [, t] [, track] (metres, m/s,
    seconds; the radar's track id: without one, each row is its own track, -1)."""
    table = read_table(path)
    cols = [float_column(table, c, path) for c in RADAR_COLUMNS]
    t = float_column(table, "t", path) if "t" in table else np.zeros(len(cols[0]))
    data = np.stack([*cols, t], 1)
    ok = np.all(np.isfinite(data), axis=1)
    track = track_codes(table["track"]) if "track" in table else np.full(len(ok), -1, np.int64)
    return Observations(
        data[ok, :3],
        data[ok, 3:6],
        data[ok, 6],
        track[ok],
        {"incomplete": int((~ok).sum())},
    )


def train_test_split(obs: Observations, *, by: str = "point", test_fraction: float = 0.2, seed: int = 0):
    """Boolean test mask: a random fraction of points, or of whole flights (``by="flight"``).

    A point split mostly measures interpolation along a track between neighbouring samples;
    a flight split measures prediction where that aircraft was never seen.
    """
    rng = np.random.default_rng(seed)
    if by == "point":
        return rng.permutation(len(obs)) < round(test_fraction * len(obs))
    if by == "flight":
        flights = np.unique(obs.flight)
        held = rng.permutation(flights)[: round(test_fraction * len(flights))]
        return np.isin(obs.flight, held)
    raise ValueError(f"by must be 'point' or 'flight', got {by!r}")


def track_weights(
    track,
    time,
    V,
    gamma,
    *,
    min_speed_mps: float = MIN_TRACK_SPEED_MPS,
    max_interval_s: float = MAX_ROW_INTERVAL_S,
) -> np.ndarray:
    """Weights of the rows of tracks: about one observation per kernel width flown.

    Rows of one track a second apart are not independent observations of the flow: counted
    as such, the evidence trusts the data by orders of magnitude too much (the prior is
    driven to nothing and the field oscillates between tracks). A row stands for the time
    to its nearer neighbour in its own track, at most ``max_interval_s`` (rows of a track
    at one ``time`` share it; a row alone in its track stands for ``max_interval_s``),
    flown at its own velocity ``V`` (at least ``min_speed_mps``), measured in kernel widths
    (``1 / sqrt(gamma)`` per axis), and counts that many observations, at most one. A row
    without a track (``track`` -1, :func:`track_codes`) is one observation, its time unused.

    The weight depends only on a row and its neighbours in its track among the rows given,
    so the rows of one upload are weighed alone and retracting an upload removes exactly
    what it added. Rows sampled ``max_interval_s`` apart or further weigh by themselves
    alone: any split of such tracks into uploads gives the same weights. Faster sampling
    is weighed by the neighbours, the same whatever the split where it is regular (cut
    between rows no further apart than the rows beside them). Tracks sampled more sparsely
    count for less than they carry (each row ``max_interval_s`` of flight): under-, never
    over-confident. Two flights along one line weigh twice one flight; one flight sampled
    16 times as often weighs the same. A track's two end rows stand for a whole interval (a
    cut end cannot be told from a true one): half a sample more than a trapezoid rule.

    Parameters
    ----------
    track : (n,) integer track id of each row (-1: none).
    time : (n,) seconds, finite where a row has a track.
    V : (n, 3) velocities, m/s.
    gamma : (3,) the kernel's inverse squared widths per axis (1/m^2).
    """
    track = np.asarray(track)
    time = np.asarray(time, dtype=float)
    V = np.asarray(V, dtype=float)
    gamma = np.broadcast_to(np.asarray(gamma, dtype=float), (3,))
    n = len(track)
    if time.shape != (n,) or V.shape != (n, 3):
        raise ValueError(
            f"track, time and V must have n, n and (n, 3) rows; got {track.shape}, {time.shape}, {V.shape}"
        )
    out = np.ones(n)
    on = track >= 0
    if not np.isfinite(time[on]).all():
        raise ValueError("every row of a track needs a finite time")
    if not on.any():
        return out
    out[on] = _tracked_weights(track[on], time[on], V[on], gamma, min_speed_mps, max_interval_s)
    return out


def _tracked_weights(track, time, V, gamma, min_speed_mps, max_interval_s) -> np.ndarray:
    """:func:`track_weights` of rows that all have a track."""
    n = len(track)
    order = np.lexsort((time, track))
    k, t = track[order], time[order]
    first = np.r_[True, (k[1:] != k[:-1]) | (t[1:] != t[:-1])]  # each (track, time) once
    group = np.cumsum(first) - 1
    gk, gt = k[first], t[first]
    same = gk[1:] == gk[:-1]
    gap = np.where(same, np.diff(gt), np.inf)
    interval = np.minimum(np.minimum(np.r_[np.inf, gap], np.r_[gap, np.inf]), max_interval_s)
    sharing = np.bincount(group)
    rate = np.maximum(
        np.linalg.norm(V[order] * np.sqrt(gamma), axis=1), min_speed_mps * np.sqrt(gamma[:2].max())
    )
    w = np.minimum(interval[group] * rate, 1.0) / sharing[group]
    out = np.empty(n)
    out[order] = w
    return out


def track_codes(ids) -> np.ndarray:
    """Integer codes of track ids (strings or integers; ``None``, ``""`` or NaN, as a file's
    numeric column with gaps reads: no track, -1)."""
    ids = np.asarray(ids)
    if ids.dtype.kind in "iu":
        return np.unique(ids, return_inverse=True)[1].ravel().astype(np.int64)
    ids = ids.astype(object)
    missing = np.array([v is None or v == "" or (isinstance(v, float) and v != v) for v in ids], bool)
    codes = np.full(len(ids), -1, np.int64)
    if (~missing).any():
        codes[~missing] = np.unique(ids[~missing].astype(str), return_inverse=True)[1].ravel()
    return codes
