"""Gradient rows along arbitrary directions (the paper's remark on directional derivatives):
the kernel blocks, and the exact GP-G on such rows against an independent NumPy posterior."""

import jax
import numpy as np
import pytest

from gpg.gp import kernels
from gpg.gp.exact import ExactGP
from gpg.gp.gram import from_bases, row_directions, to_bases
from gpg.gp.hyper import Hyper

# Every comparison below is between two float64 evaluations of the same closed forms over
# small, well-conditioned matrices (noise ≥ 1e-4 on a unit signal): rounding stays far below.
TOL = 1e-9


def _np_cov(x1, e1, v1, x2, e2, v2, s, ls):
    """NumPy covariance of a value (``v``) or a directional derivative (``e``) at two points,
    by second differences of the kernel itself: no shared closed form with the code."""
    h = 1e-4

    def k(a, b):
        return s * np.exp(-0.5 * np.sum(((a - b) / ls) ** 2))

    if v1 and v2:
        return k(x1, x2)
    if v1:
        return (k(x1, x2 + h * e2) - k(x1, x2 - h * e2)) / (2 * h)
    if v2:
        return (k(x1 + h * e1, x2) - k(x1 - h * e1, x2)) / (2 * h)
    return (
        k(x1 + h * e1, x2 + h * e2) - k(x1 + h * e1, x2 - h * e2)
        - k(x1 - h * e1, x2 + h * e2) + k(x1 - h * e1, x2 - h * e2)
    ) / (4 * h * h)  # fmt: skip


def test_direction_gram_is_the_kernels_directional_derivative(rng):
    ls = np.array([0.6, 1.3, 0.8])
    X1, X2 = rng.uniform(-1, 1, (5, 3)), rng.uniform(-1, 1, (4, 3))
    E1, E2 = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    v1, v2 = np.array([1, 0, 0, 1, 0], bool), np.array([0, 1, 0, 0], bool)
    K = np.asarray(kernels.direction_gram(X1, E1, v1, X2, E2, v2, 1.7, ls))
    ref = np.array(
        [[_np_cov(X1[i], E1[i], v1[i], X2[j], E2[j], v2[j], 1.7, ls) for j in range(4)]
         for i in range(5)]
    )  # fmt: skip
    # Central second differences with h = 1e-4 on an O(1) kernel: truncation ~1e-8, rounding
    # ~1e-16/h² = 1e-8.
    np.testing.assert_allclose(K, ref, atol=5e-7)


def test_one_hot_directions_are_row_gram(rng):
    X = rng.uniform(-1, 1, (6, 4))
    a = np.array([-1, 0, 3, -1, 2, 1])
    E = np.zeros((6, 4))
    E[a >= 0, a[a >= 0]] = 1.0
    K1 = kernels.direction_gram(X, E, a < 0, X, E, a < 0, 0.9, np.array([0.5, 1, 2, 0.7]))
    K2 = kernels.row_gram(X, a, X, a, 0.9, np.array([0.5, 1, 2, 0.7]))
    np.testing.assert_allclose(K1, K2, rtol=TOL, atol=1e-14)


def _problem(rng, n=7, d=3, dims=(0, 2)):
    X = rng.uniform(-1, 1, (n, d))
    g = len(dims)
    B = rng.normal(size=(n, g, g))
    Y = rng.normal(size=(n, 2))
    dY = rng.normal(size=(n, 2, g))
    hyper = Hyper(variance=1.3, lengthscale=np.array([0.7, 1.1, 0.9]), noise=1e-3,
                  grad_noise=np.array([1e-3, 2e-3]))  # fmt: skip
    return X, Y, dY, B, dims, hyper


def _np_posterior(X, Y, dY, B, dims, hyper, Xq, observed=None):
    """Posterior mean and latent variance at ``Xq``, written out in NumPy row by row."""
    n, g = len(X), len(dims)
    s, ls = float(hyper.variance), np.asarray(hyper.lengthscale)
    rows = [(i, None) for i in range(n)] + [(i, k) for k in range(g) for i in range(n)]
    if observed is not None:
        rows = [(i, k) for i, k in rows if k is None or observed[i, k]]

    def direction(i, k):
        e = np.zeros(X.shape[1])
        e[list(dims)] = B[i, k]
        return e

    z = np.zeros(X.shape[1])
    K = np.array(
        [[_np_cov(X[i], z if a is None else direction(i, a), a is None,
                  X[j], z if b is None else direction(j, b), b is None, s, ls)
          for j, b in rows] for i, a in rows]
    )  # fmt: skip
    noise = [hyper.noise if a is None else np.asarray(hyper.grad_noise)[a] for _, a in rows]
    K += np.diag(noise)
    y = np.array([Y[i] if a is None else dY[i, :, a] for i, a in rows])
    kq = np.array(
        [[_np_cov(xq, z, True, X[i], z if a is None else direction(i, a), a is None, s, ls)
          for i, a in rows] for xq in Xq]
    )  # fmt: skip
    mean = kq @ np.linalg.solve(K, y)
    var = s - np.einsum("qr,qr->q", kq, np.linalg.solve(K, kq.T).T)
    return mean, var


