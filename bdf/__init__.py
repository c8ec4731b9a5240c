"""Bayesian Dynamic Fields: 3D velocity maps with calibrated uncertainty.

The package's names load on first use (PEP 562): a process that needs only a light module
(``bdf.sectors`` in a planning process) does not compile the field's kernels."""

__all__ = ["BayesianDynamicField", "Evidence"]


def __getattr__(name: str):
    if name == "BayesianDynamicField":
        from bdf.field import BayesianDynamicField

        return BayesianDynamicField
    if name == "Evidence":
        from bdf.statistics import Evidence

        return Evidence
    raise AttributeError(f"module 'bdf' has no attribute {name!r}")
