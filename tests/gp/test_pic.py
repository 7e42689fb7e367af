"""PIC with gradient inducing points: the Woodbury training against a dense PIC computation
written here in NumPy; one block and every-point-inducing reduce to the exact GP-G."""

import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import ExactGP, Hyper, binned, kernels, partition, pic, stack_targets

SIGMA = 1.2


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(3)
    N, D, M = 40, 3, 2
    X = rng.uniform(-1, 1, (N, D))
    W = rng.normal(size=(D, M))
    Y = np.sin(X @ W)
    dims = (0, 2)
    dY = np.stack([np.cos(X @ W) * W[d] for d in dims], axis=-1)
    hyper = Hyper(SIGMA, np.array([0.5, 0.8, 0.6]), 1e-2, np.array([1e-2, 2e-2]))
    return X, Y, dY, dims, hyper, rng.uniform(-1, 1, (15, D))


def fitted(problem, n_bins, Z, jitter):
    X, Y, dY, dims, hyper, _ = problem
    part = partition.slab(X, n_bins, dim=0)
    bins = np.asarray(part.lookup_batch(jnp.asarray(X)))
    blocks = [np.flatnonzero(bins == b) for b in range(n_bins)]
    f = pic.precompute(X, stack_targets(Y, dY), hyper, dims, blocks, Z, jitter=jitter)
    return binned.pack_points([X[b] for b in blocks], f, part, hyper, dims, shared=Z), part


def dense_pic(problem, part, Z, jitter):
    """PIC by its definition: K̃ = Q + blkdiag(K̄ − Q) + Σ, k̃_q exact in the query's block."""
    X, Y, dY, dims, hyper, Xq = problem
    n, g = X.shape[0], len(dims)

    def G(A, B, d1, d2):
        return np.array(
            kernels.gram(jnp.asarray(A), jnp.asarray(B), SIGMA, hyper.lengthscale, d1, d2)
        )

    Kuu = G(Z, Z, dims, dims)
    Kuu[np.diag_indices_from(Kuu)] *= 1 + jitter
    Kfu = G(X, Z, dims, dims)
    Q = Kfu @ np.linalg.solve(Kuu, Kfu.T)
    block = np.tile(np.asarray(part.lookup_batch(jnp.asarray(X))), 1 + g)
    Kt = np.where(block[:, None] == block[None, :], G(X, X, dims, dims), Q)
    Kt += np.diag(np.asarray(hyper.noise_diagonal(n, g)))
    qb = np.asarray(part.lookup_batch(jnp.asarray(Xq)))
    kq = np.where(
        qb[:, None] == block[None, :],
        G(Xq, X, (), dims),
        G(Xq, Z, (), dims) @ np.linalg.solve(Kuu, Kfu.T),
    )
    mean = kq @ np.linalg.solve(Kt, stack_targets(Y, dY))
    var = SIGMA - np.einsum("qi,iq->q", kq, np.linalg.solve(Kt, kq.T))
    return mean, var


def test_woodbury_training_equals_dense_pic(problem):
    X, Xq = problem[0], problem[5]
    Z = pic.inducing_inputs(X, 6, seed=0)
    model, part = fitted(problem, 3, Z, 1e-6)
    m, v = model.predict_unclipped(Xq)
    mr, vr = dense_pic(problem, part, Z, 1e-6)
    np.testing.assert_allclose(m, mr, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(v, vr, rtol=1e-8, atol=1e-10)
    assert np.all(np.asarray(v) > 0) and np.all(np.asarray(v) <= SIGMA)


def test_one_block_is_exact_gpg(problem):
    X, Y, dY, dims, hyper, Xq = problem
    exact = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    model, _ = fitted(problem, 1, pic.inducing_inputs(X, 6, seed=0), 1e-8)
    m, v = model.predict_unclipped(Xq)
    me, ve = exact.predict_unclipped(Xq)
    np.testing.assert_allclose(m, me, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(v, ve, rtol=1e-7, atol=1e-9)


def test_every_point_inducing_is_exact_gpg(problem):
    """Q = K̄ up to the inducing jitter, so K̃ = K̄: exact to that jitter's order."""
    X, Y, dY, dims, hyper, Xq = problem
    exact = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    model, part = fitted(problem, 3, pic.inducing_inputs(X, X.shape[0]), 1e-10)
    m, v = model.predict_unclipped(Xq)
    me, ve = exact.predict_unclipped(Xq)
    np.testing.assert_allclose(m, me, atol=1e-7)
    np.testing.assert_allclose(v, ve, atol=1e-7)


def test_inducing_inputs(problem):
    X = problem[0]
    Z = pic.inducing_inputs(X, 7, seed=1)
    assert Z.shape == (7, 3) and np.unique(Z, axis=0).shape[0] == 7
    np.testing.assert_array_equal(Z, pic.inducing_inputs(X, 7, seed=1))  # deterministic
    np.testing.assert_array_equal(pic.inducing_inputs(X, 40), X)
    with pytest.raises(ValueError, match="more inducing points than the 40 training points"):
        pic.inducing_inputs(X, 41)
    with pytest.raises(ValueError, match="positive integer"):
        pic.inducing_inputs(X, 0)


def test_blocks_must_partition(problem):
    X, Y, dY, dims, hyper, _ = problem
    with pytest.raises(ValueError, match="partition the training points"):
        pic.precompute(X, stack_targets(Y, dY), hyper, dims, [np.arange(30)], X[:3])
