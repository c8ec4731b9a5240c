"""The precision's sparse algebra: no maintained package offers selected inversion.

- :mod:`bdf.sparse.stencil`: the stencil of a lattice's precision, bands on it, the nested
  dissection, supports (the hinges a band touches) and factors.
- :mod:`bdf.sparse.symbolic`: the elimination tree, its postorder, column counts and
  relaxed supernodes of a pattern: the layout of its factor.
- :mod:`bdf.sparse.supernodal`: the compiled factorisation, solves and selected inversion
  on that layout (LAPACK and BLAS without the GIL, :mod:`bdf.sparse._lapack`).
"""

from bdf.sparse.stencil import (
    Factor,
    NotPositiveDefinite,
    Stencil,
    band_density,
    band_product,
    lattice_stencil,
    midpoint_band,
    stencil_on,
)

__all__ = [
    "Factor",
    "NotPositiveDefinite",
    "Stencil",
    "band_density",
    "band_product",
    "lattice_stencil",
    "midpoint_band",
    "stencil_on",
]
