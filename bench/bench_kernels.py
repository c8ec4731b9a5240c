"""In-process figures behind the build and service readings of bench/RESULTS.md (2026-11-25).

    python bench/bench_kernels.py [--parts evidence,digests,arrow,floor,lanes,windows]

* evidence: ``bdf.region.evidence.increments`` of 200,000 synthetic-city points (``make_city``), in
  microseconds a point, best of 5, with 1 and 8 heading sectors;
* digests: SHA-256 of a city Parquet file by ``hashlib.file_digest`` and by fresh 16 MB
  reads (the code before 2026-11-25), in nanoseconds a point;
* Arrow bodies: a 100 x 100 x 30 grid's columns, made as the grid route makes them, encoded
  by ``formats.arrow_body`` (one buffer of the stream's exact size) and by a growing stream copied
  into ``bytes`` (before), median of 10;
* the evidence search's floor: one heading class of the 8-sector city (1 million points),
  its log evidence at ``lam`` = 1e-10 and 1e-3 x mean(diag G), from the factorisation and
  from a dense eigendecomposition, and ``G``'s smallest eigenvalue over mean(diag G);
* lanes: the point-by-point gather (``features.gather_pointwise``) of 1,000 random points
  from tables of the demo's 8-sector shapes (its hinge lattice, 41 x 41 x 8 at gamma =
  1 / spacing^2, 36 channels; its midpoint lattice, 10 channels), at the demo's cutoff and
  the default one, in chunks of 32 values against 16 (the median ratio of 30 pairs), and
  the width ``features.lanes_for`` gives;
* windows: the share of such a gather (demo's cutoff; one class's tables, 3 and 2 channels,
  and 8 sectors') that is its points' windows and factors (``features._point_windows``,
  one vectorised exponential), median of 30.

Medians or best of several runs; prints a table (not appended: the readings quote it).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))
import make_city

from bdf import features, hyperparameters, sparse
from bdf.grid import Lattice
from bdf.posterior import _local_prior
from bdf.region.evidence import increments, region_total
from bdf.region.spec import RegionSpec
from clients.samples import PARIS_REGION_CUTOFF
from service import formats


def timings(fn, repeat: int) -> np.ndarray:
    """Seconds of ``repeat`` calls of ``fn``."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return np.array(times)


def best(fn, repeat=5) -> float:
    return float(timings(fn, repeat).min())


def median(fn, repeat=10) -> float:
    return float(np.median(timings(fn, repeat)))


def evidence_rows() -> list[tuple[str, str]]:
    X, V, _ = make_city.sample(200_000, np.random.default_rng(0))
    rows = []
    for S in (1, 8):
        spec = RegionSpec.model_validate(make_city.region_spec(directions=S))
        increments(spec, X[:1000], V[:1000])  # compile
        s = best(lambda spec=spec: increments(spec, X, V))
        rows.append((f"evidence, {S} sector(s) [us a point]", f"{s / len(X) * 1e6:.3f}"))
    return rows


def digest_rows() -> list[tuple[str, str]]:
    with tempfile.TemporaryDirectory() as folder:
        (path,) = make_city.write(Path(folder), 1_000_000, progress=False, rows_per_file=None)

        def blocks():
            h = hashlib.sha256()
            with open(path, "rb") as fh:
                while block := fh.read(1 << 24):
                    h.update(block)
            return h.hexdigest()

        def file_digest():
            with open(path, "rb") as fh:
                return hashlib.file_digest(fh, "sha256").hexdigest()

        assert blocks() == file_digest()
        return [
            ("digest, hashlib.file_digest [ns a point]", f"{best(file_digest) * 1e3:.1f}"),
            ("digest, fresh 16 MB reads [ns a point]", f"{best(blocks) * 1e3:.1f}"),
        ]


def arrow_rows() -> list[tuple[str, str]]:
    """As the grid route does: columns made from the prediction's arrays on each request."""
    rng = np.random.default_rng(0)
    axes = [np.linspace(0.0, 1.0, n) for n in (100, 100, 30)]
    mean, std, known = (
        rng.random((100, 100, 30, 3)),
        rng.random((100, 100, 30, 3)),
        rng.random((100, 100, 30)) > 0.5,
    )
    metadata = {"shape": "100,100,30"}

    def columns():
        mesh = np.stack([m.ravel() for m in np.meshgrid(*axes, indexing="ij")], axis=1)
        return {
            **formats.vector_columns("", mesh, ("x", "y", "z")),
            **formats.vector_columns("v", mean.reshape(-1, 3)),
            **formats.vector_columns("std_", std.reshape(-1, 3)),
            "known": known.ravel(),
        }

    def growing():
        table = pa.table(columns(), metadata=metadata)
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as writer:
            writer.write_table(table)
        return sink.getvalue().to_pybytes()

    def sized():
        return formats.arrow_body(columns(), metadata)

    assert bytes(sized()) == growing()
    return [
        ("Arrow grid body, arrow_body [ms, median]", f"{median(sized) * 1e3:.1f}"),
        ("Arrow grid body, growing stream into bytes [ms, median]", f"{median(growing) * 1e3:.1f}"),
    ]


