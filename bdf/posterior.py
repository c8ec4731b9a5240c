"""The posterior of a field: what a factorisation of its evidence gives (paper III-A..E)."""

from __future__ import annotations

import numpy as np

from bdf import features, linalg, noise, tuning
from bdf.grid import HingeGrid
from bdf.stats import MIDPOINT_BLOCK, Evidence, stencil_of


class Posterior:
    """What a factorisation of the evidence gives: weights now, the variance density on demand.

    Derived data only (tiles cache these per version); the evidence is the source of truth.
    With ``noise_lattice`` (and the evidence's moments), the noise term of the predictive
    variance is local (:mod:`bdf.noise`) with prior weight ``noise_prior``.
    """

    def __init__(
        self,
        grid: HingeGrid,
        gamma,
        evidence: Evidence,
        alpha,
        beta,
        cutoff,
        noise_lattice=None,
        noise_prior=None,
    ):
        self.grid, self.gamma, self.cutoff = grid, gamma, cutoff
        self.noise_lattice, self.noise_prior, self._moments = noise_lattice, noise_prior, evidence.moments
        self.stencil = stencil_of(grid, gamma, cutoff)
        #: alpha or beta came from evidence maximisation ("auto" and some data)
        self.fitted = (isinstance(alpha, str) or isinstance(beta, str)) and evidence.count > 0
        self.alpha, self.beta, sols = tuning.fit_evidence(
            self.stencil,
            evidence.gram_band(self.stencil),
            evidence.proj,
            evidence.v_sq,
            evidence.count,
            alpha,
            beta,
        )
        self.log_evidence = np.array(
            [tuning.log_evidence(s, self.alpha, self.beta, evidence.count)[c] for c, s in enumerate(sols)]
        )
        self.weights = np.stack([s.weights[:, c] for c, s in enumerate(sols)], axis=1)
        self._solutions = sols
        self._variance = None

    def mean(self, X: np.ndarray) -> np.ndarray:
        T = self.weights.reshape(*self.grid.shape, 3)
        return features.gather(self.grid, X, T, self.gamma, cutoff=self.cutoff)

    def epistemic_variance(self, X: np.ndarray) -> np.ndarray:
        """``phi(x)^T Sigma_c phi(x)`` per component, (N, 3), via the variance density."""
        if self._variance is None:
            self._variance = self._variance_density()
        densities, columns = self._variance
        var = features.gather(
            self.grid.midpoints(),
            X,
            densities,
            2.0 * self.gamma,
            cutoff=self.cutoff,
            block=MIDPOINT_BLOCK,
        )
        return np.maximum(var[:, columns] / self.beta, 0.0)

    def predict_grid(self, axes) -> tuple[np.ndarray, np.ndarray]:
        """Mean and predictive variance (noise included) on the grid ``axes`` (three 1-D
        arrays), each (nx, ny, nz, 3); separable, see :func:`features.gather_grid`."""
        if self._variance is None:
            self._variance = self._variance_density()
        densities, columns = self._variance
        mean = features.gather_grid(
            self.grid, axes, self.weights.reshape(*self.grid.shape, 3), self.gamma, cutoff=self.cutoff
        )
        var = features.gather_grid(
            self.grid.midpoints(), axes, densities, 2.0 * self.gamma, cutoff=self.cutoff
        )[..., columns]
        if self._moments is None:
            scatter = 1.0 / self.beta
        else:
            scatter = noise.noise_variance_grid(
                self.noise_lattice, self._moments, axes, mean, self.beta, self.noise_prior
            )
        return mean, np.maximum(var / self.beta, 0.0) + scatter

    def noise_variance(self, X: np.ndarray, mean: np.ndarray) -> np.ndarray:
        """The noise term of the predictive variance at ``X`` (n, 3): ``1/beta``, or the
        local estimate of :mod:`bdf.noise` where the posterior mean is ``mean``."""
        if self._moments is None:
            return np.broadcast_to(1.0 / self.beta, mean.shape)
        return noise.noise_variance(self.noise_lattice, self._moments, X, mean, self.beta, self.noise_prior)

    def predict(self, X: np.ndarray, return_std=False, include_noise=True):
        """Mean (N, 3), and the std if asked: predictive, or epistemic without ``1/beta``."""
        mean = self.mean(X)
        if not return_std:
            return mean
        var = self.epistemic_variance(X)
        if include_noise:
            var = var + self.noise_variance(X, mean)
        return mean, np.sqrt(var)

    def compact(self) -> Posterior:
        """Compute the variance density and the gather tables now and drop the factors:
        what a cache keeps (a few times the midpoint lattice)."""
        if self._variance is None:
            self._variance = self._variance_density()
        self._solutions = None
        return self

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays of this posterior."""
        held = self.weights.nbytes + (0 if self._moments is None else self._moments.nbytes)
        if self._variance is not None:
            held += self._variance[0].nbytes
        if self._solutions is not None:
            held += sum(12 * s.factor.nnz for s in {id(s): s for s in self._solutions}.values())
        return held

    def _variance_density(self):
        # Sigma_c = (G + lam I)^-1 / beta_c on the stencil (selected inversion); one
        # density per distinct factorisation
        densities, columns = {}, []
        for sol in self._solutions:
            if id(sol) not in densities:
                inverse = sol.factor.inverse_band()
                densities[id(sol)] = linalg.band_density(self.stencil, inverse, self.grid.midpoints())
            columns.append(list(densities).index(id(sol)))
        return np.stack(list(densities.values()), axis=-1), columns
