"""The map layer the routes call: uploads into tiles, queries blended from cached posteriors.

The store holds the truth (statistics, versions, ledger); posteriors are derived data,
kept per ``(region_id, tile, version)`` in a memory-bounded LRU and recomputed when a
tile's version changes.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bdf._validate import noise_std_rows
from bdf.field import Posterior
from bdf.tiles import Increment, RegionSpec, TileKey
from service.store import MapStore, RegionInfo, payload_digest

log = logging.getLogger(__name__)
#: Region versions whose tile versions a :class:`RegionMaps` remembers.
VERSIONS_KEPT = 64


class PosteriorCache:
    """Least-recently-used posteriors, bounded by their memory (``max_mb``)."""

    def __init__(self, max_mb: float = 512.0):
        self.max_bytes = int(max_mb * 2**20)
        self._items: OrderedDict[tuple, Posterior] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key: tuple) -> Posterior | None:
        with self._lock:
            post = self._items.get(key)
            if post is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return post

    def put(self, key: tuple, post: Posterior) -> None:
        with self._lock:
            if key in self._items:
                return
            self._items[key] = post
            self._bytes += post.nbytes
            while self._bytes > self.max_bytes and len(self._items) > 1:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class Prediction:
    mean: np.ndarray  # (n, 3) m/s
    std: np.ndarray  # (n, 3) predictive std, m/s
    known: np.ndarray  # (n,) some tile with data covers the point
    version: int  # region version the answer was computed from
    region_id: str  # with the version, names the map state (ETag)


class RegionMaps:
    """Tiled maps over a :class:`MapStore`: exactly-once uploads, blended queries."""

    def __init__(self, store: MapStore, cache_mb: float = 512.0):
        self.store = store
        self.cache = PosteriorCache(cache_mb)
        # (region_id, region version) -> tile versions and what a tile without data answers:
        # every upload bumps the region's version, so a region version names both for good
        self._versions: OrderedDict[tuple[str, int], tuple[dict[TileKey, int], np.ndarray | None]] = (
            OrderedDict()
        )
        self._lock = threading.Lock()

    def upload(
        self,
        region: str,
        upload_id: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        replace: bool = False,
        progress: Callable[[float], None] | None = None,
    ) -> dict:
        """Apply observations (ENU metres, m/s) to a region once per ``upload_id``.

        Rows with a non-finite value or outside the region are rejected and counted, the
        rest accepted. ``replace``: the region's map becomes this data alone (a fit).
        Returns the ledger result: accepted, rejected (by reason), tiles_updated,
        region_version, replayed. ``progress(fraction)`` follows the per-tile work.
        """
        X, V, noise, weight = _checked(X, V, input_noise_std, sample_weight)
        digest = payload_digest("fit" if replace else "observations", X, V, noise, weight)
        first = self.store.upload_result(region, upload_id, digest)
        if first is not None:
            return first
        spec = self.store.region(region).spec
        increments, summary = _evidence(spec, X, V, noise, weight, progress)
        return self.store.apply(
            region,
            upload_id,
            digest,
            increments,
            observations=summary["accepted"],
            replace=replace,
            summary=summary,
        )

    def predict(self, region: str, X, info: RegionInfo | None = None) -> Prediction:
        """Blended mean, std and ``known`` at ENU points ``X`` (n, 3) inside the region.

        ``info``: the region as the caller read it; its spec applies, and at its version
        cached posteriors answer without reading the store again.
        """
        info = info or self.store.region(region)
        X = np.asarray(X, float)
        groups = info.spec.tiles_containing(X)  # validates X, names the outside rows
        posteriors, info, empty = self._posteriors(region, info, groups)
        if posteriors is None:  # the name was re-created in between: start again
            return self.predict(region, X)  # without the stale spec
        mean, std, known = info.spec.predict(X, posteriors, groups, empty)
        return Prediction(mean, std, known, info.version, info.region_id)

    def predict_grid(self, region: str, axes, info: RegionInfo | None = None) -> Prediction:
        """:meth:`predict` on the grid ``axes[0] x axes[1] x axes[2]``: arrays shaped
        (nx, ny, nz, 3) and (nx, ny, nz)."""
        info = info or self.store.region(region)
        keys = info.spec.tiles_overlapping([np.min(a) for a in axes], [np.max(a) for a in axes])
        posteriors, info, empty = self._posteriors(region, info, keys)
        if posteriors is None:
            return self.predict_grid(region, axes)
        mean, std, known = info.spec.predict_grid(axes, posteriors, empty)
        return Prediction(mean, std, known, info.version, info.region_id)

    def _posteriors(self, region: str, info: RegionInfo, keys):
        """Posteriors of those ``keys`` that hold data, the region's info and the variance of
        a tile without data: from the cache alone when it holds them all at ``info``'s
        version, else from one snapshot (cache first). ``(None, info, None)`` if the region
        no longer has ``info.spec``."""
        with self._lock:
            known = self._versions.get((info.region_id, info.version))
        if known is not None:
            versions, empty = known
            cached = {k: self.cache.get((info.region_id, k, versions[k])) for k in keys if k in versions}
            if all(post is not None for post in cached.values()):
                return cached, info, empty
        spec = info.spec
        found = {}

        def need(region_id: str, key: TileKey, version: int) -> bool:
            found[key] = self.cache.get((region_id, key, version))
            return found[key] is None

        snap = self.store.snapshot(region, keys, need=need)
        if snap.region.spec != spec:
            return None, snap.region, None
        empty = snap.empty_variance
        with self._lock:  # the tile versions at this region version, for the next query
            self._versions[(snap.region.region_id, snap.region.version)] = (
                {k: t.version for k, t in snap.tiles.items()},
                empty,
            )
            while len(self._versions) > VERSIONS_KEPT:
                self._versions.popitem(last=False)
        posteriors = {}
        for key in keys:
            tile = snap.tiles.get(key)
            if tile is None:
                continue  # no data: the prior answers
            post = found.get(key)
            if post is None:
                post = spec.posterior(key, snap.evidence[key])
                self.cache.put((snap.region.region_id, key, tile.version), post)
            posteriors[key] = post
        return posteriors, snap.region, empty


def _checked(X, V, input_noise_std, sample_weight):
    X, V = np.asarray(X, float), np.asarray(V, float)
    if X.ndim != 2 or X.shape[1] != 3 or V.shape != X.shape:
        raise ValueError(f"points and velocities must both be (n, 3), got {X.shape} and {V.shape}")
    noise = None if input_noise_std is None else noise_std_rows(input_noise_std, len(X))
    weight = None if sample_weight is None else np.asarray(sample_weight, float)
    if weight is not None and weight.shape != (len(X),):
        raise ValueError(f"sample_weight must have shape ({len(X)},), got {weight.shape}")
    return X, V, noise, weight


def observations_evidence(
    spec: RegionSpec, X, V, input_noise_std=None, sample_weight=None, progress=None
) -> tuple[dict[TileKey, Increment], dict]:
    """The tile increments of observations, and the summary the ledger keeps: rows with a
    non-finite value (or a negative weight or noise) or outside the region are rejected
    and counted, the rest accepted. Uploads, fits and Dask builds all learn through this."""
    return _evidence(spec, *_checked(X, V, input_noise_std, sample_weight), progress)


def _evidence(spec: RegionSpec, X, V, noise, weight, progress):
    """:func:`observations_evidence` of arrays :func:`_checked` has passed."""
    finite = np.isfinite(X).all(1) & np.isfinite(V).all(1)
    if noise is not None:
        finite &= np.isfinite(noise).all(1) & (noise >= 0).all(1)
    if weight is not None:
        finite &= np.isfinite(weight) & (weight >= 0)
    inside = np.zeros(len(X), bool)
    inside[finite] = spec.inside(X[finite])
    keep = finite & inside
    increments = (
        {}
        if not keep.any()
        else spec.increments(
            X[keep],
            V[keep],
            input_noise_std=None if noise is None else noise[keep],
            sample_weight=None if weight is None else weight[keep],
            progress=None if progress is None else (lambda f: progress(0.9 * f)),
        )
    )
    summary = {
        "accepted": int(keep.sum()),
        "rejected": {"non_finite": int((~finite).sum()), "outside_region": int((finite & ~inside).sum())},
    }
    return increments, summary
