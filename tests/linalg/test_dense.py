"""gpg.linalg: in-place LAPACK factorisations against NumPy."""

import numpy as np
import pytest

from gpg.linalg import dense


def spd(rng, n):
    A = rng.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


def test_cholesky_inplace(rng):
    K = spd(rng, 60)
    K0 = K.copy()
    L = dense.cholesky_inplace(K)
    assert L is K  # no second copy of the matrix
    np.testing.assert_allclose(L, np.linalg.cholesky(K0), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.triu(L, 1), 0.0)


def test_cho_solve_and_triangular_inverse(rng):
    K = spd(rng, 40)
    B = rng.standard_normal((40, 3))
    L = dense.cholesky_inplace(K.copy())
    np.testing.assert_allclose(K @ dense.cho_solve(L, B), B, atol=1e-10)
    Linv = dense.triangular_inverse_inplace(L.copy())
    np.testing.assert_allclose(Linv @ L, np.eye(40), atol=1e-12)
    np.testing.assert_array_equal(np.triu(Linv, 1), 0.0)


def test_rejects_bad_buffers(rng):
    with pytest.raises(ValueError, match="square"):
        dense.cholesky_inplace(np.ones((3, 4)))
    with pytest.raises(ValueError, match="C-contiguous"):
        dense.cholesky_inplace(np.asfortranarray(spd(rng, 5)))
    with pytest.raises(dense.NotPositiveDefiniteError, match="pivot 1"):
        dense.cholesky_inplace(np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_blocked_cholesky_equals_lapack(rng, monkeypatch):
    K = spd(rng, 300)
    want = np.linalg.cholesky(K)
    monkeypatch.setattr(dense, "BLOCKED_ABOVE", 100)
    L = dense.cholesky_inplace(K.copy(), block=64)
    np.testing.assert_allclose(L, want, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(np.triu(L, 1), 0.0)
    bad = K.copy()
    bad[200, 200] = -1.0
    with pytest.raises(dense.NotPositiveDefiniteError, match="pivot 200"):
        dense.cholesky_inplace(bad, block=64)


def test_gram_t_is_ata(rng):
    a = rng.standard_normal((70, 9))
    np.testing.assert_allclose(dense.gram_t(a), a.T @ a, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(dense.gram_t(np.asfortranarray(a)), a.T @ a, rtol=1e-12)