@pytest.mark.parametrize("partial", [False, True])
def test_exact_gp_on_directional_rows_matches_numpy(rng, partial):
    X, Y, dY, B, dims, hyper = _problem(rng)
    observed = None
    if partial:
        observed = rng.uniform(size=(X.shape[0], len(dims))) < 0.6
        observed[0] = False
    gp = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B, observed=observed)
    Xq = rng.uniform(-1, 1, (5, 3))
    mean, var = gp.predict(Xq)
    ref_mean, ref_var = _np_posterior(X, Y, dY, B, dims, hyper, Xq, observed)
    # The reference's kernel comes from second differences (errors ~1e-7, see above), then a
    # solve with a condition number ~1e3: 1e-4 absolute on O(1) posteriors.
    np.testing.assert_allclose(mean, ref_mean, atol=1e-4)
    np.testing.assert_allclose(var, ref_var, atol=1e-4)


def test_identity_bases_are_the_coordinate_gp(rng):
    X, Y, dY, _, dims, hyper = _problem(rng)
    eye = np.broadcast_to(np.eye(len(dims)), (X.shape[0], 2, 2))
    a = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    b = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=eye)
    Xq = rng.uniform(-1, 1, (6, 3))
    for u, v in zip(a.predict(Xq), b.predict(Xq), strict=True):
        np.testing.assert_allclose(u, v, rtol=TOL, atol=1e-12)
    np.testing.assert_allclose(a.log_marginal_likelihood, b.log_marginal_likelihood, rtol=TOL)


def test_invertible_bases_are_a_change_of_variables(rng):
    """Observing ``B ∇f`` with noise ``B Σ Bᵀ`` is observing ``∇f`` with noise ``Σ``: with
    orthogonal ``B`` and one gradient noise the two GPs are the same posterior."""
    X, Y, dY, _, dims, hyper = _problem(rng)
    hyper = Hyper(variance=1.3, lengthscale=np.array([0.7, 1.1, 0.9]), noise=1e-3,
                  grad_noise=np.array([2e-3, 2e-3]))  # fmt: skip
    Q = np.linalg.qr(rng.normal(size=(X.shape[0], 2, 2)))[0]
    a = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    b = ExactGP.fit(X, Y, np.einsum("igh,imh->img", Q, dY), grad_dims=dims, hyper=hyper,
                    bases=Q)  # fmt: skip
    Xq = rng.uniform(-1, 1, (6, 3))
    for u, v in zip(a.predict(Xq), b.predict(Xq), strict=True):
        np.testing.assert_allclose(u, v, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(a.predict_gradient(Xq), b.predict_gradient(Xq), atol=1e-9)


def test_bases_helpers_invert_each_other(rng):
    n, g = 5, 3
    B = rng.normal(size=(n, g, g))
    k = rng.normal(size=(4, n * (1 + g)))
    alpha = rng.normal(size=(n * (1 + g), 2))
    # k̄_dirᵀ α_dir = k̄_coordᵀ (Pᵀ α_dir): the mean folds the bases into its coefficients.
    np.testing.assert_allclose(
        np.asarray(to_bases(k, B, n)) @ alpha, k @ from_bases(alpha, B, n), rtol=1e-12
    )
    p, E, v = row_directions(np.arange(n * (1 + g)), n, (0, 2, 3), B, 4)
    assert v.sum() == n and np.all(E[v] == 0)
    np.testing.assert_array_equal(E[n + 2 * n + 1][[0, 2, 3]], B[1, 2])


def test_bad_bases_are_refused(rng):
    X, Y, dY, B, dims, hyper = _problem(rng)
    with pytest.raises(ValueError, match="bases must have shape"):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B[:, :1])
    bad = B.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="bases"):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=bad)
    gp = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B)
    with pytest.raises(ValueError, match="bases must have shape"):
        gp.condition(X[:1] + 0.1, Y[:1], dY[:1], bases=B[:2])


