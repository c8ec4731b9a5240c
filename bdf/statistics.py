"""Evidence: the additive sufficient statistics of a field, and the one function that makes them.

For features ``phi_m(x) = exp(-sum_d gamma_d (x_d - h_md)^2)`` the product of two
features is ``c(h_m - h_m') exp(-sum_d 2 gamma_d (x_d - g_d)^2)`` with ``g`` the midpoint of
the two hinges and ``c(d) = exp(-sum_d gamma_d d_d^2 / 2)``. Hence

    Phi^T Phi [m, m'] = c(h_m - h_m') * D(g_mm'),   D(g) = sum_n exp(-sum_d 2 gamma_d (x_nd - g_d)^2)

and the data enter ``Phi^T Phi`` only through the density ``D`` on the midpoint lattice
((2 n_d - 1) points per axis): that is what :class:`Evidence` stores, O(N K) to build and
about 8 M numbers instead of M^2. Points with input noise (the expected kernel has a
per-point width) do not fit the identity; their Gram part is kept in ``gram_noisy`` as a
band on the precision's stencil (:mod:`bdf.sparse`).

Stored format (version 3), all float64:
    density     (2nx-1, 2ny-1, 2nz-1)   D above, noise-free points
    gram_noisy  (K, M) or absent         sum of phi~ phi~^T over noisy-input points, as a
                                         band: [k, m] is the pair (m, m + o_k) of the stencil
    proj        (M, 3)                   Phi^T V
    mass        (M,)                     Phi^T 1 (weighted): the share field's right-hand side
                                         (zeros in a map of one class, which has none)
    count       ()                       sum of sample weights (decayed when forgetting)
    v_sum       (3,)                     sum of V per component
    v_sq        (3,)                     sum of V^2 per component
    moments     noise lattice + (7,)     only with local noise: see :mod:`bdf.noise`

As one blob (:meth:`Evidence.to_bytes`, what the map stores keep per tile): little-endian
float64 values in the order count, v_sum, v_sq, proj (C order), mass, density (C order),
then the moments (C order) if the tile has local noise (its spec says so), then, only if
present, the band ``gram_noisy`` (C order, K M values). Shapes follow from the tile's hinge
grid, noise lattice and stencil; the length tells whether ``gram_noisy`` is there. Version
2 had no ``mass`` (read as zeros: a map of one class never uses it).

A directional map (:mod:`bdf.sectors`) keeps one :class:`Evidence` per traffic class
(:class:`SectorEvidence`); its blob is the classes' blobs one after the other, each
preceded by its length in values (little-endian int64).

Version 4 adds, before that, the count of rows per altitude bin (:data:`ALT_BIN_M` of
altitude, over the grid's altitudes: :func:`altitude_bins`) and horizontal speed bin
(:data:`SPEED_BIN_MPS` wide, :data:`SPEED_BINS` of them): how fast the traffic near each
altitude flies (:func:`bdf.region.map.speed_bound`), as its length in values (int64, 0
without it) and the values (altitude bins x speed bins, C order); a class's own blob is as
in version 3.

Version 5 stores a tile as two such blobs, its statistics and their rounding residual
(:func:`compensated_sum`), the first after its length in bytes (int64): a tile's value is
their sum to twice float64's precision, so an upload retracted from tiles it outweighed
leaves the statistics of the rest to float64's precision (no cancellation error).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numba
import numpy as np

from bdf import features, noise, sparse
from bdf.grid import HingeGrid, Lattice
from bdf.kernel import Kernel
from bdf.sectors import Sectors
from bdf.validation import take_rows

FORMAT_VERSION = 5
#: Blob formats this code reads.
READABLE_FORMATS = (2, 3, 4, 5)
#: The speed histogram's bins (m/s), up to SPEED_BINS x SPEED_BIN_MPS (faster rows: the last)
SPEED_BIN_MPS = 2.0
SPEED_BINS = 256
#: The speed histogram's altitude bins (metres): bin k holds altitudes [k, k + 1) x ALT_BIN_M
ALT_BIN_M = 100.0


def altitude_bins(grid: HingeGrid) -> tuple[int, int]:
    """The first altitude bin over ``grid``'s altitudes and how many there are."""
    top = grid.origin[2] + (grid.shape[2] - 1) * grid.step[2]
    first = int(np.floor(grid.origin[2] / ALT_BIN_M))
    return first, int(np.floor(top / ALT_BIN_M)) - first + 1


