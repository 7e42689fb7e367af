"""The bordered Cholesky update (gpg.gp.update) and partial gradients: conditioning equals a
refit with the same hyperparameters; two steps equal one; a case without some gradients equals
the GP on its other rows."""

import numpy as np
import pytest

from gpg.gp import kernels
from gpg.gp.exact import ExactGP
from gpg.gp.hyper import Hyper

DIMS = (0, 2)
H = Hyper(variance=1.3, lengthscale=np.array([0.7, 0.8, 0.9]), noise=1e-4,
          grad_noise=np.array([1e-4, 2e-4]))  # fmt: skip
TOL = 1e-10  # normalised mean and variance; measured 5e-14


def f(X):
    return np.stack([np.sin(X @ [1.0, 2.0, 0.5]), np.cos(X @ [0.3, 1.0, 1.0])], 1)


def df(X):
    a = np.cos(X @ [1.0, 2.0, 0.5])[:, None] * np.array([1.0, 2.0, 0.5])
    b = -np.sin(X @ [0.3, 1.0, 1.0])[:, None] * np.array([0.3, 1.0, 1.0])
    return np.stack([a, b], 1)[:, :, list(DIMS)]


def data(seed, n):
    X = np.random.default_rng(seed).uniform(-1, 1, (n, 3))
    return X, f(X), df(X)


def close(a, b):
    Q = np.random.default_rng(9).uniform(-1, 1, (40, 3))
    (ma, va), (mb, vb) = a.predict(Q), b.predict(Q)
    np.testing.assert_allclose(ma, mb, atol=TOL)
    np.testing.assert_allclose(va, vb, atol=TOL)
    np.testing.assert_allclose(a.output_scale, b.output_scale, rtol=1e-10)
    assert float(a.log_marginal_likelihood) == pytest.approx(
        float(b.log_marginal_likelihood), rel=1e-10
    )


@pytest.mark.parametrize("with_gradients", [True, False])
@pytest.mark.parametrize("n_new", [1, 6])
def test_condition_equals_refit(with_gradients, n_new):
    X, Y, dY = data(0, 25)
    Xn, Yn, dYn = data(1, n_new)
    if not with_gradients:
        m = ExactGP.fit(X, Y, hyper=H).condition(Xn, Yn)
        close(m, ExactGP.fit(np.r_[X, Xn], np.r_[Y, Yn], hyper=H))
        return
    m = ExactGP.fit(X, Y, dY, grad_dims=DIMS, hyper=H).condition(Xn, Yn, dYn)
    close(m, ExactGP.fit(np.r_[X, Xn], np.r_[Y, Yn], np.r_[dY, dYn], grad_dims=DIMS, hyper=H))


def test_two_steps_equal_one_and_partial_gradients():
    X, Y, dY = data(0, 25)
    Xn, Yn, dYn = data(1, 7)
    rng = np.random.default_rng(2)
    obs, obs_n = rng.random((25, 2)) > 0.3, rng.random((7, 2)) > 0.5
    base = ExactGP.fit(X, Y, dY, grad_dims=DIMS, hyper=H, observed=obs)
    once = base.condition(Xn, Yn, dYn, observed=obs_n)
    twice = base.condition(Xn[:3], Yn[:3], dYn[:3], observed=obs_n[:3]).condition(
        Xn[3:], Yn[3:], dYn[3:], observed=obs_n[3:]
    )
    all_obs = np.r_[obs, obs_n]
    dY_all = np.r_[dY, dYn]
    dY_all[~all_obs[:, None, :].repeat(2, 1)] = np.nan  # never read where not observed
    refit = ExactGP.fit(np.r_[X, Xn], np.r_[Y, Yn], dY_all, grad_dims=DIMS, hyper=H,
                        observed=all_obs)  # fmt: skip
    close(once, refit)
    close(twice, refit)


