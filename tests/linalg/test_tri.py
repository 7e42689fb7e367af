"""Row-band triangular storage: products equal the dense ones."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.linalg.tri import BlockTriangular, BorderedTriangular
from tests.helpers import compiles


@pytest.mark.parametrize("lower", [True, False])
@pytest.mark.parametrize("n, n_blocks", [(1, 4), (7, 3), (50, 8), (64, 1)])
def test_products_match_dense(rng, lower, n, n_blocks):
    F = rng.normal(size=(n, n))
    F = np.tril(F) if lower else np.triu(F)
    bt = BlockTriangular.from_dense(F, lower=lower, n_blocks=n_blocks)
    np.testing.assert_array_equal(bt.to_dense(), F)
    k = rng.normal(size=n)
    K = rng.normal(size=(5, n))
    np.testing.assert_allclose(bt.matvec(jnp.asarray(k)), F @ k, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bt.rmatmul(jnp.asarray(K)), K @ F.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jax.vmap(bt.matvec)(jnp.asarray(K)), K @ F.T, rtol=1e-12, atol=1e-12)
    stored = sum(b.size for b in bt.blocks)
    assert stored <= n * n and (n_blocks == 1 or n < 8 or stored < 0.7 * n * n)
    if lower:  # the host products of the bordered update (gpg.gp.update)
        np.testing.assert_allclose(bt.host_matmul(K.T), F @ K.T, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(bt.host_lmatmul(K), K @ F, rtol=1e-12, atol=1e-12)


def test_rejects_non_square():
    with pytest.raises(ValueError, match="square"):
        BlockTriangular.from_dense(np.zeros((3, 4)), lower=True)


@pytest.mark.parametrize("dense_rows", [0, 3, 12, 20])
def test_dense_leading_rows(rng, dense_rows):
    """Upper factors dense in their first rows (PIC) are stored exactly, in one band."""
    n = 20
    F = np.triu(rng.normal(size=(n, n)))
    F[:dense_rows] = rng.normal(size=(dense_rows, n))
    bt = BlockTriangular.from_dense(F, lower=False, n_blocks=4, dense_rows=dense_rows)
    np.testing.assert_array_equal(bt.to_dense(), F)
    K = rng.normal(size=(3, n))
    np.testing.assert_allclose(bt.rmatmul(jnp.asarray(K)), K @ F.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bt.matvec(jnp.asarray(K[0])), F @ K[0], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="upper factors only"):
        BlockTriangular.from_dense(F, lower=True, dense_rows=2)


def test_float32_storage_halves_bytes(rng):
    F = np.triu(rng.normal(size=(30, 30)))
    b64 = BlockTriangular.from_dense(F, lower=False, n_blocks=3)
    b32 = BlockTriangular.from_dense(F.astype(np.float32), lower=False, n_blocks=3)
    assert sum(b.nbytes for b in b32.blocks) * 2 == sum(b.nbytes for b in b64.blocks)
    k = rng.normal(size=30)
    v = b32.matvec(jnp.asarray(k))
    assert v.dtype == jnp.float32
    np.testing.assert_allclose(v, F @ k, rtol=1e-5, atol=1e-5 * np.abs(F @ k).max())


def test_bordered_factor_is_the_inverse_of_the_bordered_cholesky_factor(rng):
    """Two borderings of a Cholesky factor: every product of the factored inverse equals the
    dense inverse of the grown factor ``[[L, 0], [S, L₂]]`` (NumPy)."""
    n0, sizes = 9, (4, 3)
    A = rng.normal(size=(16, 16))
    K = A @ A.T + 16 * np.eye(16)
    L = np.linalg.cholesky(K)
    F = BlockTriangular.from_dense(np.linalg.inv(L[:n0, :n0]), lower=True, n_blocks=3)
    m = n0
    for r in sizes:
        S, L2 = L[m : m + r, :m], L[m : m + r, m : m + r]
        L2inv = np.linalg.inv(L2)
        F = BorderedTriangular(F, jnp.asarray(L2inv @ S), jnp.asarray(L2inv), m + r)
        m += r
    want = np.linalg.inv(L)
    np.testing.assert_allclose(F.to_dense(), want, rtol=1e-12, atol=1e-12)
    Q = rng.normal(size=(3, 16))
    np.testing.assert_allclose(F.matvec(jnp.asarray(Q[0])), want @ Q[0], atol=1e-12)
    np.testing.assert_allclose(F.rmatvec(jnp.asarray(Q[0])), want.T @ Q[0], atol=1e-12)
    np.testing.assert_allclose(F.rmatmul(jnp.asarray(Q)), Q @ want.T, atol=1e-12)
    np.testing.assert_allclose(F.lmatmul(jnp.asarray(Q)), Q @ want, atol=1e-12)
    np.testing.assert_allclose(F.host_matmul(Q.T), want @ Q.T, atol=1e-12)
    np.testing.assert_allclose(F.host_lmatmul(Q), Q @ want, atol=1e-12)


def test_bands_from_a_buffer_are_the_rows_before_their_release():
    """``from_buffer`` gives each band's rows back to the system right after copying them:
    the copy must be complete by then. Without waiting for it, ``jnp.array``'s host copy
    could still be pending, and the last band (contiguous in the buffer) came out partly
    zeros in 9 of 40 such factors on a loaded 2-core machine."""
    from gpg.linalg import memory

    for seed in range(24):
        rng = np.random.default_rng(seed)
        n = int(rng.integers(200, 1200))
        buf = memory.square_buffer(n)
        buf.array[:] = np.tril(rng.normal(size=(n, n)))
        want = buf.array.copy()
        F = BlockTriangular.from_buffer(buf, lower=True, n_blocks=8)
        a = 0
        for blk in F.blocks:
            b = a + blk.shape[0]
            np.testing.assert_array_equal(np.asarray(blk), want[a:b, :b], err_msg=f"n={n}")
            a = b


def test_bands_of_a_device_factor_are_its_lower_rows_in_one_program(rng, caplog):
    """``from_device``: the bands are ``F``'s lower rows (its products those of ``F``), cut in
    one compiled program for ``F``'s shape (op by op, one slice each), none the second time."""
    n = 37
    F = jnp.asarray(np.tril(rng.normal(size=(n, n))))

    T, k = compiles(caplog, lambda: BlockTriangular.from_device(F, n_blocks=6))
    assert len(T.blocks) == 6 and k <= 1
    np.testing.assert_array_equal(T.to_dense(), np.asarray(F))
    _, k = compiles(caplog, lambda: BlockTriangular.from_device(F + 1.0, n_blocks=6))
    assert k <= 1  # the sum's own program, not the bands'
    _, k = compiles(caplog, lambda: BlockTriangular.from_device(F, n_blocks=6))
    assert k == 0
