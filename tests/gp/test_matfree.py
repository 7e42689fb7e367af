"""Matrix-free products with K̄ and conjugate gradients (gpg/gp/matfree.py, gpg/gp/cg.py):
equal to the dense product and the dense solve, and a clear error when CG cannot converge."""

from functools import partial

import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import cg, pic
from gpg.gp.gram import noisy_gram
from gpg.gp.hyper import Hyper
from gpg.gp.matfree import gram_matvec, gram_matvec_devices


def problem(n=41, dims=(0, 2), seed=0, iso=False):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 4))
    ls = 0.7 if iso else np.array([0.5, 0.8, 0.6, 0.9])
    lam = np.full(len(dims), 2e-2) if dims else 1e-4
    hyper = Hyper(1.3, ls, 1e-3, lam)
    B = rng.normal(size=(n * (1 + len(dims)), 3))
    return jnp.asarray(X), hyper, dims, jnp.asarray(B)


@pytest.mark.parametrize("dims", [(), (1,), (0, 2), (0, 1, 2, 3)])
@pytest.mark.parametrize("tile", [7, 64])
def test_product_equals_the_dense_one(dims, tile):
    """Values only, one, two and every gradient dimension; tiles that do and do not divide N."""
    X, hyper, dims, B = problem(dims=dims)
    ref = noisy_gram(X, hyper, dims) @ B
    got = gram_matvec(X, hyper, dims, B, tile=tile)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * float(jnp.abs(ref).max()))


def test_isotropic_lengthscale_and_one_device():
    X, hyper, dims, B = problem(iso=True)
    ref = noisy_gram(X, hyper, dims) @ B
    np.testing.assert_allclose(gram_matvec(X, hyper, dims, B), ref, atol=1e-12)
    got = gram_matvec_devices(X, hyper, dims, B, devices=1, tile=16)
    np.testing.assert_allclose(got, ref, atol=1e-12)


@pytest.mark.parametrize("preconditioner", ["nystrom", "none"])
def test_cg_solves_to_its_tolerance(preconditioner):
    """CG's α equals the dense solve to what its tolerance allows (here 1e-10 in residual),
    and the Nyström preconditioner from inducing inputs cuts the iterations."""
    X, hyper, dims, B = problem(n=60)
    K = noisy_gram(X, hyper, dims)
    ref = jnp.linalg.solve(K, B)
    Z = jnp.asarray(pic.inducing_inputs(np.asarray(X), 15))
    pre = cg.Nystrom.create(X, hyper, dims, Z) if preconditioner == "nystrom" else (lambda r: r)
    mv = partial(gram_matvec, X, hyper, dims, tile=32)
    x, info = cg.solve(mv, B, pre, tol=1e-10, max_iter=5000, progress=False)
    assert info.converged and info.residual.max() <= 1e-10
    resid = np.linalg.norm(K @ x - B, axis=0) / np.linalg.norm(B, axis=0)
    assert resid.max() <= 2e-10
    cond = np.linalg.cond(np.asarray(K))
    np.testing.assert_allclose(x, ref, atol=1e-10 * cond * float(jnp.abs(ref).max()))
    if preconditioner == "nystrom":
        plain = cg.solve(mv, B, lambda r: r, tol=1e-10, max_iter=5000, progress=False)[1]
        assert info.iterations < plain.iterations / 2


def test_nystrom_with_every_point_inducing_is_nearly_exact():
    """With all training inputs as inducing inputs, Q = K̄ up to the jitter: one or two
    iterations (the preconditioner is the inverse)."""
    X, hyper, dims, B = problem(n=20)
    pre = cg.Nystrom.create(X, hyper, dims, X, jitter=1e-10)
    mv = partial(gram_matvec, X, hyper, dims)
    _, info = cg.solve(mv, B, pre, tol=1e-8, max_iter=50, progress=False)
    assert info.iterations <= 3


def test_unreachable_tolerance_is_a_clear_error():
    X, hyper, dims, B = problem(n=40)
    mv = partial(gram_matvec, X, hyper, dims)
    with pytest.raises(cg.NotConverged, match=r"did not reach the relative residual 1e-12 in 3"):
        cg.solve(mv, B, lambda r: r, tol=1e-12, max_iter=3, progress=False)
    with pytest.raises(ValueError, match="tol must be in"):
        cg.solve(mv, B, lambda r: r, tol=0.0)
    with pytest.raises(ValueError, match="max_iter must be a positive integer"):
        cg.solve(mv, B, lambda r: r, max_iter=0)
