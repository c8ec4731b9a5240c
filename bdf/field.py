"""BayesianDynamicField: exact Bayesian linear regression on local RBF features (paper III-A..E)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bdf import noise, sparse
from bdf.grid import HingeGrid, noise_lattice
from bdf.kernel import DEFAULT_CUTOFF, Kernel
from bdf.posterior import Mixture, Modes, Posterior
from bdf.sectors import Sectors
from bdf.statistics import FORMAT_VERSION, SectorEvidence
from bdf.validation import (
    as_headings,
    as_hyper,
    as_noise_std,
    as_observations,
    as_points,
    as_positive,
    as_sample_weight,
    as_vector3,
)


class BayesianDynamicField:
    """A 3D velocity field with calibrated uncertainty: exact Bayesian linear regression
    on squared-exponential features centred on a regular hinge grid.

    Parameters
    ----------
    lower, upper : 3 numbers
        Box of the hinge grid (metres in the map layer). Hinges are ``lower + i * spacing``
        per axis up to ``upper`` inclusive.
    spacing : number or 3 numbers
        Hinge spacing per axis.
    gamma : number or 3 numbers
        Inverse squared bandwidth per axis: kernel ``exp(-sum_d gamma_d (x_d - h_d)^2)``.
    alpha : "auto", number, 3 numbers or (1 + classes, 3)
        Prior precision of the weights (prior ``N(0, alpha^-1 I)``). "auto" fits it by
        evidence maximisation. A directional field takes a row per class after the row of
        the map with one class (:class:`bdf.posterior.Mixture`).
    beta : "auto", number, 3 numbers or (1 + classes, 3)
        Noise precision per velocity component. "auto" fits one per component.
    cutoff : float
        Kernel cutoff: per-axis Gaussian factors below it are dropped (see :mod:`bdf.features`).
    half_life : float or None
        Exponential forgetting: before each :meth:`partial_fit`, old evidence is weighted
        by ``0.5 ** ((time - previous_time) / half_life)``. None keeps everything.
    noise_spacing : None, number or 3 numbers
        None: the noise variance is ``1/beta`` everywhere (the paper's model). A spacing:
        it is local, the data's mean squared residual smoothed at about this scale and
        shrunk towards ``1/beta`` (:mod:`bdf.noise`); the mean is unchanged. Finer than the
        hinge spacing (Paris: 1 km x 1 km x 125 m under 4 km x 4 km x 1 km hinges).
    noise_prior : float
        With ``noise_spacing``: the weight of ``1/beta`` in the local estimate, in units of
        sample weight (the data near a point outweigh it once they weigh more).
    directions : int
        1 (the paper's model) or S in 2-32: a mixture over S horizontal heading sectors
        and a slow class, with a share field (:mod:`bdf.sectors`).
    slow_mps : float
        With ``directions > 1``: horizontal speeds below it form the slow class.

    Attributes
    ----------
    evidence_ : Evidence
        The additive statistics of everything learned (decayed when forgetting).
    alpha_, beta_ : ndarray (3,)
        Hyperparameters in use per component (the fitted values when "auto").
    log_evidence_ : ndarray (3,)
        Log marginal likelihood per component at ``alpha_``, ``beta_``.
    weights_ : ndarray (M, 3)
        Posterior mean of the weights.
    time_ : float
        Time of the last update (forgetting).

    Notes
    -----
    The three components share the features and hence ``Phi^T Phi``; with a shared ratio
    ``alpha / beta`` they share one Cholesky factorisation. The posterior is computed
    lazily after each update and the variance only when a std is asked for.

    Examples
    --------
    >>> f = BayesianDynamicField([0, 0, 0], [10, 10, 10], 2.0, 0.3).fit(X, V)  # doctest: +SKIP
    >>> mean, std = f.predict(Xq, return_std=True)                              # doctest: +SKIP
    """

    def __init__(
        self,
        lower,
        upper,
        spacing,
        gamma,
        alpha=1e-2,
        beta=1e2,
        *,
        cutoff=DEFAULT_CUTOFF,
        half_life=None,
        noise_spacing=None,
        noise_prior=0.1,
        directions=1,
        slow_mps=5.0,
    ):
        self.lower = lower
        self.upper = upper
        self.spacing = spacing
        self.gamma = gamma
        self.alpha = alpha
        self.beta = beta
        self.cutoff = cutoff
        self.half_life = half_life
        self.noise_spacing = noise_spacing
        self.noise_prior = noise_prior
        self.directions = directions
        self.slow_mps = slow_mps

    def get_params(self, deep=True) -> dict:
        """Constructor arguments as given (scikit-learn convention)."""
        return {k: getattr(self, k) for k in _PARAMS}

    # -- configuration -------------------------------------------------------------------
    def _setup(self):
        """Validate the constructor arguments (scikit-learn style: at fit, not in __init__)."""
        grid = HingeGrid(self.lower, self.upper, self.spacing)
        gamma = as_vector3(self.gamma, "gamma", positive=True)
        self._sectors = Sectors(self.directions, float(self.slow_mps))
        rows = 1 if self._sectors.classes == 1 else 1 + self._sectors.classes
        alpha, beta = as_hyper(self.alpha, "alpha", rows), as_hyper(self.beta, "beta", rows)
        if not 0 < float(self.cutoff) < 1:
            raise ValueError(f"cutoff must be in (0, 1), got {self.cutoff!r}")
        if self.half_life is not None and not float(self.half_life) > 0:
            raise ValueError(f"half_life must be positive or None, got {self.half_life!r}")
        lattice = None
        if self.noise_spacing is not None:
            lattice = noise_lattice(self.lower, self.upper, self.noise_spacing)
            as_positive(self.noise_prior, "noise_prior")
        return grid, Kernel(tuple(gamma), float(self.cutoff)), alpha, beta, lattice

    @property
    def hinges(self) -> np.ndarray:
        """(M, 3) hinge coordinates, first axis slowest."""
        return HingeGrid(self.lower, self.upper, self.spacing).points()

    # -- learning --------------------------------------------------------------------------
    def fit(self, X, V, *, input_noise_std=None, sample_weight=None, time=None):
        """Learn from ``(X, V)`` only, replacing what was learned. Returns self."""
        self._grid, self._kernel, self._alpha, self._beta, self._noise_lattice = self._setup()
        self.evidence_ = SectorEvidence.zeros(self._grid, self._noise_lattice, self._sectors)
        self.time_ = None
        return self.partial_fit(X, V, input_noise_std=input_noise_std, sample_weight=sample_weight, time=time)

    def partial_fit(self, X, V, *, input_noise_std=None, sample_weight=None, time=None):
        """Add evidence: the posterior of the data so far is the prior of ``(X, V)``.

        Any split and order of the data gives the same result as one :meth:`fit`.

        Parameters
        ----------
        X, V : (N, 3)
            Positions and velocities.
        input_noise_std : None, number, (N,) or (N, 3)
            Std of Gaussian noise on the positions; such points use the expected kernel.
        sample_weight : None or (N,)
            Likelihood weight per point (>= 0). Correlated samples (ADS-B at 1 Hz along one
            track) should share one unit of weight, or the evidence overfits:
            see :func:`bdf.ingest.track_weights`.
        time : float, optional
            Time of this batch, in the units of ``half_life`` (forgetting only); defaults to
            the previous time plus one.
        """
        if not hasattr(self, "evidence_"):
            return self.fit(X, V, input_noise_std=input_noise_std, sample_weight=sample_weight, time=time)
        X, V = as_observations(X, V)
        input_noise = as_noise_std(input_noise_std, len(X))
        weight = as_sample_weight(sample_weight, len(X))
        time = self._advance(time)
        self._warm_start()
        self.evidence_ = self.evidence_ + SectorEvidence.from_points(
            self._grid,
            self._kernel,
            X,
            V,
            input_noise,
            weight,
            sectors=self._sectors,
            noise_lattice=self._noise_lattice,
        )
        self._posterior = None
        return self

    def _advance(self, time):
        """Decay the evidence to ``time`` (forgetting) and return the new time."""
        previous = self.time_
        if time is None:
            time = 0.0 if previous is None else previous + 1.0
        time = float(time)
        if not np.isfinite(time):
            raise ValueError(f"time must be finite, got {time}")
        if previous is not None:
            if time < previous:
                raise ValueError(f"time {time} is before the previous update at {previous}")
            if self.half_life is not None:
                self.evidence_ = self.evidence_.scaled(0.5 ** ((time - previous) / self.half_life))
        self.time_ = time
        return time

    # -- the posterior -----------------------------------------------------------------------
    @property
    def posterior_(self) -> Posterior | Mixture:
        if not hasattr(self, "evidence_"):
            raise ValueError("this field has not been fitted: call fit(X, V) first")
        if getattr(self, "_posterior", None) is None:
            model = (self._grid, self._kernel)
            rest = (self._noise_lattice, float(self.noise_prior))
            start, settle = getattr(self, "_start", None), getattr(self, "_settle", True)
            if self._sectors.classes == 1:
                (evidence,) = self.evidence_.classes
                self._posterior = Posterior(
                    *model, evidence, self._alpha, self._beta, *rest, start=start, settle=settle
                )
            else:
                self._posterior = Mixture(
                    *model, self.evidence_, self._alpha, self._beta, *rest, self._sectors, start, settle
                )
        return self._posterior

    def _warm_start(self) -> None:
        """Before the evidence changes: the next "auto" search starts at the current
        optimum (the same optimum, found in fewer factorisations than from nowhere)."""
        post = getattr(self, "_posterior", None)
        if post is not None and post.fitted:
            self._start, self._settle = post.next_start, True

    @property
    def alpha_(self) -> np.ndarray:
        return self.posterior_.alpha

    @property
    def beta_(self) -> np.ndarray:
        return self.posterior_.beta

    @property
    def log_evidence_(self) -> np.ndarray:
        return self.posterior_.log_evidence

    @property
    def weights_(self) -> np.ndarray:
        return self.posterior_.weights

    def predict(self, X, return_std=False, *, include_noise=True, heading_deg=None):
        """Predictive mean, and std if asked, at positions ``X`` (n, 3).

        Parameters
        ----------
        return_std : bool
            Also return the std (n, 3). Only then is any variance computed.
        include_noise : bool
            True: predictive std ``sqrt(1/beta + phi^T Sigma phi)`` (what a new
            observation would scatter by; local with ``noise_spacing``). False: epistemic
            std ``sqrt(phi^T Sigma phi)`` (the uncertainty of the mean field itself).
        heading_deg : None, number or (n,)
            None: a directional field answers its mixture's mean and std. A heading
            (degrees from north, clockwise): the mode of traffic flying it (the two
            nearest sectors' modes pooled, their noise narrowed by the heading:
            :func:`bdf.sectors.heading_mode`).
            A field of one direction has one mode.
        """
        X = as_points(X, "X", allow_empty=True)
        if heading_deg is None:
            return self.posterior_.predict(X, return_std, include_noise)
        modes = self.posterior_.predict_modes(X, include_noise)
        mean, std = modes.answer(self._sectors, as_headings(heading_deg, len(X)))
        return (mean, std) if return_std else mean

    def predict_modes(self, X, *, include_noise=True) -> Modes:
        """Per traffic class (the heading sectors, then the slow class; one class for a
        field of one direction) at ``X`` (n, 3): ``share`` (n, C), ``share_std`` (n,),
        ``mean`` and ``std`` (n, C, 3). See :class:`bdf.posterior.Modes`."""
        return self.posterior_.predict_modes(as_points(X, "X", allow_empty=True), include_noise)

    @property
    def heading_deg_(self) -> np.ndarray:
        """The centre heading of each sector (degrees from north, clockwise)."""
        return Sectors(self.directions, float(self.slow_mps)).centres_deg

    # -- persistence -----------------------------------------------------------------------
    def save(self, path) -> None:
        """Write parameters and evidence to an ``.npz`` file (versioned format)."""
        if not hasattr(self, "evidence_"):
            raise ValueError("nothing to save: the field has not been fitted")
        params = {k: _jsonable(v) for k, v in self.get_params().items()}
        params["time_"] = self.time_
        with open(path, "wb") as fh:  # np.savez would append .npz to a bare name
            np.savez(
                fh,
                format_version=FORMAT_VERSION,
                params=json.dumps(params),
                **{f"evidence_{k}": v for k, v in self.evidence_.to_arrays().items()},
            )

    @classmethod
    def load(cls, path) -> BayesianDynamicField:
        path = Path(path)
        with np.load(path, allow_pickle=False) as data:
            version = int(data["format_version"]) if "format_version" in data else None
            if version not in (3, FORMAT_VERSION):  # 4 changed only the stored tiles' blobs
                raise ValueError(
                    f"{path}: format version {version}, this library reads 3 and {FORMAT_VERSION}"
                )
            params = json.loads(str(data["params"]))
            arrays = {k.removeprefix("evidence_"): data[k] for k in data.files if k.startswith("evidence_")}
        time = params.pop("time_")
        field = cls(**params)
        grid, kernel, _, _, lattice = field._setup()
        stencil = sparse.stencil_on(grid, kernel)
        evidence = SectorEvidence.from_arrays(arrays, grid, stencil, lattice, field._sectors)
        return field.set_evidence(evidence, time)

    def set_evidence(
        self, evidence: SectorEvidence, time=None, start=None, settle=True
    ) -> BayesianDynamicField:
        """Take ``evidence`` (made on this field's grid, e.g. stored per tile) as everything
        learned. ``start``: ratios alpha / beta where the "auto" search starts ((3,), or a
        row per class of a directional field: an optimum found on earlier evidence); the
        optimum is the same from any start. ``settle=False``: a search from ``start`` may
        stop within a nat of the optimum (:func:`bdf.hyperparameters.fit_evidence`; the
        posterior's ``settled`` says whether it did). Returns self."""
        self._start, self._settle = start, settle
        self._grid, self._kernel, self._alpha, self._beta, self._noise_lattice = self._setup()
        if len(evidence.classes) != self._sectors.classes:
            raise ValueError(
                f"evidence of {len(evidence.classes)} classes given to a field of {self._sectors.classes}"
            )
        lattice = self._noise_lattice
        expected = None if lattice is None else (*lattice.shape, noise.CHANNELS)
        for part in evidence.classes:
            if part.proj.shape != (self._grid.size, 3):
                raise ValueError(
                    f"evidence for {len(part.proj)} hinges given to a field of {self._grid.size}"
                )
            if (None if part.moments is None else part.moments.shape) != expected:
                raise ValueError(
                    f"evidence moments do not fit this field's noise_spacing (expected {expected})"
                )
        self.evidence_ = evidence
        self.time_ = time
        self._posterior = None
        return self


_PARAMS = (
    "lower",
    "upper",
    "spacing",
    "gamma",
    "alpha",
    "beta",
    "cutoff",
    "half_life",
    "noise_spacing",
    "noise_prior",
    "directions",
    "slow_mps",
)


def _jsonable(value):
    if isinstance(value, str | type(None) | int):
        return value
    return np.asarray(value, float).tolist()
