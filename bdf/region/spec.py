"""What a region is: a named city area, its geometry, its tiling and its model settings.

A region's ENU box is cut into tiles of ``tile_size_m``; tile ``(i, j, k)`` has the *core*
box ``bounds.min + (i, j, k) * tile_size`` (the last tile per axis ends at ``bounds.max``).
Tiles are the unit of storage, of exactly-once update and of caching, not of the model:
each observation belongs to the one tile whose core holds it, and the tile keeps what
its core's observations add to the region's evidence, over the region's hinges those
points reach (its *support*: the core grown by the kernel's reach at the cutoff, on the
region's lattice, :meth:`RegionSpec.tile_grid`). :mod:`bdf.region.evidence` turns points
into those increments and sums them; :mod:`bdf.region.map` answers queries from the
posterior of ONE field over the region's lattice, with one set of hyperparameters.

:class:`RegionSpec` is also the body ``POST /v1/regions`` accepts: every spec it accepts
can be served (its validator bounds the lattice, the stencil and the map's memory).
"""

from __future__ import annotations

import functools
import logging
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bdf.frames import ENUFrame
from bdf.grid import HingeGrid, Lattice, bounded_counts, noise_lattice
from bdf.kernel import DEFAULT_CUTOFF, NOISE_CUTOFF, Kernel
from bdf.sectors import AUTO_DIRECTIONS, MAX_DIRECTIONS, Sectors
from bdf.validation import as_points, bad_rows, rows_all

if TYPE_CHECKING:  # the schema loads no numerics (numba, scipy): a client or planner may use it
    from bdf.statistics import SectorEvidence

log = logging.getLogger(__name__)
TileKey = tuple[int, int, int]
#: Most tiles a region may have (keys, ledgers and listings stay small).
MAX_TILES = 100_000
#: A region's bounds lie within this distance of its origin (metres): ENU is a local frame.
MAX_EXTENT_M = 1e6
#: Most hinge offsets per axis-aligned box the kernel reaches (checked first, cheaply), and
#: most couplings (hinges x the stencil's offsets, each a float64 of a class's Gram band):
#: what bounds a factor's memory.
MAX_STENCIL = 5000
MAX_COUPLINGS = 3e8
#: Peak memory of computing a region's map where data covers the whole lattice (the
#: factor's fill is largest; it grows with the lattice), with room: per coupling (the
#: factors of the map with one class and of a mode per thread, alive at once), and per
#: hinge and traffic class (each class's evidence and tables, all kept)
#: (``bench/bench_isolation.py --parts maps`` measures both).
MAP_BYTES_PER_COUPLING = 250
MAP_BYTES_PER_CLASS_HINGE = 1000
#: The model behind a region that answers one class (:attr:`RegionSpec.model_directions`).
ONE_CLASS_MODEL_DIRECTIONS = 8
#: The model of a region of ``directions: "auto"`` until a fit chooses (uploads before one
#: are split into these sectors).
AUTO_FIRST_DIRECTIONS = 16
#: Folds of the flight-grouped cross-validation by which a fit chooses (:mod:`bdf.region.resolution`).
CHOICE_FOLDS = 3

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
PositiveVec3 = Annotated[list[Positive], Field(min_length=3, max_length=3)]
Hyper = Literal["auto"] | Positive | PositiveVec3


