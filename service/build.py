"""City-scale builds with Dask: many observation files, one exactly-once upload.

One task per file turns its rows into tile increments (:func:`observations_evidence`,
the same function uploads use), the increments are summed pairwise in a tree on the
workers (statistics are additive, so the sum is the batch's), and one ``store.apply``
commits the sum: the build is one ledger entry, replayable like any upload, and a
failure anywhere stores nothing. Service replicas see the new region version at once.

Files are Parquet (``.parquet``) or Arrow IPC streams (``.arrow``) with the columns an
upload takes: ``x, y, z`` (or ``lat, lon, alt_m``), ``ve, vn, vu``, and optionally
``input_noise_std`` and ``sample_weight``. Workers read them by path, so on a cluster
the paths must be visible to every worker (a shared volume in ``docker/compose.yaml``).
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from bdf.tiles import Increment, RegionSpec, TileKey
from service import formats
from service.maps import fitted, observations_evidence, write_posterior
from service.problems import Problem
from service.store import MapStore, payload_digest

SUFFIXES = {".parquet": formats.PARQUET, ".arrow": formats.ARROW}


@dataclass
class Part:
    """The evidence of some files: tile increments, ledger summary, per-file digests."""

    increments: dict[TileKey, Increment]
    summary: dict
    digests: list[str]


def file_evidence(spec_json: str, path: str) -> Part:
    """The evidence of one file (runs on a worker)."""
    spec = RegionSpec.model_validate_json(spec_json)
    try:
        obs = formats.read_observations(
            spec, Path(path).read_bytes(), SUFFIXES[Path(path).suffix], sys.maxsize
        )
    except Problem as exc:
        raise ValueError(f"{path}: {exc.detail}") from None
    increments, summary = observations_evidence(spec, obs.X, obs.V, obs.input_noise_std, obs.sample_weight)
    digest = payload_digest("file", obs.X, obs.V, obs.input_noise_std, obs.sample_weight)
    return Part(increments, summary, [digest])


def merge(a: Part, b: Part) -> Part:
    """The evidence of both parts (``a``'s files first)."""
    increments = dict(a.increments)
    for key, inc in b.increments.items():
        old = increments.get(key)
        increments[key] = (
            inc if old is None else Increment(old.evidence + inc.evidence, old.points + inc.points)
        )
    summary = {
        "accepted": a.summary["accepted"] + b.summary["accepted"],
        "rejected": {k: a.summary["rejected"][k] + b.summary["rejected"][k] for k in a.summary["rejected"]},
    }
    return Part(increments, summary, a.digests + b.digests)


def build(
    store: MapStore,
    region: str,
    paths,
    client,
    *,
    replace: bool = True,
    upload_id: str | None = None,
    progress: bool | None = None,
) -> dict:
    """Learn ``region`` from observation files on the Dask ``client``'s workers.

    ``replace``: the map becomes these files alone (a fit); otherwise they are added.
    ``upload_id`` defaults to one derived from the files' content, so re-running the
    same build is a replay. Returns the ledger result, like an upload's.
    ``progress``: a bar over the files (default: on a terminal).
    """
    paths = [Path(p).resolve() for p in paths]
    if not paths:
        raise ValueError("a build needs at least one observation file")
    for p in paths:
        if p.suffix not in SUFFIXES:
            raise ValueError(f"{p}: a build reads {' or '.join(SUFFIXES)} files")
        if not p.is_file():
            raise ValueError(f"{p}: no such file")
    info = store.region(region)
    spec_id, spec_json = info.region_id, info.spec.model_dump_json()
    parts = client.map(file_evidence, [spec_json] * len(paths), [str(p) for p in paths], pure=False)
    _follow(parts, progress)
    while len(parts) > 1:  # pairwise tree sum, on the workers
        pairs = [parts[i : i + 2] for i in range(0, len(parts), 2)]
        parts = [client.submit(merge, *pair, pure=False) if len(pair) == 2 else pair[0] for pair in pairs]
    total = parts[0].result()
    digest = hashlib.sha256(f"build:{replace}:{','.join(total.digests)}".encode()).hexdigest()
    info = store.region(region)
    if info.region_id != spec_id:
        raise ValueError(f"region {region!r} was deleted and re-created during the build: run it again")
    post = write_posterior(info, total.increments, replace)
    return store.apply(
        region,
        upload_id or f"build-{digest[:40]}",
        digest,
        total.increments,
        observations=total.summary["accepted"],
        replace=replace,
        summary=total.summary,
        hyper=None if post is None else fitted(post),
    )


def _follow(futures, progress: bool | None) -> None:
    """Wait for ``futures`` with a bar; the first failure raises here."""
    from distributed import as_completed

    disable = not sys.stderr.isatty() if progress is None else not progress
    with tqdm(total=len(futures), unit="file", desc="evidence", disable=disable) as bar:
        for future in as_completed(futures):
            future.result()
            bar.update()
