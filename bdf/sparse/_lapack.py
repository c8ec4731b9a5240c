"""LAPACK and BLAS for compiled kernels, without the GIL.

scipy's own OpenBLAS (its ``cython_blas`` / ``cython_lapack`` entry points, the library
:mod:`bdf._blas` limits) called from numba: a kernel that factors or inverts runs as one
compiled call that releases the GIL, so the classes of a directional map are factored
side by side in threads (:mod:`bdf.posterior`). The entry points are registered with
LLVM under fixed names, which keeps the kernels cacheable.

Matrices are column-major views of flat arrays with an explicit leading dimension; the
Fortran convention passes every argument by pointer, and characters as their codes.
"""

from __future__ import annotations

import llvmlite.binding as llvm
import numba
import numpy as np
from numba import types
from numba.extending import get_cython_function_address

_ARGS = {"dpotrf": 5, "dpotri": 5, "dtrsm": 11, "dgemm": 13, "dsymm": 12, "dsyrk": 10}


def _entry(name: str):
    module = "scipy.linalg.cython_lapack" if name.startswith("dpot") else "scipy.linalg.cython_blas"
    llvm.add_symbol(f"bdf_{name}", get_cython_function_address(module, name))
    return types.ExternalFunction(f"bdf_{name}", types.void(*([types.voidptr] * _ARGS[name])))


_dpotrf, _dpotri, _dtrsm, _dgemm, _dsymm, _dsyrk = (_entry(name) for name in _ARGS)

L, R, N, T = ord("L"), ord("R"), ord("N"), ord("T")


@numba.njit(nogil=True, cache=True)
def _positive_definite(inverse, a, n, lda):  # pragma: no cover - compiled
    """``dpotri`` if ``inverse`` else ``dpotrf`` on the lower (n, n) block of ``a``; info."""
    ch = np.array([L], np.uint8)
    ints = np.array([n, lda, 0], np.int32)
    if inverse:
        _dpotri(ch.ctypes, ints[0:].ctypes, a.ctypes, ints[1:].ctypes, ints[2:].ctypes)
    else:
        _dpotrf(ch.ctypes, ints[0:].ctypes, a.ctypes, ints[1:].ctypes, ints[2:].ctypes)
    return ints[2]


@numba.njit(nogil=True, cache=True)
def potrf(a, n, lda):  # pragma: no cover - compiled
    """Lower Cholesky factor of the (n, n) block of ``a`` in place; LAPACK's info."""
    return _positive_definite(False, a, n, lda)


@numba.njit(nogil=True, cache=True)
def potri(a, n, lda):  # pragma: no cover - compiled
    """``(L L^T)^-1`` (lower triangle) from the lower factor in ``a``, in place; info."""
    return _positive_definite(True, a, n, lda)


@numba.njit(nogil=True, cache=True)
def trsm(side, trans, m, n, alpha, a, lda, b, ldb):  # pragma: no cover - compiled
    """``b <- alpha op(A)^-1 b`` (side L) or ``alpha b op(A)^-1`` (side R), A lower, (m, n) b."""
    ch = np.array([side, L, trans, N], np.uint8)
    ints = np.array([m, n, lda, ldb], np.int32)
    scalar = np.array([alpha])
    _dtrsm(
        ch[0:].ctypes, ch[1:].ctypes, ch[2:].ctypes, ch[3:].ctypes, ints[0:].ctypes, ints[1:].ctypes,
        scalar.ctypes, a.ctypes, ints[2:].ctypes, b.ctypes, ints[3:].ctypes,
    )  # fmt: skip


@numba.njit(nogil=True, cache=True)
def gemm(ta, tb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc):  # pragma: no cover - compiled
    """``c <- alpha op(a) op(b) + beta c``, (m, n) c."""
    ch = np.array([ta, tb], np.uint8)
    ints = np.array([m, n, k, lda, ldb, ldc], np.int32)
    scalars = np.array([alpha, beta])
    _dgemm(
        ch[0:].ctypes, ch[1:].ctypes, ints[0:].ctypes, ints[1:].ctypes, ints[2:].ctypes, scalars[0:].ctypes,
        a.ctypes, ints[3:].ctypes, b.ctypes, ints[4:].ctypes, scalars[1:].ctypes, c.ctypes, ints[5:].ctypes,
    )  # fmt: skip


@numba.njit(nogil=True, cache=True)
def symm(m, n, alpha, a, lda, b, ldb, beta, c, ldc):  # pragma: no cover - compiled
    """``c <- alpha A b + beta c``, A (m, m) symmetric from its lower triangle, (m, n) c."""
    ch = np.array([L, L], np.uint8)
    ints = np.array([m, n, lda, ldb, ldc], np.int32)
    scalars = np.array([alpha, beta])
    _dsymm(
        ch[0:].ctypes, ch[1:].ctypes, ints[0:].ctypes, ints[1:].ctypes, scalars[0:].ctypes, a.ctypes,
        ints[2:].ctypes, b.ctypes, ints[3:].ctypes, scalars[1:].ctypes, c.ctypes, ints[4:].ctypes,
    )  # fmt: skip


@numba.njit(nogil=True, cache=True)
def syrk(n, k, alpha, a, lda, beta, c, ldc):  # pragma: no cover - compiled
    """``c <- alpha a a^T + beta c`` on the lower triangle of (n, n) c, (n, k) a."""
    ch = np.array([L, N], np.uint8)
    ints = np.array([n, k, lda, ldc], np.int32)
    scalars = np.array([alpha, beta])
    _dsyrk(
        ch[0:].ctypes, ch[1:].ctypes, ints[0:].ctypes, ints[1:].ctypes, scalars[0:].ctypes, a.ctypes,
        ints[2:].ctypes, scalars[1:].ctypes, c.ctypes, ints[3:].ctypes,
    )  # fmt: skip
