"""A region's map: the posterior of its one field, queried at points and on grids.

:func:`compute_posterior` turns the region's evidence (:mod:`bdf.region.evidence`) into
the posterior at the spec's hyperparameters: fixed, or ("auto") the evidence maximum of
the data in force, its search started at the previous version's optimum.
:class:`RegionMap` answers queries from it: predictive mean and std, the modes of a
directional map, and ``known``.

Where the region has no data the field reverts to its prior, whose predictive variance
under "auto" is set by the region's evidence (on the scale of its velocities). ``known``
marks the points where the data within the kernel's reach weigh at least
:data:`bdf.posterior.KNOWN_WEIGHT` (their own density,
:meth:`bdf.posterior.Posterior.data_weight`, not the boxes of the tiles that hold them);
per class, the same says where a mode is only its prior.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from bdf.posterior import Mixture, Modes, Posterior, known
from bdf.region.spec import RegionSpec
from bdf.sparse import NotPositiveDefinite
from bdf.statistics import SectorEvidence
from bdf.validation import as_headings

log = logging.getLogger(__name__)


def compute_posterior(
    spec: RegionSpec, evidence: SectorEvidence, start=None, *, stored: bool = True, settle: bool = True
) -> Posterior | Mixture:
    """The region's posterior of ``evidence`` (:func:`bdf.region.evidence.region_total`) at the spec's
    hyperparameters, variance density ready, factors dropped. "auto" is this
    evidence's maximum (``posterior.alpha``, ``posterior.beta``), its search started at
    ``start`` (ratios alpha / beta, (3,) or a row per class: the optimum of the
    region's previous version) and the same from any start; ``settle=False``: within a nat
    of it, where that is quicker (:func:`bdf.hyperparameters.fit_evidence`).

    Fixed values that do not factor on ``stored`` data (which must be served) are
    raised (alpha by powers of ten) to the least that factors, with a warning; on data
    not stored yet (a fit, before it is applied) they raise ``NotPositiveDefinite``."""
    try:
        return spec.field().set_evidence(evidence, start=start, settle=settle).posterior_.compact()
    except NotPositiveDefinite:
        if spec.alpha == "auto" or not stored:
            raise
    # the spec's fixed alpha does not factor on stored (accepted) data, which must still
    # be served: at the least alpha ten times larger, a hundred, ... that does
    for power in range(1, 13):
        try:
            field = spec.field(np.asarray(spec.alpha, float) * 10.0**power)
            post = field.set_evidence(evidence, start=start, settle=settle).posterior_.compact()
        except NotPositiveDefinite:
            continue
        log.warning("region %s: served at alpha x 1e%d: its fixed alpha does not factor", spec.name, power)
        return post
    raise NotPositiveDefinite(f"region {spec.name}: no alpha up to 1e12 times the spec's factors")


@dataclass(frozen=True)
class RegionMap:
    """A region's posterior (:func:`compute_posterior`) with the spec it answers for:
    points and grids are checked against the region once, here."""

    spec: RegionSpec
    posterior: Posterior | Mixture

    def predict(
        self, X, heading_deg=None, modes: Modes | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predictive mean (n, 3), std (n, 3) and ``known`` (n,) at ``X`` inside the region,
        from the region's posterior. ``heading_deg`` (one or (n,)): the mode of that
        heading (a region of one direction has one). ``modes``: :meth:`predict_modes` of
        the same points when the caller has them (the answer derives from them)."""
        X = self.spec.inside_points(X)
        if heading_deg is not None:
            heading_deg = as_headings(heading_deg, len(X))
        if modes is None and self.spec.directions == 1:
            mean, std, weight = self.posterior.answer(X)
        else:
            modes = self.posterior.predict_modes(X) if modes is None else modes
            mean, std = modes.answer(self.spec.sectors, heading_deg)
            weight = modes.weight
        return mean, std, known(weight)

    def predict_modes(self, X) -> Modes:
        """:class:`~bdf.posterior.Modes` at ``X`` inside the region."""
        return self.posterior.predict_modes(self.spec.inside_points(X))

    def predict_grid(self, axes, modes: Modes | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`predict` on the grid ``axes[0] x axes[1] x axes[2]`` (inside the region):
        mean and std (nx, ny, nz, 3), known (nx, ny, nz); separable, so a few small
        contractions per axis. ``modes``: :meth:`predict_grid_modes` of the same grid when
        the caller has them (the answer derives from them)."""
        axes = self.spec.grid_axes(axes)
        if modes is None:
            mean, var = self.posterior.predict_grid(axes)
            std = np.sqrt(var)
            weight = self.posterior.data_weight_grid(axes)
        else:
            mean, std = modes.answer(self.spec.sectors)
            weight = modes.weight
        return mean, std, known(weight)

    def predict_grid_modes(self, axes) -> Modes:
        """:class:`~bdf.posterior.Modes` on the grid ``axes``, the grid's shape first."""
        return self.posterior.predict_grid_modes(self.spec.grid_axes(axes))
