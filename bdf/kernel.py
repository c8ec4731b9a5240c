"""The features' kernel: a separable squared exponential, cut where it falls below a cutoff.

A hinge's feature is ``exp(-sum_d gamma_d (x_d - h_d)^2)``; every sum over lattice points
drops the per-axis factors below ``cutoff`` (:mod:`bdf.features`), so each point reaches
the lattice points within the :func:`window` of its axis, and two hinges couple in the
precision where their ``c(o) = exp(-sum_d gamma_d o_d^2 / 2)`` is at least the cutoff
(:meth:`Kernel.couplings`, the precision's stencil, :mod:`bdf.sparse.stencil`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_CUTOFF = 1e-12
#: Kernel cutoff of the local-noise moments (:mod:`bdf.noise`): they feed a smoothed
#: estimate, not the exact posterior, and terms below 1e-6 of the largest change it by about
#: that fraction (at a third of the cost of the exact features' 1e-12).
NOISE_CUTOFF = 1e-6


def window(k, cutoff: float) -> np.ndarray:
    """How far a Gaussian ``exp(-k d^2)`` stays above ``cutoff``: the half-width of its window
    (per axis, as ``k``; in the units of ``1 / sqrt(k)``)."""
    with np.errstate(over="ignore", divide="ignore"):
        return np.sqrt(np.log(1.0 / cutoff) / np.asarray(k, float))


@dataclass(frozen=True)
class Kernel:
    """``gamma`` (1/m^2 per axis, the paper's inverse squared bandwidth) and ``cutoff``.
    Hashable: stencils are cached per lattice and kernel."""

    gamma: tuple[float, float, float]
    cutoff: float = DEFAULT_CUTOFF

    def __post_init__(self):
        gamma = np.broadcast_to(np.asarray(self.gamma, float), (3,))
        object.__setattr__(self, "gamma", tuple(float(g) for g in gamma))
        object.__setattr__(self, "cutoff", float(self.cutoff))

    @property
    def reach_m(self) -> np.ndarray:
        """Per axis, how far a hinge's feature reaches above the cutoff (metres)."""
        return window(np.array(self.gamma), self.cutoff)

    def couplings(self, step, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """On a lattice of ``step`` (metres) and ``shape``: the hinge offsets ``o`` whose
        coupling ``c(o)`` is at least the cutoff, the half kept in bands (lexicographically
        >= 0, zero first), their ``c(o)``, and the reach per axis in hinge steps."""
        steps = np.array(self.gamma) * np.asarray(step, float) ** 2 / 2.0  # exponent per squared step
        reach = np.minimum(np.floor(window(steps, self.cutoff)).astype(int), np.array(shape) - 1)
        axes = [np.arange(-r, r + 1) for r in reach]
        o = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        o = o[(o**2 @ steps) <= np.log(1.0 / self.cutoff)]
        half = (o[:, 0] > 0) | ((o[:, 0] == 0) & ((o[:, 1] > 0) | ((o[:, 1] == 0) & (o[:, 2] >= 0))))
        o = o[half]
        offsets = o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]
        return offsets, np.exp(-(offsets**2 @ steps)), reach