class Origin(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    lat: Annotated[float, Field(ge=-90, le=90)]
    lon: Annotated[float, Field(ge=-180, le=180)]
    alt_m: Finite = 0.0


class Bounds(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _ordered(self):
        if any(hi <= lo for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"bounds_m.max {self.max} must exceed bounds_m.min {self.min} on every axis")
        return self


#: A region's name (its URL path segment), and the rule it states in words
REGION_NAME = r"^[a-z0-9][a-z0-9_-]{0,62}$"
REGION_NAME_RULE = "1 to 63 lowercase letters, digits, _ and -, starting with a letter or digit"
#: A sum of non-negative terms may round to this fraction of its largest below zero.
ROUNDING = 1e-9


class Envelope(BaseModel):
    """What the region's traffic can physically do (defaults: aircraft). Rows outside are
    rejected and counted by reason, like non-finite ones; the bounds also keep every
    accepted row's contribution to the statistics finite and the precision well posed."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    max_horizontal_speed_mps: Positive = 400.0
    max_vertical_speed_mps: Positive = 100.0
    max_input_noise_std_m: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = 1000.0
    min_sample_weight: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1e-6
    max_sample_weight: Annotated[float, Field(ge=1, le=1e6, allow_inf_nan=False)] = 1000.0

    def speed_ok(self, V: np.ndarray) -> np.ndarray:
        """(n,): the velocity rows (finite) within the speed limits."""
        horizontal = V[:, 0] ** 2 + V[:, 1] ** 2
        vertical = np.abs(V[:, 2])
        return (horizontal <= self.max_horizontal_speed_mps**2) & (vertical <= self.max_vertical_speed_mps)

    def noise_ok(self, noise: np.ndarray) -> np.ndarray:
        """(n,): input-noise rows (finite) within ``[0, max_input_noise_std_m]`` on every axis."""
        return rows_all((noise >= 0) & (noise <= self.max_input_noise_std_m))

    def weight_ok(self, weight: np.ndarray) -> np.ndarray:
        """(n,): sample weights (finite) in ``[min_sample_weight, max_sample_weight]``."""
        return (weight >= self.min_sample_weight) & (weight <= self.max_sample_weight)

    def problems(self, evidence: SectorEvidence, points: int) -> list[str]:
        """What in a tile's statistics of ``points`` observations no accepted rows can make:
        values that are not finite, weights or mean squared speeds beyond the envelope (a
        store written before the envelope was checked, or damaged), sums of non-negative
        terms negative beyond rounding (a retraction of more than the tile held)."""
        out = []
        square = np.array(
            [self.max_horizontal_speed_mps, self.max_horizontal_speed_mps, self.max_vertical_speed_mps]
        )
        for c, ev in enumerate(evidence.classes):
            parts = [ev.density, ev.proj, ev.mass, ev.v_sum, ev.v_sq, np.array(ev.count)]
            parts += [a for a in (ev.gram_noisy, ev.moments) if a is not None]
            negative = [
                name
                for name in ("count", "density", "mass", "v_sq")
                if np.min(getattr(ev, name)) < -ROUNDING * np.abs(getattr(ev, name)).max()
            ]
            if not all(np.isfinite(a).all() for a in parts):
                out.append(f"class {c}: statistics that are not finite")
            elif negative:
                out.append(
                    f"class {c}: {negative[0]} negative beyond rounding, a sum of non-negative terms (what "
                    "a retraction of more than the tile held leaves): these statistics cannot be trusted; "
                    "fit the region again"
                )
            elif ev.count > points * self.max_sample_weight * (1 + 1e-9):
                out.append(
                    f"class {c}: weights summing to {ev.count:.6g} over {points} observations "
                    f"(at most {self.max_sample_weight:g} each)"
                )
            elif np.any(ev.v_sq > ev.count * square**2 * (1 + 1e-9)):
                rms = np.sqrt(ev.v_sq / ev.count).tolist()
                out.append(f"class {c}: root mean square velocity {rms} m/s beyond the envelope")
        return out


class DirectionsScore(BaseModel):
    """How one heading resolution scored when a fit chose among them (``directions: "auto"``,
    :mod:`bdf.region.resolution`): flight-grouped cross-validation of the fit's rows."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    directions: int
    #: held-out mixture MSLL (the density of the velocity, :func:`bdf.metrics.mixture_msll`),
    #: mean over the folds and its standard error
    mixture_msll: float
    mixture_msll_se: float
    #: held-out MSLL of the answer without a heading (the mixture's moments)
    msll: float
    #: RMSE of the mode of the heading each held-out row flies (m/s)
    conditional_rmse_mps: float
    chosen: bool


class RegionSpec(BaseModel):
    """A named city region: geodetic origin, ENU box, tiling and model settings (metres, 1/m^2).

    Its JSON form (``model_dump(mode="json")``) is the body ``POST /v1/regions`` accepts.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: Annotated[str, Field(pattern=REGION_NAME, description=REGION_NAME_RULE)]
    origin: Origin
    bounds_m: Bounds
    tile_size_m: PositiveVec3
    spacing_m: PositiveVec3
    gamma: PositiveVec3
    alpha: Hyper = "auto"
    beta: Hyper = "auto"
    noise_spacing_m: PositiveVec3 | None = None
    noise_prior: Positive = 0.1
    #: Kernel cutoff (:mod:`bdf.kernel`): it sets the precision's stencil, so the cost of
    #: a solve; looser values trade exactness for speed.
    cutoff: Annotated[float, Field(gt=0, lt=1)] = DEFAULT_CUTOFF
    #: Heading sectors the region answers (1: one velocity per point; more: a mixture of
    #: traffic classes, :mod:`bdf.sectors`, and the mode of a heading); "auto" (the default,
    #: unless ``model_directions`` is named: then 1): as many as the region's fits choose
    #: (:mod:`bdf.region.resolution`), ``model_directions`` until then. A mixture answers its
    #: moments as ``mean`` and ``std`` too, so a client of one class reads the same columns.
    directions: Annotated[int, Field(ge=1, le=MAX_DIRECTIONS)] | Literal["auto"] = "auto"
    #: Heading sectors of the model behind the answers (:data:`ONE_CLASS_MODEL_DIRECTIONS`
    #: when one class is answered, :data:`AUTO_FIRST_DIRECTIONS` for "auto" until a fit
    #: chooses, else ``directions``): a region of one class answers the moments of a
    #: directional mixture, since one smooth field cannot represent flows stacked a few
    #: hundred metres apart that fly opposite ways (it swings between them to several times
    #: the fastest traffic: ``bench/bench_one_class.py``); 1 is the paper's model of one field.
    model_directions: Annotated[
        int, Field(ge=1, le=MAX_DIRECTIONS, default_factory=lambda spec: _model_for(spec["directions"]))
    ]
    #: ``directions: "auto"``: the scores of each candidate (:data:`bdf.sectors.AUTO_DIRECTIONS`)
    #: when the region's last fit chose ``model_directions`` (written by the fit, not sent).
    directions_scores: tuple[DirectionsScore, ...] | None = None
    slow_mps: Positive = 5.0
    #: The longest time a row of a track stands for (its tracks' sampling interval, at most:
    #: :func:`bdf.ingest.track_weights`); sparser tracks count for less than they carry.
    track_interval_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = 1.0
    envelope: Envelope = Envelope()

    @model_validator(mode="before")
    @classmethod
    def _default_directions(cls, data):
        """A spec that names its model's sectors and not ``directions`` is of one class, as
        before "auto" was the default: only a region of one class answered from another model."""
        if isinstance(data, dict) and "directions" not in data and data.get("model_directions") is not None:
            return {**data, "directions": 1}
        return data

    @model_validator(mode="after")
    def _consistent(self):
        """Refuse a spec that could not be served: every accepted one takes uploads and
        answers queries, grids and slices (a property test, tests/service/test_hostile.py)."""
        if self.directions == "auto":
            if self.model_directions == 1:
                raise ValueError('directions "auto" needs a model of heading sectors: model_directions > 1')
        elif self.directions > 1 and self.model_directions != self.directions:
            raise ValueError(
                f"model_directions {self.model_directions} must equal directions {self.directions} (or be "
                "left out): only a region of one class answers from another model"
            )
        if self.directions_scores is not None and self.directions != "auto":
            raise ValueError('directions_scores are written by the fit of a region of directions "auto"')
        lower, upper, spacing = self.lower, self.upper, np.array(self.spacing_m)
        extent = upper - lower
        if np.abs(np.r_[lower, upper]).max() > MAX_EXTENT_M:
            raise ValueError(f"bounds_m must lie within {MAX_EXTENT_M:g} m of the origin on every axis")
        if np.any(spacing > extent):
            raise ValueError(
                f"spacing_m {self.spacing_m} must not exceed the box {extent.tolist()} on any axis"
            )
        if self.noise_spacing_m is not None and np.any(np.array(self.noise_spacing_m) > extent):
            raise ValueError(
                f"noise_spacing_m {self.noise_spacing_m} must not exceed the box {extent.tolist()} on any "
                "axis"
            )
        reach = self.reach_m
        # every point of the box (its last hinge may lie up to a spacing short of its edge)
        # reaches a hinge, and the kernel does not reach past the whole box
        if np.any(reach < spacing) or np.any(reach > extent.max()):
            raise ValueError(
                f"the kernel's reach at the cutoff, sqrt(log(1/cutoff) / gamma) = {reach.tolist()} m, must "
                f"be at least the spacing {spacing.tolist()} and at most the box's longest side "
                f"{extent.max():g} on every axis: change gamma"
            )
        self.tile_counts  # noqa: B018  (raises if the region would have too many tiles)
        self.grid  # noqa: B018  (raises if the region would have too many hinges)
        self.noise_lattice  # noqa: B018  (or too many noise lattice points)
        widths = np.minimum(2 * np.floor(reach / spacing) + 1, 2 * np.array(self.grid.shape) - 1)
        if np.prod(widths) > MAX_STENCIL:
            raise ValueError(
                f"the kernel couples {np.prod(widths):.6g} hinge offsets ({widths.tolist()} per axis), more "
                f"than {MAX_STENCIL}: raise gamma or the spacing"
            )
        if self.couplings > MAX_COUPLINGS:
            raise ValueError(
                f"{self.grid.size} hinges x {self.coupled_offsets} coupled offsets is {self.couplings:.3g} "
                f"couplings, more than {MAX_COUPLINGS:g}: raise the spacing or gamma"
            )
        return self

    @property
    def coupled_offsets(self) -> int:
        """The hinge offsets each hinge couples to in the precision (its stencil's half)."""
        return len(self.kernel.couplings(self.grid.step, self.grid.shape)[0])

    @property
    def couplings(self) -> int:
        """Hinges x the stencil's offsets: what a factor's memory grows with (a map factors
        its classes one at a time per thread, :class:`bdf.posterior.Mixture`)."""
        return self.grid.size * self.coupled_offsets

    @property
    def map_bytes(self) -> float:
        """The most memory computing its map may take (data over the whole lattice; of
        ``directions: "auto"``, at the most sectors a fit may choose)."""
        classes = (Sectors(max(AUTO_DIRECTIONS)) if self.directions == "auto" else self.model_sectors).classes
        return (
            float(self.couplings) * MAP_BYTES_PER_COUPLING
            + float(self.grid.size * classes) * MAP_BYTES_PER_CLASS_HINGE
        )

    # -- geometry ---------------------------------------------------------------------------
    @property
    def lower(self) -> np.ndarray:
        return np.array(self.bounds_m.min, float)

    @property
    def upper(self) -> np.ndarray:
        return np.array(self.bounds_m.max, float)

    @property
    def kernel(self) -> Kernel:
        return Kernel(tuple(self.gamma), self.cutoff)

    @property
    def reach_m(self) -> np.ndarray:
        """Per axis, how far the kernel reaches above the cutoff (metres)."""
        return self.kernel.reach_m

    @property
    def auto(self) -> bool:
        """Some hyperparameter is fitted by evidence maximisation."""
        return self.alpha == "auto" or self.beta == "auto"

    @functools.cached_property  # a tuple: equality of specs still compares fields only
    def tile_counts(self) -> tuple[int, int, int]:
        with np.errstate(over="ignore"):  # a tiny tile counts as infinitely many
            n = np.maximum(np.ceil((self.upper - self.lower) / np.array(self.tile_size_m) - 1e-9), 1)
        if not np.prod(n) <= MAX_TILES:
            raise ValueError(f"{np.prod(n):.6g} tiles ({n.tolist()} per axis) is more than {MAX_TILES}")
        return tuple(int(c) for c in n)

    @property
    def posteriors(self) -> int:
        """Posteriors its map holds: one, or (a directional model) the total and each class's."""
        return 1 if self.model_directions == 1 else 1 + self.model_sectors.classes

    @property
    def grid(self) -> HingeGrid:
        """The region's hinge lattice: ``bounds.min + i * spacing`` up to ``bounds.max``."""
        return _grid(tuple(self.bounds_m.min), tuple(self.bounds_m.max), tuple(self.spacing_m))

    @property
    def noise_lattice(self) -> Lattice | None:
        """The region's local-noise lattice, or None with the global noise."""
        if self.noise_spacing_m is None:
            return None
        return _noise_lattice(tuple(self.bounds_m.min), tuple(self.bounds_m.max), tuple(self.noise_spacing_m))

    @property
    def sectors(self) -> Sectors:
        """The traffic classes the region answers (of "auto": its model's)."""
        return Sectors(self.model_directions if self.directions == "auto" else self.directions, self.slow_mps)

    @property
    def one_class(self) -> bool:
        """The region answers one velocity per point (the moments of its model, if directional)."""
        return self.directions == 1

    @property
    def fit_classes(self) -> int:
        """Traffic classes a fit of this region computes maps of: its model's, or
        (``directions: "auto"``) each candidate's, once on all the rows and once per fold
        (:mod:`bdf.region.resolution`)."""
        if self.directions != "auto":
            return self.model_sectors.classes
        return (1 + CHOICE_FOLDS) * sum(Sectors(S).classes for S in AUTO_DIRECTIONS)

    def with_directions(
        self, directions: int, scores: tuple[DirectionsScore, ...] | None = None
    ) -> RegionSpec:
        """This spec of ``directions: "auto"`` with the model a fit chose (and its scores)."""
        update = {"model_directions": directions, "directions_scores": scores}
        return RegionSpec.model_validate({**self.model_dump(), **update})

    @property
    def model_sectors(self) -> Sectors:
        """The traffic classes its evidence is split into and its map fits."""
        return Sectors(self.model_directions, self.slow_mps)

    def frame(self) -> ENUFrame:
        return _frame(self.origin.lat, self.origin.lon, self.origin.alt_m)

    def core(self, key: TileKey) -> tuple[np.ndarray, np.ndarray]:
        """The tile's own box: the observations it holds."""
        lo = self.lower + np.array(key) * np.array(self.tile_size_m)
        return lo, np.minimum(lo + self.tile_size_m, self.upper)

    def _support(self, key: TileKey, lattice: Lattice, reach: np.ndarray) -> Lattice:
        """The points of ``lattice`` within ``reach`` (metres per axis) of the tile's core."""
        lo, hi = self.core(key)
        first = np.maximum(np.ceil((lo - reach - lattice.origin) / lattice.step - 1e-9), 0).astype(int)
        last = np.minimum(
            np.floor((hi + reach - lattice.origin) / lattice.step + 1e-9), np.array(lattice.shape) - 1
        ).astype(int)
        return Lattice(
            lattice.origin + first * lattice.step, lattice.step, tuple(int(c) for c in last - first + 1)
        )

    def tile_grid(self, key: TileKey) -> HingeGrid:
        """The tile's support: the region's hinges its core's points reach (at the cutoff)."""
        sub = self._support(key, self.grid, self.reach_m)
        return HingeGrid(sub.origin, sub.origin + sub.step * (np.array(sub.shape) - 1) + 1e-9, sub.step)

    def tile_noise_lattice(self, key: TileKey) -> Lattice | None:
        """The part of the region's noise lattice the tile's points reach, or None."""
        if self.noise_lattice is None:
            return None
        reach = np.sqrt(np.log(1.0 / NOISE_CUTOFF)) * self.noise_lattice.step
        return self._support(key, self.noise_lattice, reach)

    def inside(self, X: np.ndarray) -> np.ndarray:
        """Rows of ``X`` (n, 3) inside the region's box (closed)."""
        return rows_all(self._in_box(X))

    def _in_box(self, X: np.ndarray) -> np.ndarray:
        """(n, 3): each coordinate within the region's bounds (closed; never for NaN)."""
        return (X >= self.lower) & (X <= self.upper)

    def inside_points(self, X) -> np.ndarray:
        """``X`` as validated points (n, 3), all inside the region (``ValueError`` names the
        rows outside)."""
        X = as_points(X, "X", allow_empty=True)
        in_box = self._in_box(X)
        if not in_box.all():  # rows only for the message
            raise ValueError(f"points outside region {self.name!r} bounds: {bad_rows(~rows_all(in_box))}")
        return X

    # -- grids of voxels ----------------------------------------------------------------
    @staticmethod
    def box_axes(lo, hi, step, max_voxels: float = np.inf) -> list[np.ndarray]:
        """The voxel grid of a box: per axis ``lo + i * step`` up to ``hi`` inclusive.
        ``ValueError`` above ``max_voxels``, checked before anything is allocated."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        step = np.broadcast_to(np.asarray(step, float), (3,))
        counts = bounded_counts(
            lo, hi, step, max_voxels, "the grid", "voxels", "raise the step or shrink the box"
        )
        # the last point may pass hi by rounding (far from the origin): it is hi
        return [np.minimum(lo[d] + step[d] * np.arange(int(counts[d])), hi[d]) for d in range(3)]

    def grid_axes(self, axes) -> list[np.ndarray]:
        """The axes of a grid of voxels, checked: finite, non-empty, inside the region."""
        axes = [np.asarray(a, float).ravel() for a in axes]
        for d, a in enumerate(axes):
            if (
                len(a) == 0
                or not np.all(np.isfinite(a))
                or a.min() < self.lower[d]
                or a.max() > self.upper[d]
            ):
                raise ValueError(f"grid axis {d} must be finite, non-empty and inside region {self.name!r}")
        return axes


def _model_for(directions: int | str) -> int:
    """The model's sectors of a spec that does not name them: written out, so that a
    stored spec says what its evidence holds."""
    if directions == "auto":
        return AUTO_FIRST_DIRECTIONS
    return ONE_CLASS_MODEL_DIRECTIONS if directions == 1 else directions


@functools.lru_cache(maxsize=64)
def _grid(lower, upper, spacing) -> HingeGrid:
    """Lattices are shared per spec (specs are frozen; every request reads its region's)."""
    return HingeGrid(lower, upper, spacing)


@functools.lru_cache(maxsize=64)
def _noise_lattice(lower, upper, spacing) -> Lattice:
    return noise_lattice(lower, upper, spacing)


@functools.lru_cache(maxsize=64)
def _frame(lat: float, lon: float, alt_m: float) -> ENUFrame:
    """Frames are shared per origin: building a pyproj transformer costs milliseconds."""
    return ENUFrame(lat, lon, alt_m)


def key_str(key: TileKey) -> str:
    """Tile key as stored and shown: ``"i_j_k"``."""
    return "_".join(str(int(v)) for v in key)


def parse_key(text: str) -> TileKey:
    parts = text.split("_")
    if len(parts) != 3 or not all(p.lstrip("-").isdigit() for p in parts):
        raise ValueError(f"a tile key is three integers joined by '_', got {text!r}")
    return tuple(int(p) for p in parts)
