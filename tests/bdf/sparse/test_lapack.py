"""The LAPACK and BLAS wrappers the supernodal kernels call, against numpy, on column-major
blocks inside taller buffers (leading dimension above the rows, as the supernodes' blocks)."""

import numpy as np
import pytest

from bdf.sparse import _lapack

RNG = np.random.default_rng(17)


def flat(A: np.ndarray, lda: int) -> np.ndarray:
    """``A`` (m, n) column-major in a flat buffer of leading dimension ``lda`` (padding NaN)."""
    m, n = A.shape
    out = np.full(lda * n, np.nan)
    for j in range(n):
        out[j * lda : j * lda + m] = A[:, j]
    return out


def block(buf: np.ndarray, m: int, n: int, lda: int) -> np.ndarray:
    return np.stack([buf[j * lda : j * lda + m] for j in range(n)], axis=1)


def spd(n: int) -> np.ndarray:
    A = RNG.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


def test_potrf_and_potri_give_the_lower_factor_and_the_inverse():
    A, lda = spd(5), 7
    buf = flat(A, lda)
    assert _lapack.potrf(buf, 5, lda) == 0
    L = np.tril(block(buf, 5, 5, lda))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-13)
    assert _lapack.potri(buf, 5, lda) == 0
    np.testing.assert_allclose(np.tril(block(buf, 5, 5, lda)), np.tril(np.linalg.inv(A)), rtol=1e-12)
    assert _lapack.potrf(flat(-np.eye(3), 3), 3, 3) == 1  # not positive definite: info names the column


@pytest.mark.parametrize(
    ("side", "trans"), [(_lapack.R, _lapack.T), (_lapack.R, _lapack.N), (_lapack.L, _lapack.N)]
)
def test_trsm_solves_with_a_lower_triangle(side, trans):
    L = np.tril(RNG.standard_normal((4, 4))) + 4 * np.eye(4)
    m, n = (3, 4) if side == _lapack.R else (4, 3)
    B = RNG.standard_normal((m, n))
    buf = flat(B, m + 2)
    _lapack.trsm(side, trans, m, n, 2.0, flat(L, 6), 6, buf, m + 2)
    op = L.T if trans == _lapack.T else L
    want = 2.0 * (B @ np.linalg.inv(op) if side == _lapack.R else np.linalg.inv(op) @ B)
    np.testing.assert_allclose(block(buf, m, n, m + 2), want, rtol=1e-12)


def test_gemm_symm_and_syrk_equal_numpy():
    A, B, C = RNG.standard_normal((3, 4)), RNG.standard_normal((5, 4)), RNG.standard_normal((3, 5))
    c = flat(C, 4)
    _lapack.gemm(_lapack.N, _lapack.T, 3, 5, 4, 1.5, flat(A, 3), 3, flat(B, 6), 6, -1.0, c, 4)
    np.testing.assert_allclose(block(c, 3, 5, 4), 1.5 * A @ B.T - C, rtol=1e-12)
    S, D = spd(4), RNG.standard_normal((4, 2))
    out = flat(np.zeros((4, 2)), 4)
    _lapack.symm(4, 2, 2.0, flat(np.tril(S), 5), 5, flat(D, 4), 4, 0.0, out, 4)  # lower triangle read
    np.testing.assert_allclose(block(out, 4, 2, 4), 2.0 * S @ D, rtol=1e-12)
    E = RNG.standard_normal((4, 3))
    c = flat(np.zeros((4, 4)), 4)
    _lapack.syrk(4, 3, 1.0, flat(E, 5), 5, 0.0, c, 4)
    np.testing.assert_allclose(np.tril(block(c, 4, 4, 4)), np.tril(E @ E.T), rtol=1e-12)
