"""Observation and query files for the command line: CSV, Parquet or JSON(.gz).

Three layouts are recognised by their columns:

* ENU: ``x, y, z`` (region metres) and ``ve, vn, vu`` (m/s) [``input_noise_std``]
  [``track``, ``t``: each row's track id and time in seconds];
* WGS84: ``lat, lon, alt_m`` and ``ve, vn, vu`` in each point's local axes [the same];
* ADS-B state vectors (OpenSky / ``traffic``): ``icao24, latitude, longitude, altitude``
  (ft), ``groundspeed`` (kt), ``track`` (deg), ``vertical_rate`` (ft/min), ``timestamp``;
  on-ground and incomplete rows are dropped and counted; a track per icao24 and callsign.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bdf import ingest
from bdf.region.spec import RegionSpec


@dataclass
class FileObservations:
    X: np.ndarray
    V: np.ndarray
    input_noise_std: np.ndarray | None
    frame: str  # "enu" or "wgs84"
    dropped: dict[str, int]
    track: np.ndarray | None = None  # (n,) id of each row's track, with ``time``
    time: np.ndarray | None = None  # (n,) seconds


def _columns(table: dict, names, path) -> np.ndarray:
    return np.stack([ingest.float_column(table, n, path) for n in names], axis=1)


def read_observations(path, spec: RegionSpec) -> FileObservations:
    table = ingest.read_table(path)
    noise = ingest.float_column(table, "input_noise_std", path) if "input_noise_std" in table else None
    if ingest.adsb_schema(table):
        obs = ingest.adsb_observations(table, spec.frame(), source=str(path))
        return FileObservations(obs.X, obs.V, None, "enu", obs.dropped, obs.flight, obs.time)
    frame, P = read_points_table(table, path)
    V = _columns(table, ("ve", "vn", "vu"), path)
    if ("track" in table) != ("t" in table):
        raise ValueError(f"{path}: the columns track and t go together (a track's rows weigh by their times)")
    if "track" not in table:
        return FileObservations(P, V, noise, frame, {})
    track = ingest.track_codes(table["track"])
    return FileObservations(P, V, noise, frame, {}, track, ingest.float_column(table, "t", path))


def read_points_table(table: dict, path) -> tuple[str, np.ndarray]:
    if {"x", "y", "z"} <= set(table):
        return "enu", _columns(table, ("x", "y", "z"), path)
    if {"lat", "lon", "alt_m"} <= set(table):
        return "wgs84", _columns(table, ("lat", "lon", "alt_m"), path)
    raise ValueError(
        f"{path}: need the columns x, y, z (ENU), lat, lon, alt_m (WGS84) or ADS-B state vectors; "
        f"found {sorted(table)}"
    )


def read_points(path) -> tuple[str, np.ndarray]:
    return read_points_table(ingest.read_table(path), path)