def floor_rows(klass: int = 2) -> list[tuple[str, str]]:
    spec = RegionSpec.model_validate(make_city.region_spec(directions=8))
    X, V, _ = make_city.sample(1_000_000, np.random.default_rng(0))
    tile_increments = increments(spec, X, V)
    evidence = region_total(spec, {k: i.evidence for k, i in tile_increments.items()}).classes[klass]
    grid, gamma, stencil = spec.grid, np.array(spec.gamma), sparse.stencil_on(spec.grid, spec.kernel)
    band = evidence.gram_band(stencil)
    # the statistics the search sees, with the mode's prior mean (bdf.posterior.Posterior)
    w0 = _local_prior(evidence, grid, gamma)
    Gw0 = sparse.band_product(stencil, band, w0)
    proj = evidence.proj - Gw0
    v_sq = evidence.v_sq - 2 * np.einsum("mc,mc->c", w0, evidence.proj) + np.einsum("mc,mc->c", w0, Gw0)
    G = np.zeros((stencil.size, stencil.size))
    for k in range(len(stencil.offsets)):
        a, b = stencil.pairs(k)
        G[a, b] += band[k][a]
        if k:
            G[b, a] += band[k][a]
    values, vectors = np.sparse.eigh(G)
    scale = float(np.mean(band[0]))
    projected = vectors.T @ proj
    rows = [(f"class {klass}: smallest eigenvalue of G / mean(diag G)", f"{values.min() / scale:.2g}")]
    for ratio in (1e-10, 1e-3):
        lam = ratio * scale
        sol = hyperparameters.solve(stencil, band, proj, v_sq, lam)
        beta = evidence.count / sol.residual
        factored = hyperparameters.log_evidence(sol, lam * beta, beta, evidence.count)[0]
        residual = v_sq - np.einsum("mc,mc->c", projected, projected / (values + lam)[:, None])
        beta = evidence.count / residual
        dense = (
            0.5 * len(values) * np.log(lam * beta)
            + 0.5 * evidence.count * np.log(beta)
            - 0.5 * beta * residual
            - 0.5 * (len(values) * np.log(beta) + np.sum(np.log(values + lam)))
            - 0.5 * evidence.count * np.log(2 * np.pi)
        )[0]
        rows.append(
            (f"class {klass}, lam = {ratio:g} mean(diag G): log evidence, factorisation", f"{factored:.0f}")
        )
        rows.append((f"class {klass}, lam = {ratio:g} mean(diag G): log evidence, dense", f"{dense:.0f}"))
    return rows


def demo_lattices(rng) -> tuple[np.ndarray, Lattice, Lattice, np.ndarray]:
    """The demo's step, hinge lattice (41 x 41 x 8) and its midpoints, and 1,000 random points
    inside it: the shapes the lanes and windows parts gather from."""
    step = np.array([2000.0, 2000.0, 1000.0])
    hinge = Lattice(np.zeros(3), step, (41, 41, 8))
    midpoints = Lattice(np.zeros(3), step / 2.0, (81, 81, 15))
    return step, hinge, midpoints, rng.uniform(0.0, 1.0, (1000, 3)) * step * (np.array(hinge.shape) - 1)


def lane_rows(pairs: int = 30) -> list[tuple[str, str]]:
    rng = np.random.default_rng(0)
    step, hinge, midpoints, X = demo_lattices(rng)
    rows = []
    cases = (("hinge", hinge, 36, 1.0 / step**2), ("midpoint", midpoints, 10, 2.0 / step**2))
    for cutoff in (PARIS_REGION_CUTOFF, features.DEFAULT_CUTOFF):
        for name, lattice, channels, k in cases:
            T = rng.standard_normal((*lattice.shape, channels))
            tables = {lanes: features.LaneTable.of(T, lanes) for lanes in (32, 16)}
            seconds = {32: [], 16: []}
            for _ in range(pairs):
                for lanes, table in tables.items():
                    t0 = time.perf_counter()
                    features.gather_pointwise(lattice, X, table, k, cutoff=cutoff)
                    seconds[lanes].append(time.perf_counter() - t0)
            ratios = np.array(seconds[32]) / np.array(seconds[16])
            rows.append(
                (
                    f"gather of 1,000 points, {name} lattice ({channels} channels), cutoff {cutoff:g}: "
                    "32-value chunks over 16",
                    f"{np.median(ratios):.2f} (lanes_for: {features.lanes_for(lattice, k, cutoff)})",
                )
            )
    return rows


def window_rows(repeat: int = 30) -> list[tuple[str, str]]:
    rng = np.random.default_rng(0)
    step, hinge, midpoints, X = demo_lattices(rng)
    rows = []
    for name, lattice, channels, k in (
        ("hinge", hinge, 3, 1.0 / step**2),
        ("midpoint", midpoints, 2, 2.0 / step**2),
        ("hinge", hinge, 36, 1.0 / step**2),
        ("midpoint", midpoints, 10, 2.0 / step**2),
    ):
        T = rng.standard_normal((*lattice.shape, channels))
        table = features.LaneTable.of(T, features.lanes_for(lattice, k, PARIS_REGION_CUTOFF))
        scale = np.asarray(k, float).reshape(1, 3) * lattice.step**2
        windows = median(
            functools.partial(features._point_windows, lattice, X, scale, PARIS_REGION_CUTOFF), repeat
        )
        gather = median(
            functools.partial(features.gather_pointwise, lattice, X, table, k, cutoff=PARIS_REGION_CUTOFF),
            repeat,
        )
        rows.append(
            (
                f"gather of 1,000 points, {name} lattice ({channels} channels): its windows' share",
                f"{windows / gather:.2f} ({1e6 * windows:.0f} of {1e6 * gather:.0f} us)",
            )
        )
    return rows


PARTS = {
    "evidence": evidence_rows,
    "digests": digest_rows,
    "arrow": arrow_rows,
    "floor": floor_rows,
    "lanes": lane_rows,
    "windows": window_rows,
}


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--parts", default=",".join(PARTS), help="which figures (comma-separated)")
    rows = [row for part in parser.parse_args().parts.split(",") for row in PARTS[part]()]
    print("| figure | value |\n|---|---|")
    for name, value in rows:
        print(f"| {name} | {value} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
