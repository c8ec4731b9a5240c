"""Regular lattices: the hinge grid of a field and its half-spacing midpoint grid."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bdf.validation import as_vector3

#: Largest hinge count a field accepts: its sparse factor grows about as M^(4/3) on a 3-D
#: lattice (``bench/bench_tiles.py`` measures it).
MAX_HINGES = 250_000
#: Largest noise lattice (:mod:`bdf.noise`: 7 float64 channels per point, 56 bytes each).
MAX_NOISE_CELLS = 2_000_000


def axis_counts(lower, upper, step) -> np.ndarray:
    """Points ``lower + i * step`` up to ``upper`` inclusive, per axis, as floats: a tiny
    step counts as infinitely many, never as an overflowed integer, so callers check their
    limit before they allocate anything."""
    with np.errstate(over="ignore"):
        return np.floor((np.asarray(upper) - lower) / step + 1e-9) + 1


def bounded_counts(lower, upper, step, limit: float, what: str, unit: str, advice: str) -> np.ndarray:
    """:func:`axis_counts`, refused with a ``ValueError`` where their product exceeds
    ``limit``: ``what`` names the lattice, ``unit`` its points, ``advice`` what to change."""
    counts = axis_counts(lower, upper, step)
    size = float(np.prod(counts))
    if not size <= limit:
        raise ValueError(
            f"{what} would have {size:.6g} {unit} ({counts.tolist()} per axis), "
            f"more than {limit:.12g}; {advice}"
        )
    return counts


@dataclass(frozen=True)
class Lattice:
    """Points ``origin + i * step`` for ``i`` in ``[0, shape)`` per axis, in C order."""

    origin: np.ndarray
    step: np.ndarray
    shape: tuple[int, int, int]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def axis(self, d: int) -> np.ndarray:
        return self.origin[d] + self.step[d] * np.arange(self.shape[d])

    def points(self) -> np.ndarray:
        """All lattice points, (size, 3), first axis slowest."""
        mesh = np.meshgrid(*(self.axis(d) for d in range(3)), indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)


class HingeGrid(Lattice):
    """Hinges ``lower + i * spacing`` per axis, up to ``upper`` inclusive.

    The midpoints of all hinge pairs lie on the half-spacing lattice returned by
    :meth:`midpoints`; hinges ``(i, j, k)`` and ``(i', j', k')`` have their midpoint at
    index ``(i + i', j + j', k + k')`` there, which is what makes the Gram identity and
    the variance identity of :mod:`bdf.statistics` cheap.
    """

    def __init__(self, lower, upper, spacing):
        lower = as_vector3(lower, "lower")
        upper = as_vector3(upper, "upper")
        spacing = as_vector3(spacing, "spacing", positive=True)
        if np.any(upper <= lower):
            raise ValueError(f"upper {upper.tolist()} must exceed lower {lower.tolist()} on every axis")
        counts = bounded_counts(lower, upper, spacing, MAX_HINGES, "the grid", "hinges", "increase spacing")
        super().__init__(lower, spacing, tuple(int(c) for c in counts))

    def midpoints(self) -> Lattice:
        return Lattice(self.origin, self.step / 2.0, tuple(2 * n - 1 for n in self.shape))


def noise_lattice(lower, upper, spacing) -> Lattice:
    """The local-noise lattice (:mod:`bdf.noise`): ``lower + i * spacing`` per axis covering
    ``[lower, upper]``."""
    lower, upper = as_vector3(lower, "lower"), as_vector3(upper, "upper")
    step = as_vector3(spacing, "noise_spacing", positive=True)
    counts = bounded_counts(
        lower, upper, step, MAX_NOISE_CELLS, "the noise lattice", "points", "increase noise_spacing"
    )
    return Lattice(lower, step, tuple(int(n) for n in counts))