def test_unobserved_gradients_are_the_gp_without_those_rows():
    """Against a dense NumPy posterior written here on the observed rows only."""
    X, Y, dY = data(3, 15)
    obs = np.random.default_rng(4).random((15, 2)) > 0.5
    m = ExactGP.fit(X, Y, dY, grad_dims=DIMS, hyper=H, observed=obs)
    rows = np.r_[np.ones(15, bool), obs.T.ravel()]
    K = np.asarray(kernels.gram(X, X, 1.3, H.lengthscale, DIMS, DIMS))[np.ix_(rows, rows)]
    K += np.diag(np.r_[np.full(15, 1e-4), np.full(15, 1e-4), np.full(15, 2e-4)][rows])
    Ybar = np.r_[Y, dY[:, :, 0], dY[:, :, 1]][rows]
    Q = np.random.default_rng(5).uniform(-1, 1, (20, 3))
    kq = np.asarray(kernels.gram(Q, X, 1.3, H.lengthscale, (), DIMS))[:, rows]
    mean, var = m.predict(Q)
    np.testing.assert_allclose(mean, kq @ np.linalg.solve(K, Ybar), atol=1e-9)
    np.testing.assert_allclose(var, 1.3 - np.sum(kq * np.linalg.solve(K, kq.T).T, 1), atol=1e-9)
    # Only the observed rows are factorised: a values-only case is one row, not 1 + G.
    assert m.chol_inv.n == rows.sum() < rows.size
    lml = sum(
        -0.5 * Ybar[:, j] @ np.linalg.solve(K, Ybar[:, j])
        - 0.5 * np.linalg.slogdet(K)[1]
        - 0.5 * rows.sum() * np.log(2 * np.pi)
        for j in range(2)
    )
    assert float(m.log_marginal_likelihood) == pytest.approx(lml, rel=1e-10)
    from gpg.gp.gram import log_marginal_likelihood

    Ybar_layout = np.r_[Y, np.where(obs[:, None, :], dY, 0.0).transpose(2, 0, 1).reshape(-1, 2)]
    assert float(log_marginal_likelihood(X, Ybar_layout, H, DIMS, rows)) == pytest.approx(
        lml, rel=1e-10
    )


def test_a_decoupled_factor_of_format_8_still_conditions():
    """Files of format 7 and 8 kept the unobserved rows in the factor, decoupled (identity
    rows in K̄, zero columns in L⁻¹, no ``order``): conditioning one equals the refit."""
    import equinox as eqx

    from gpg.gp.gram import assemble_gram, mask_gram_inplace, observed_rows
    from gpg.linalg.tri import BlockTriangular

    X, Y, dY = data(3, 15)
    Xn, Yn, dYn = data(6, 4)
    obs = np.random.default_rng(4).random((15, 2)) > 0.5
    compact = ExactGP.fit(X, Y, dY, grad_dims=DIMS, hyper=H, observed=obs)
    rows = observed_rows(obs, 15)
    K = mask_gram_inplace(assemble_gram(X, H, DIMS), rows)
    Linv = np.linalg.inv(np.linalg.cholesky(K))
    Linv[:, ~rows] = 0.0
    legacy = eqx.tree_at(
        lambda t: (t.chol_inv, t.order),
        compact,
        (BlockTriangular.from_dense(Linv, lower=True, n_blocks=2), None),
        is_leaf=lambda x: x is None,
    )
    close(legacy, compact)
    dY_all = np.r_[dY, dYn]
    dY_all[~np.r_[obs, np.ones((4, 2), bool)][:, None, :].repeat(2, 1)] = np.nan
    refit = ExactGP.fit(np.r_[X, Xn], np.r_[Y, Yn], dY_all, grad_dims=DIMS, hyper=H,
                        observed=np.r_[obs, np.ones((4, 2), bool)])  # fmt: skip
    close(legacy.condition(Xn, Yn, dYn), refit)


def test_bad_new_cases_are_refused():
    X, Y, dY = data(0, 10)
    m = ExactGP.fit(X, Y, dY, grad_dims=DIMS, hyper=H)
    with pytest.raises(ValueError, match="X has 2 inputs but the model has 3"):
        m.condition(X[:2, :2], Y[:2])
    with pytest.raises(ValueError, match="Y has 1 outputs but the model has 2"):
        m.condition(X[:2] + 0.1, Y[:2, :1])
    with pytest.raises(ValueError, match="NaN or inf"):
        m.condition(np.full((1, 3), np.nan), Y[:1])
    values = ExactGP.fit(X, Y, hyper=H)
    with pytest.raises(ValueError, match="fitted without gradient"):
        values.condition(X[:1] + 0.1, Y[:1], dY[:1])