@pytest.mark.parametrize("sides", ["both", "old", "new"])
def test_conditioning_on_directional_rows_is_the_refit(rng, sides):
    """The bordered update with directions on either side (the other along the inputs) is
    the fit on all the cases, to the rounding of two factorisations of a small K̄."""
    X, Y, dY, B, dims, hyper = _problem(rng, n=9)
    eye = np.broadcast_to(np.eye(2), B.shape).copy()
    B = {"both": B, "old": np.concatenate([B[:6], eye[6:]]),
         "new": np.concatenate([eye[:6], B[6:]])}[sides]  # fmt: skip
    old_b = None if sides == "new" else B[:6]
    new_b = None if sides == "old" else B[6:]
    grown = ExactGP.fit(X[:6], Y[:6], dY[:6], grad_dims=dims, hyper=hyper, bases=old_b)
    grown = grown.condition(X[6:], Y[6:], dY[6:], bases=new_b)
    full = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B)
    Xq = rng.uniform(-1, 1, (5, 3))
    for u, v in zip(grown.predict(Xq), full.predict(Xq), strict=True):
        np.testing.assert_allclose(u, v, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(grown.log_marginal_likelihood, full.log_marginal_likelihood,
                               rtol=1e-9)  # fmt: skip


def test_directional_predictions_differentiate(rng):
    X, Y, dY, B, dims, hyper = _problem(rng)
    gp = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B)
    x = rng.uniform(-1, 1, 3)
    f = lambda x: gp.predict(x[None])[1][0]  # noqa: E731
    g = jax.grad(f)(x)
    h = 1e-6
    fd = [(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(g, fd, atol=1e-6)


def test_likelihood_is_invariant_under_orthogonal_bases(rng):
    """``z = Q ∇f + ε`` with orthogonal ``Q`` and iid ``ε`` has the density of ``∇f + ε`` at
    ``Qᵀ z``: the two marginal likelihoods are equal, and so are their gradients in the
    hyperparameters (what the fit follows)."""
    from gpg.gp.gram import log_marginal_likelihood, stack_targets

    X, Y, dY, _, dims, _ = _problem(rng)
    Q = np.linalg.qr(rng.normal(size=(X.shape[0], 2, 2)))[0]
    turned = np.einsum("igh,imh->img", Q, dY)

    def lml(var, bases, grads):
        h = Hyper(variance=var, lengthscale=np.array([0.7, 1.1, 0.9]), noise=1e-3,
                  grad_noise=np.array([2e-3, 2e-3]))  # fmt: skip
        return log_marginal_likelihood(X, stack_targets(Y, grads), h, dims, bases=bases)

    np.testing.assert_allclose(lml(1.3, Q, turned), lml(1.3, None, dY), rtol=1e-10)
    np.testing.assert_allclose(jax.grad(lml)(1.3, Q, turned), jax.grad(lml)(1.3, None, dY),
                               rtol=1e-8)  # fmt: skip


def test_the_acquisitions_whitened_rows_read_the_directions(rng):
    """The active design's ``L⁻¹ K̄(A, ·)`` covers the directional rows: the variance it
    implies at value queries is ``predict``'s and the NumPy posterior's."""
    from gpg.design.acquisition import _whitened

    X, Y, dY, B, dims, hyper = _problem(rng)
    gp = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, bases=B)
    Xq = rng.uniform(-1, 1, (4, 3))
    V = _whitened(gp, Xq, ())
    np.testing.assert_allclose(
        float(hyper.variance) - np.sum(V * V, axis=1), gp.predict(Xq)[1], rtol=1e-10, atol=1e-12
    )
    _, ref_var = _np_posterior(X, Y, dY, B, dims, hyper, Xq)
    np.testing.assert_allclose(float(hyper.variance) - np.sum(V * V, axis=1), ref_var, atol=1e-4)


def test_hyperparameter_fit_on_orthogonal_bases_is_the_coordinate_fit(rng):
    """The likelihood is invariant under orthogonal bases (above), so BFGS from the same start
    follows the same path: the fitted hyperparameters agree to the optimiser's tolerance."""
    from gpg.gp.fit import fit_hyperparameters

    X, dims = rng.uniform(-1, 1, (14, 3)), (0, 2)
    W = rng.normal(size=(3, 2))
    Y = np.sin(X @ W)  # a smooth function, so that the fit converges
    dY = (np.cos(X @ W)[:, :, None] * W.T[None])[:, :, list(dims)]
    Q = np.linalg.qr(rng.normal(size=(X.shape[0], 2, 2)))[0]
    init = Hyper(variance=1.0, lengthscale=np.array([0.8, 0.8, 0.8]), noise=1e-2,
                 grad_noise=np.array([2e-3, 2e-3]))  # fmt: skip
    kw = {"grad_dims": dims, "init": init, "subset_size": None, "on_failure": "raise"}
    a = fit_hyperparameters(X, Y, dY, **kw)
    b = fit_hyperparameters(X, Y, np.einsum("igh,imh->img", Q, dY), bases=Q, **kw)
    np.testing.assert_allclose(b.hyper.lengthscale, a.hyper.lengthscale, rtol=1e-5)
    np.testing.assert_allclose(b.hyper.variance, a.hyper.variance, rtol=1e-5)
    np.testing.assert_allclose(b.nll_final, a.nll_final, rtol=1e-8)
