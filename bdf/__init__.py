"""Bayesian Dynamic Fields: 3D velocity maps with calibrated uncertainty."""

from bdf.field import BayesianDynamicField
from bdf.statistics import Evidence

__all__ = ["BayesianDynamicField", "Evidence"]
