"""A synthetic city with ground truth: drone and aircraft traffic on known air roads.

Every road is a straight line with one lane in each direction (lanes a few hundred metres
apart), and a lane's traffic is a Gaussian tube around its axis moving at the lane's
velocity plus noise. The known field at ``x`` follows from the lanes' densities there:
the mean velocity of all traffic (what a map of one class should learn), each lane's
velocity (what the mode of its heading should learn) and each lane's share.

    python bench/make_city.py --points 20000000 --out /tmp/city   # 20 files of 1M rows
    python bench/make_city.py --points 20000000 --out /tmp/city --rows-per-file 0   # one file

writes Parquet files of the upload columns (``x, y, z, ve, vn, vu``, region metres) with
row groups of 100,000 rows, and ``region.json``, the spec of the region to build them into.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

#: The city's box (m): 40 km square, 3 km up.
SIZE = np.array([40_000.0, 40_000.0, 3_000.0])
ROWS_PER_FILE = 1_000_000
ROW_GROUP = 100_000


@dataclass(frozen=True)
class Lane:
    start: tuple[float, float, float]  # m
    end: tuple[float, float, float]
    speed: float  # m/s along the lane
    weight: float  # share of all traffic
    width: float  # lateral std (m)
    height: float  # vertical std (m)
    noise: float  # velocity noise std (m/s), per component


def _road(a, b, speed, weight, width, height, noise, gap) -> list[Lane]:
    """Both lanes of a road from ``a`` to ``b``, ``gap`` metres apart (keep right)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = (b - a)[:2] / np.linalg.norm((b - a)[:2])
    right = np.array([d[1], -d[0], 0.0]) * gap / 2
    there = Lane(tuple(a + right), tuple(b + right), speed, weight / 2, width, height, noise)
    back = Lane(tuple(b - right), tuple(a - right), speed, weight / 2, width, height, noise)
    return [there, back]


#: Drone roads low (crossing at right angles and diagonally), an aircraft corridor
#: climbing through the box, and a cruise route above.
LANES = [
    *_road((2e3, 12e3, 120), (38e3, 12e3, 120), 18.0, 0.25, 80.0, 15.0, 1.5, 400.0),
    *_road((20e3, 2e3, 180), (20e3, 38e3, 180), 15.0, 0.20, 80.0, 15.0, 1.5, 400.0),
    *_road((4e3, 4e3, 300), (36e3, 36e3, 300), 22.0, 0.20, 100.0, 20.0, 2.0, 600.0),
    *_road((2e3, 30e3, 600), (38e3, 22e3, 2400), 110.0, 0.20, 300.0, 60.0, 5.0, 2000.0),
    *_road((30e3, 2e3, 2800), (10e3, 38e3, 2800), 180.0, 0.15, 400.0, 50.0, 6.0, 3000.0),
]


def _unit(lane: Lane) -> tuple[np.ndarray, np.ndarray, float]:
    a, b = np.array(lane.start), np.array(lane.end)
    return a, (b - a) / np.linalg.norm(b - a), float(np.linalg.norm(b - a))


def lane_velocity(lane: Lane) -> np.ndarray:
    return _unit(lane)[1] * lane.speed


def sample(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` observations: positions, velocities and the lane of each."""
    weights = np.array([lane.weight for lane in LANES])
    lane = rng.choice(len(LANES), n, p=weights / weights.sum())
    X, V = np.empty((n, 3)), np.empty((n, 3))
    for i, spec in enumerate(LANES):
        rows = np.flatnonzero(lane == i)
        a, d, length = _unit(spec)
        side = np.array([d[1], -d[0], 0.0]) / np.hypot(d[0], d[1])
        t = rng.uniform(0, length, len(rows))
        X[rows] = (
            a
            + t[:, None] * d
            + rng.normal(0, spec.width, (len(rows), 1)) * side
            + rng.normal(0, spec.height, (len(rows), 1)) * [0, 0, 1]
        )
        V[rows] = lane_velocity(spec) + rng.normal(0, spec.noise, (len(rows), 3))
    inside = np.all((X >= 0) & (X <= SIZE), axis=1)
    return X[inside], V[inside], lane[inside]


def densities(X: np.ndarray) -> np.ndarray:
    """Each lane's traffic density at ``X`` (n, lanes), per unit of the lane's weight."""
    out = np.empty((len(X), len(LANES)))
    for i, spec in enumerate(LANES):
        a, d, length = _unit(spec)
        r = X - a
        t = r @ d
        off = r - t[:, None] * d
        side = np.array([d[1], -d[0], 0.0]) / np.hypot(d[0], d[1])
        lateral, vertical = off @ side, off[:, 2]
        on = (t >= 0) & (t <= length)
        g = np.exp(-0.5 * (lateral / spec.width) ** 2 - 0.5 * (vertical / spec.height) ** 2)
        out[:, i] = spec.weight * on * g / (length * 2 * np.pi * spec.width * spec.height)
    return out


def true_mean(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean velocity of all traffic at ``X`` (n, 3) and the total density (n,)."""
    rho = densities(X)
    total = rho.sum(axis=1)
    velocities = np.array([lane_velocity(lane) for lane in LANES])
    return rho @ velocities / np.maximum(total, 1e-300)[:, None], total


def region_spec(name: str = "city", directions: int = 1) -> dict:
    """The city's region: 2 km x 2 km x 500 m lattice, 10 km tiles."""
    return {
        "name": name,
        "origin": {"lat": 48.85, "lon": 2.35, "alt_m": 0.0},
        "bounds_m": {"min": [0.0, 0.0, 0.0], "max": SIZE.tolist()},
        "tile_size_m": [10_000.0, 10_000.0, float(SIZE[2])],
        "spacing_m": [2000.0, 2000.0, 500.0],
        "gamma": [1 / 2000.0**2, 1 / 2000.0**2, 1 / 500.0**2],
        "directions": directions,
    }


def write(
    out: Path, points: int, seed: int = 0, progress: bool = True, rows_per_file: int | None = ROWS_PER_FILE
) -> list[Path]:
    """``points`` observations in files of ``rows_per_file`` rows (None: one file), written
    a million rows at a time."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths, left = [], points
    with tqdm(total=points, unit="pt", unit_scale=True, desc="city", disable=not progress) as bar:
        writer, in_file = None, 0
        while left > 0:
            rows = min(left, ROWS_PER_FILE, (rows_per_file or points) - in_file)
            X, V, _ = sample(int(rows * 1.02) + 100, rng)  # a few fall outside
            X, V = X[:rows], V[:rows]
            columns = {n: X[:, i] for i, n in enumerate("xyz")} | {
                n: V[:, i] for i, n in enumerate(("ve", "vn", "vu"))
            }
            table = pa.table(columns)
            if writer is None:
                paths.append(out / f"part-{len(paths):05d}.parquet")
                writer = pq.ParquetWriter(paths[-1], table.schema, compression="zstd")
            writer.write_table(table, row_group_size=ROW_GROUP)
            in_file += rows
            if in_file == (rows_per_file or points):
                writer.close()
                writer, in_file = None, 0
            left -= rows
            bar.update(rows)
        if writer is not None:
            writer.close()
    (out / "region.json").write_text(json.dumps(region_spec(), indent=1))
    return paths


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rows-per-file", type=int, default=ROWS_PER_FILE, help="0: one file")
    args = parser.parse_args(argv)
    paths = write(args.out, args.points, args.seed, rows_per_file=args.rows_per_file or None)
    print(f"{args.points:,} points in {len(paths)} files under {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