#: Midpoint-lattice cells per block: 2 = one hinge cell (fewest BLAS calls for the flops, measured).
MIDPOINT_BLOCK = 2


@dataclass
class Evidence:
    """Additive statistics of a set of observations on one hinge grid (see module doc)."""

    density: np.ndarray
    proj: np.ndarray
    mass: np.ndarray
    count: float
    v_sum: np.ndarray
    v_sq: np.ndarray
    gram_noisy: np.ndarray | None = None
    moments: np.ndarray | None = None

    @classmethod
    def zeros(cls, grid: HingeGrid, noise_lattice: Lattice | None = None) -> Evidence:
        return cls(
            density=np.zeros(grid.midpoints().shape),
            proj=np.zeros((grid.size, 3)),
            mass=np.zeros(grid.size),
            count=0.0,
            v_sum=np.zeros(3),
            v_sq=np.zeros(3),
            moments=None if noise_lattice is None else np.zeros((*noise_lattice.shape, noise.CHANNELS)),
        )

    @classmethod
    def from_points(
        cls,
        grid: HingeGrid,
        kernel: Kernel,
        X: np.ndarray,
        V: np.ndarray,
        input_noise_std: np.ndarray | None = None,
        sample_weight: np.ndarray | None = None,
        *,
        noise_lattice: Lattice | None = None,
        mass: bool = True,
    ) -> Evidence:
        """The statistics increment of observations ``(X, V)``: everything that learns calls this.

        ``X``, ``V`` are validated (N, 3) arrays; ``input_noise_std`` is None or (N, 3);
        ``sample_weight`` is None or (N,) >= 0: each point's log-likelihood counts that many
        times (a weight of 2 equals the point given twice). With ``noise_lattice``, the
        local-noise moments are kept too (at the given positions, input noise or not).
        ``mass=False`` leaves ``mass`` zero: only the share field of a directional map reads
        it, and a map of one class saves a quarter of ``Phi^T V``'s splat.
        """
        gamma, cutoff = np.array(kernel.gamma), kernel.cutoff
        w = np.ones(len(X)) if sample_weight is None else sample_weight
        noisy = None if input_noise_std is None else np.any(input_noise_std > 0, 1)
        if noisy is not None and not noisy.any():
            noisy = None
        plain = slice(None) if noisy is None else ~noisy  # a view when no point is noisy
        density = features.splat(
            grid.midpoints(), X[plain], w[plain, None], 2.0 * gamma, cutoff=cutoff, block=MIDPOINT_BLOCK
        )[..., 0]
        wV = V * w[:, None]
        wV1 = np.concatenate([wV, w[:, None]], axis=1) if mass else wV  # Phi^T V and Phi^T 1 in one pass
        C = wV1.shape[1]
        proj = features.splat(grid, X[plain], wV1[plain], gamma, cutoff=cutoff).reshape(-1, C)
        gram_noisy = None
        if noisy is not None:
            k, amplitude = features.expected_kernel(gamma, input_noise_std[noisy])
            weighted = wV1[noisy] * amplitude[:, None]
            proj += features.splat(grid, X[noisy], weighted, k, cutoff=cutoff).reshape(-1, C)
            gram_noisy = features.gram_band(
                grid,
                X[noisy],
                k,
                amplitude * np.sqrt(w[noisy]),
                sparse.stencil_on(grid, kernel),
                cutoff=cutoff,
            )
        return cls(
            density=density,
            proj=np.ascontiguousarray(proj[:, :3]),
            mass=np.ascontiguousarray(proj[:, 3]) if mass else np.zeros(grid.size),
            count=float(w.sum()),
            v_sum=V.T @ w,  # BLAS: numpy's sums down a column are several times slower
            v_sq=(V * V).T @ w,
            gram_noisy=gram_noisy,
            moments=None if noise_lattice is None else noise.moments(noise_lattice, X, V, w),
        )

    def __add__(self, other: Evidence) -> Evidence:
        if self.density.shape != other.density.shape:
            raise ValueError(f"cannot add evidence of grids {self.density.shape} and {other.density.shape}")
        if self.gram_noisy is None or other.gram_noisy is None:
            gram_noisy = self.gram_noisy if other.gram_noisy is None else other.gram_noisy
        else:
            gram_noisy = self.gram_noisy + other.gram_noisy
        if (self.moments is None) != (other.moments is None):
            raise ValueError("cannot add evidence with local-noise moments to evidence without")
        moments = None if self.moments is None else self.moments + other.moments
        return Evidence(
            density=self.density + other.density,
            proj=self.proj + other.proj,
            mass=self.mass + other.mass,
            count=self.count + other.count,
            v_sum=self.v_sum + other.v_sum,
            v_sq=self.v_sq + other.v_sq,
            gram_noisy=gram_noisy,
            moments=moments,
        )

    def __sub__(self, other: Evidence) -> Evidence:
        return self + other.scaled(-1.0)

    def scaled(self, factor: float) -> Evidence:
        """Every statistic times ``factor`` (exponential forgetting uses 0 < factor < 1)."""
        return Evidence(
            density=self.density * factor,
            proj=self.proj * factor,
            mass=self.mass * factor,
            count=self.count * factor,
            v_sum=self.v_sum * factor,
            v_sq=self.v_sq * factor,
            gram_noisy=None if self.gram_noisy is None else self.gram_noisy * factor,
            moments=None if self.moments is None else self.moments * factor,
        )

    def accumulated(self, residual: Evidence, increment: Evidence) -> tuple[Evidence, Evidence]:
        """``self + residual + increment`` as a new (sum, residual), statistic by statistic
        (:func:`compensated_sum`; a statistic absent from some is their zeros)."""
        sums, residuals = {}, {}
        for f in fields(self):
            parts = [getattr(e, f.name) for e in (self, residual, increment)]
            present = [np.asarray(a, float) for a in parts if a is not None]
            if not present:
                sums[f.name] = residuals[f.name] = None
                continue
            if f.name == "moments" and len(present) != 3:
                raise ValueError("cannot add evidence with local-noise moments to evidence without")
            hi, lo, inc = (np.zeros_like(present[0]) if a is None else np.asarray(a, float) for a in parts)
            sums[f.name], residuals[f.name] = _accumulated(hi, lo, inc)
        for out in (sums, residuals):
            out["count"] = float(out["count"])
        return Evidence(**sums), Evidence(**residuals)

    def gram_band(self, stencil: sparse.Stencil) -> np.ndarray:
        """``Phi^T Phi`` on the stencil, as a band (K, M): ``c(o) D(midpoint)`` per pair
        (the midpoint of hinges m and m + o is at index ``2 idx(m) + o``), plus the noisy part."""
        out = sparse.midpoint_band(stencil, self.density)
        if self.gram_noisy is not None:
            out += self.gram_noisy
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for storage (format documented in the module docstring)."""
        return {
            f.name: np.asarray(getattr(self, f.name))
            for f in fields(self)
            if getattr(self, f.name) is not None
        }

    def to_bytes(self) -> bytes:
        """The stored blob (layout in the module docstring)."""
        parts = [[self.count], self.v_sum, self.v_sq, self.proj.ravel(), self.mass, self.density.ravel()]
        if self.moments is not None:
            parts.append(self.moments.ravel())
        if self.gram_noisy is not None:
            parts.append(self.gram_noisy.ravel())
        return np.concatenate(parts).astype("<f8", copy=False).tobytes()

    @classmethod
    def from_bytes(
        cls,
        blob: bytes,
        grid: HingeGrid,
        stencil: sparse.Stencil,
        noise_lattice: Lattice | None = None,
        format_version: int = FORMAT_VERSION,
    ) -> Evidence:
        values = np.frombuffer(blob, dtype="<f8").astype(np.float64)
        if format_version not in READABLE_FORMATS:
            raise ValueError(f"statistics format {format_version}: this code reads {READABLE_FORMATS}")
        M, n_density = grid.size, grid.midpoints().size
        n_mass = M if format_version >= 3 else 0
        dense = 7 + 3 * M + n_mass + n_density
        shape = None if noise_lattice is None else (*noise_lattice.shape, noise.CHANNELS)
        plain = dense + (0 if shape is None else int(np.prod(shape)))
        band = len(stencil.offsets) * M
        if len(values) not in (plain, plain + band):
            raise ValueError(
                f"an evidence blob of {len(values)} values does not fit a grid of {M} hinges "
                f"{'without' if shape is None else 'with'} local noise "
                f"(expected {plain} or {plain + band})"
            )
        gram_noisy = values[plain:].reshape(len(stencil.offsets), M) if len(values) > plain else None
        return cls(
            count=float(values[0]),
            v_sum=values[1:4],
            v_sq=values[4:7],
            proj=values[7 : 7 + 3 * M].reshape(M, 3),
            mass=values[7 + 3 * M : 7 + 3 * M + n_mass] if n_mass else np.zeros(M),
            density=values[7 + 3 * M + n_mass : dense].reshape(grid.midpoints().shape),
            moments=None if shape is None else values[dense:plain].reshape(shape),
            gram_noisy=gram_noisy,
        )

    @classmethod
    def from_arrays(
        cls, arrays, grid: HingeGrid, stencil: sparse.Stencil, noise_lattice: Lattice | None = None
    ) -> Evidence:
        M = grid.size
        expected = {
            "density": grid.midpoints().shape,
            "proj": (M, 3),
            "mass": (M,),
            "count": (),
            "v_sum": (3,),
            "v_sq": (3,),
        }
        if "gram_noisy" in arrays:
            expected["gram_noisy"] = (len(stencil.offsets), M)
        if noise_lattice is not None:
            expected["moments"] = (*noise_lattice.shape, noise.CHANNELS)
        elif "moments" in arrays:
            raise ValueError("evidence has local-noise moments but the field has no noise_spacing")
        values = {}
        for name, shape in expected.items():
            if name not in arrays:
                raise ValueError(f"evidence is missing {name!r}")
            arr = np.asarray(arrays[name], dtype=np.float64)
            if arr.shape != tuple(shape):
                raise ValueError(f"evidence {name!r} has shape {arr.shape}, expected {tuple(shape)}")
            values[name] = arr
        values["count"] = float(values["count"])
        return cls(**values)


@dataclass
class SectorEvidence:
    """The evidence of a map: one :class:`Evidence` per traffic class (:mod:`bdf.sectors`),
    each made by :meth:`Evidence.from_points` from that class's observations. Additive like
    its parts; a map of one class is its one part."""

    classes: tuple[Evidence, ...]
    #: rows per altitude bin over the grid and horizontal speed bin (altitude_bins, SPEED_BINS),
    #: or None
    speeds: np.ndarray | None = None

    @classmethod
    def zeros(cls, grid: HingeGrid, noise_lattice: Lattice | None, sectors: Sectors) -> SectorEvidence:
        classes = tuple(Evidence.zeros(grid, noise_lattice) for _ in range(sectors.classes))
        return cls(classes, np.zeros((altitude_bins(grid)[1], SPEED_BINS)))

    @classmethod
    def from_points(
        cls,
        grid: HingeGrid,
        kernel: Kernel,
        X: np.ndarray,
        V: np.ndarray,
        input_noise_std: np.ndarray | None = None,
        sample_weight: np.ndarray | None = None,
        *,
        sectors: Sectors,
        noise_lattice: Lattice | None = None,
    ) -> SectorEvidence:
        """The increment of ``(X, V)``: each observation in the class of its velocity."""
        label = sectors.classify(V)
        rows = (X, V, input_noise_std, sample_weight)
        parts = []
        for c in range(sectors.classes):
            part = rows if sectors.classes == 1 else take_rows(rows, np.flatnonzero(label == c))
            parts.append(
                Evidence.from_points(
                    grid, kernel, *part, noise_lattice=noise_lattice, mass=sectors.classes > 1
                )
            )
        return cls(tuple(parts))

    @property
    def count(self) -> float:
        return float(sum(e.count for e in self.classes))

    def total(self) -> Evidence:
        """Every class together: the evidence of the map with one class."""
        out = self.classes[0]
        for e in self.classes[1:]:
            out = out + e
        return out

    def _zip(self, other: SectorEvidence):
        if len(self.classes) != len(other.classes):
            raise ValueError(f"cannot add evidence of {len(self.classes)} and {len(other.classes)} classes")
        return zip(self.classes, other.classes, strict=True)

    def _speeds(self, other: SectorEvidence, sign: float) -> np.ndarray | None:
        """The histograms' sum, or None where either is unknown (a tile stored before them)."""
        if self.speeds is None or other.speeds is None:
            return None
        return self.speeds + sign * other.speeds

    def __add__(self, other: SectorEvidence) -> SectorEvidence:
        return SectorEvidence(tuple(a + b for a, b in self._zip(other)), self._speeds(other, 1.0))

    def __sub__(self, other: SectorEvidence) -> SectorEvidence:
        return SectorEvidence(tuple(a - b for a, b in self._zip(other)), self._speeds(other, -1.0))

    def accumulated(
        self, residual: SectorEvidence, increment: SectorEvidence
    ) -> tuple[SectorEvidence, SectorEvidence]:
        """``self + residual + increment`` as a new (sum, residual) (:func:`compensated_sum`)."""
        if not len(self.classes) == len(residual.classes) == len(increment.classes):
            raise ValueError(
                f"cannot add evidence of {len(self.classes)} and {len(increment.classes)} classes"
            )
        classes = zip(self.classes, residual.classes, increment.classes, strict=True)
        pairs = [a.accumulated(r, b) for a, r, b in classes]
        speeds = (None, None)
        if self.speeds is not None and increment.speeds is not None:
            lo = np.zeros_like(self.speeds) if residual.speeds is None else residual.speeds
            speeds = _accumulated(self.speeds, lo, increment.speeds)
        return (
            SectorEvidence(tuple(p[0] for p in pairs), speeds[0]),
            SectorEvidence(tuple(p[1] for p in pairs), speeds[1]),
        )

    def scaled(self, factor: float) -> SectorEvidence:
        speeds = None if self.speeds is None else self.speeds * factor
        return SectorEvidence(tuple(e.scaled(factor) for e in self.classes), speeds)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays, ``"{class}_{name}"``."""
        return {f"{c}_{k}": v for c, e in enumerate(self.classes) for k, v in e.to_arrays().items()}

    @classmethod
    def from_arrays(cls, arrays, grid, stencil, noise_lattice, sectors: Sectors) -> SectorEvidence:
        parts = []
        for c in range(sectors.classes):
            mine = {k.removeprefix(f"{c}_"): v for k, v in arrays.items() if k.startswith(f"{c}_")}
            parts.append(Evidence.from_arrays(mine, grid, stencil, noise_lattice))
        if any(
            not k.split("_", 1)[0].isdigit() or int(k.split("_", 1)[0]) >= sectors.classes for k in arrays
        ):
            raise ValueError(f"evidence arrays of more than {sectors.classes} classes")
        return cls(tuple(parts))

    def to_bytes(self) -> bytes:
        """The speed histogram after its length (int64, in values); then one class: its
        blob; several: each blob after its length."""
        speeds = np.zeros(0) if self.speeds is None else self.speeds.ravel()
        out = [np.array([len(speeds)], "<i8").tobytes(), speeds.astype("<f8").tobytes()]
        if len(self.classes) == 1:
            return b"".join([*out, self.classes[0].to_bytes()])
        for e in self.classes:
            blob = e.to_bytes()
            out += [np.array([len(blob) // 8], "<i8").tobytes(), blob]
        return b"".join(out)

    @classmethod
    def from_bytes(
        cls,
        blob: bytes,
        grid: HingeGrid,
        stencil: sparse.Stencil,
        noise_lattice: Lattice | None,
        sectors: Sectors,
        format_version: int = FORMAT_VERSION,
    ) -> SectorEvidence:
        speeds = None
        if format_version >= 4:
            n = int(np.frombuffer(blob[:8], "<i8")[0]) if len(blob) >= 8 else -1
            if n < 0 or 8 + 8 * n > len(blob) or n not in (0, altitude_bins(grid)[1] * SPEED_BINS):
                raise ValueError(f"an evidence blob of {len(blob)} bytes has no speed histogram of its grid")
            if n:
                speeds = np.frombuffer(blob[8 : 8 + 8 * n], "<f8").astype(np.float64).reshape(-1, SPEED_BINS)
            blob = blob[8 + 8 * n :]
        if sectors.classes == 1:
            return cls((Evidence.from_bytes(blob, grid, stencil, noise_lattice, format_version),), speeds)
        if format_version < 3:
            raise ValueError(f"statistics format {format_version} holds one class, not {sectors.classes}")
        parts, at = [], 0
        for _ in range(sectors.classes):
            if at + 8 > len(blob):
                raise ValueError(f"an evidence blob of {len(blob)} bytes ends before class {len(parts)}")
            n = int(np.frombuffer(blob[at : at + 8], "<i8")[0])
            if n < 0 or at + 8 + 8 * n > len(blob):
                raise ValueError(f"an evidence blob of {len(blob)} bytes is cut in class {len(parts)}")
            parts.append(Evidence.from_bytes(blob[at + 8 : at + 8 + 8 * n], grid, stencil, noise_lattice))
            at += 8 + 8 * n
        if at != len(blob):
            raise ValueError(
                f"an evidence blob has {len(blob) - at} bytes after its {sectors.classes} classes"
            )
        return cls(tuple(parts), speeds)


def _accumulated(hi, lo, inc) -> tuple[np.ndarray, np.ndarray]:
    """``hi + lo + inc`` (same shapes) as a new ``(hi, lo)``: one compiled pass."""
    shape = np.shape(hi)
    flat = [np.ascontiguousarray(a, dtype=float).reshape(-1) for a in (hi, lo, inc)]
    out_hi, out_lo = np.empty_like(flat[0]), np.empty_like(flat[0])
    _accumulate(*flat, out_hi, out_lo)
    return out_hi.reshape(shape), out_lo.reshape(shape)


@numba.njit(cache=True, nogil=True)
def _accumulate(hi, lo, inc, out_hi, out_lo):  # pragma: no cover (compiled)
    """Per value: ``s + e = hi + inc`` exactly (Knuth's TwoSum), ``e += lo``, then ``s + e``
    renormalised the same way (strict IEEE: numba does not reassociate without fastmath)."""
    for i in range(hi.shape[0]):
        a, b = hi[i], inc[i]
        s = a + b
        v = s - a
        e = (a - (s - v)) + (b - v) + lo[i]
        t = s + e
        w = t - s
        out_lo[i] = (s - (t - w)) + (e - w)
        out_hi[i] = t


def compensated_sum(
    total: SectorEvidence, residual: SectorEvidence | None, increment: SectorEvidence
) -> tuple[SectorEvidence, SectorEvidence]:
    """``total + residual + increment`` as a new ``(total, residual)``: a sum kept to about
    twice float64's precision (double-double; ``residual`` None: zero). Adding an increment
    and later subtracting the same one returns the statistics before it to float64's
    precision of *them*, however much larger the increment was (a retraction)."""
    return total.accumulated(total.scaled(0.0) if residual is None else residual, increment)
