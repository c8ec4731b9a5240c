"""Accuracy and calibration metrics, per velocity component (columns) or over all values."""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp
from scipy.stats import norm


def _check(*arrays):
    shapes = {np.shape(a) for a in arrays}
    if len(shapes) != 1:
        raise ValueError(f"metric inputs must have the same shape, got {sorted(shapes)}")
    return [np.asarray(a, float) for a in arrays]


def rmse(y, mean, axis=None):
    """Root mean squared error."""
    y, mean = _check(y, mean)
    return np.sqrt(np.mean((y - mean) ** 2, axis=axis))


def msll(y, mean, std, train_mean, train_std, axis=None):
    """Mean standardised log loss (GPML eq. 2.34): the negative log predictive density
    minus that of a Gaussian with the training data's mean and std. Lower is better; 0 is
    the trivial model; it rewards calibrated std, not only accurate means."""
    y, mean, std = _check(y, mean, std)
    if np.any(std <= 0):
        raise ValueError("std must be positive")
    model = -norm.logpdf(y, mean, std)
    trivial = -norm.logpdf(y, np.asarray(train_mean, float), np.asarray(train_std, float))
    return np.mean(model - trivial, axis=axis)


def coverage(y, mean, std, level=0.95, axis=None):
    """Fraction of values inside the central ``level`` predictive interval (ideal: level)."""
    y, mean, std = _check(y, mean, std)
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    z = norm.ppf(0.5 + level / 2)
    return np.mean(np.abs(y - mean) <= z * std, axis=axis)


def mixture_msll(y, share, mean, std, train_mean, train_std):
    """:func:`msll` of a mixture of modes with independent Gaussian components: ``y`` (n, 3),
    ``share`` (n, C), ``mean`` and ``std`` (n, C, 3). The joint log loss of the 3 components
    over that of the trivial model, per component (with one mode it is :func:`msll`)."""
    y, share, mean, std = (np.asarray(a, float) for a in (y, share, mean, std))
    if share.shape != mean.shape[:2] or mean.shape != std.shape or y.shape != (len(mean), mean.shape[2]):
        raise ValueError(
            f"shapes y {y.shape}, share {share.shape}, mean {mean.shape}, std {std.shape} differ"
        )
    if np.any(std <= 0):
        raise ValueError("std must be positive")
    joint = norm.logpdf(y[:, None, :], mean, std).sum(-1)  # (n, C)
    with np.errstate(divide="ignore"):
        model = -logsumexp(joint, b=share, axis=1)
    trivial = -norm.logpdf(y, np.asarray(train_mean, float), np.asarray(train_std, float)).sum(-1)
    return float(np.mean(model - trivial) / y.shape[1])
