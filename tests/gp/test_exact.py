"""gpg.gp.ExactGP against an independent dense NumPy implementation, closed forms and FD."""

import logging
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import gp as gpmod
from gpg.gp import ExactGP, FitError, FitWarning, Hyper
from gpg.linalg.dense import NotPositiveDefiniteError

# ----------------------------------------------------------------------------------------------
# Independent reference: point-major layout, closed-form blocks, dense solves.
# ----------------------------------------------------------------------------------------------


def ref_cov(x, xp, var, ls, dn, dm):
    """Cov of (f if dn is None else ∂_dn f)(x) with (f if dm is None else ∂_dm f)(xp)."""
    ls2 = np.broadcast_to(np.asarray(ls, float) ** 2, x.shape)
    d = x - xp
    k = var * np.exp(-0.5 * np.sum(d * d / ls2))
    if dn is None and dm is None:
        return k
    if dn is None:
        return d[dm] / ls2[dm] * k
    if dm is None:
        return -d[dn] / ls2[dn] * k
    return ((dn == dm) / ls2[dn] - d[dn] * d[dm] / (ls2[dn] * ls2[dm])) * k


def ref_posterior(X, Y, dY, dims, hyper, Xq):
    var = float(hyper.variance)
    ls = np.asarray(hyper.lengthscale)
    lam = np.broadcast_to(np.asarray(hyper.grad_noise), (len(dims),))
    obs = []  # (point, dim or None, noise, target row)
    for i in range(X.shape[0]):
        obs.append((i, None, float(hyper.noise), Y[i]))
        for g, d in enumerate(dims):
            obs.append((i, d, lam[g], dY[i, :, g]))
    R = len(obs)
    K = np.empty((R, R))
    for a, (i, dn, noise, _) in enumerate(obs):
        for b, (j, dm, _, _) in enumerate(obs):
            K[a, b] = ref_cov(X[i], X[j], var, ls, dn, dm)
        K[a, a] += noise
    T = np.array([o[3] for o in obs])
    Kq = np.array([[ref_cov(xq, X[j], var, ls, None, dm) for (j, dm, _, _) in obs] for xq in Xq])
    mean = Kq @ np.linalg.solve(K, T)
    v = var - np.einsum("qr,rq->q", Kq, np.linalg.solve(K, Kq.T))
    return mean, v, K


@pytest.fixture
def problem(rng):
    N, D, M = 25, 3, 2
    X = rng.uniform(-1, 1, (N, D))
    W = rng.normal(size=(D, M))
    Y = np.sin(X @ W)
    dims = (0, 2)
    dY = np.stack([np.cos(X @ W) * W[d] for d in dims], axis=-1)  # (N, M, G)
    hyper = Hyper(
        variance=1.3,
        lengthscale=np.array([0.6, 0.9, 0.7]),
        noise=1e-6,
        grad_noise=np.array([1e-4, 3e-4]),
    )
    Xq = rng.uniform(-1.2, 1.2, (7, D))
    return X, Y, dY, dims, hyper, Xq


def test_gram_symmetric_positive_definite(problem):
    X, _, _, dims, hyper, _ = problem
    K = gpmod.assemble_gram(jnp.asarray(X), hyper, dims, chunk_rows=8)  # several chunks
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-14)
    assert np.linalg.eigvalsh(K).min() > 0


def test_matches_numpy_reference(problem):
    X, Y, dY, dims, hyper, Xq = problem
    model = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    mean, var = model.predict(Xq)
    ref_mean, ref_var, K = ref_posterior(X, Y, dY, dims, hyper, Xq)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(var, ref_var, rtol=1e-9, atol=1e-12)
    # The log marginal likelihood as well, from the reference's own point-major K̄ and targets
    # (rows y_i, ∂_{dims[0]} y_i, ∂_{dims[1]} y_i, … per point): Σ_m log N(T_m | 0, K).
    M = Y.shape[1]
    Tp = np.concatenate([Y[:, None, :], np.moveaxis(dY, 2, 1)], axis=1).reshape(-1, M)
    sign, logdet = np.linalg.slogdet(K)
    assert sign > 0
    want = (
        -0.5 * np.sum(Tp * np.linalg.solve(K, Tp))
        - 0.5 * M * logdet
        - 0.5 * M * Tp.shape[0] * np.log(2 * np.pi)
    )
    T = np.concatenate([Y, np.moveaxis(dY, 2, 0).reshape(-1, M)])  # gpg's block-major layout
    np.testing.assert_allclose(model.log_marginal_likelihood, want, rtol=1e-9)
    np.testing.assert_allclose(
        gpmod.log_marginal_likelihood(jnp.asarray(X), jnp.asarray(T), hyper, dims), want, rtol=1e-9
    )


def test_no_gradient_dims_is_plain_gp(problem):
    X, Y, dY, _, hyper, Xq = problem
    plain = ExactGP.fit(X, Y, hyper=hyper)
    empty = ExactGP.fit(X, Y, dY[:, :, :0], grad_dims=(), hyper=hyper)
    m0, v0 = plain.predict(Xq)
    m1, v1 = empty.predict(Xq)
    np.testing.assert_array_equal(m0, m1)
    np.testing.assert_array_equal(v0, v1)
    # Plain GP textbook formula (Rasmussen & Williams Eq. 2.25-2.26).
    ls2 = np.asarray(hyper.lengthscale) ** 2
    k = lambda A, B: 1.3 * np.exp(-0.5 * (((A[:, None] - B[None]) ** 2) / ls2).sum(-1))  # noqa: E731
    K = k(X, X) + 1e-6 * np.eye(len(X))
    np.testing.assert_allclose(m0, k(Xq, X) @ np.linalg.solve(K, Y), rtol=1e-9, atol=1e-12)
    ref_v = 1.3 - np.einsum("qn,nq->q", k(Xq, X), np.linalg.solve(K, k(X, Xq)))
    np.testing.assert_allclose(v0, ref_v, rtol=1e-9, atol=1e-12)


def test_interpolates_values_and_gradients(rng):
    X = rng.uniform(-1, 1, (30, 2))
    Y = np.sin(3 * X[:, 0]) + X[:, 1] ** 2
    dY = np.stack([3 * np.cos(3 * X[:, 0]), 2 * X[:, 1]], axis=1)[:, None, :]
    model = ExactGP.fit(X, Y, dY, hyper=Hyper(1.0, 0.5, noise=1e-10, grad_noise=1e-10))
    mean, var = model.predict(X)
    np.testing.assert_allclose(mean[:, 0], Y, atol=1e-5)
    assert np.all(np.asarray(var) < 1e-6)
    np.testing.assert_allclose(model.predict_gradient(X)[:, 0, :], dY[:, 0, :], atol=1e-4)


def test_predicted_gradient_matches_finite_differences(problem):
    X, Y, dY, dims, hyper, Xq = problem
    model = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    grad = np.asarray(model.predict_gradient(Xq))  # (Q, M, D)
    h = 1e-6
    for d in range(X.shape[1]):
        e = np.zeros(X.shape[1])
        e[d] = h
        fd = (model.predict_mean(Xq + e) - model.predict_mean(Xq - e)) / (2 * h)
        np.testing.assert_allclose(grad[:, :, d], fd, rtol=1e-6, atol=1e-8)


def test_likelihood_gradient_finite_differences(problem):
    X, Y, dY, dims, hyper, _ = problem
    T = jnp.asarray(np.concatenate([Y, np.moveaxis(dY, 2, 0).reshape(-1, 2)]))
    Xj = jnp.asarray(X)

    def f(theta):
        h = Hyper(jnp.exp(theta[0]), jnp.exp(theta[1:4]), 1e-6, jnp.exp(theta[4:6]))
        return gpmod.log_marginal_likelihood(Xj, T, h, dims)

    theta = jnp.log(jnp.array([1.3, 0.6, 0.9, 0.7, 1e-3, 3e-3]))
    g = np.asarray(jax.grad(f)(theta))
    eps = 1e-5
    fd = np.array(
        [(f(theta.at[i].add(eps)) - f(theta.at[i].add(-eps))) / (2 * eps) for i in range(6)]
    )
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def test_fit_recovers_prior_hyperparameters():
    """Data drawn from the GP-G prior: BFGS finds the generating σ and l (loose tolerance).

    The nugget is fitted too; the truth's ν²/σ = 5e-6 is above the fit's floor (1e-6): a
    floor above the truth is binding and moves σ (the likelihood is that sharp in ν²)."""
    rng = np.random.default_rng(7)
    N, D = 150, 2
    true = Hyper(variance=2.0, lengthscale=np.array([0.4, 0.8]), noise=1e-5, grad_noise=1e-4)
    X = rng.uniform(-1, 1, (N, D))
    K = gpmod.assemble_gram(jnp.asarray(X), true, (0, 1))
    draws = np.linalg.cholesky(K) @ rng.standard_normal((K.shape[0], 3))  # M = 3 outputs
    Y = draws[:N]
    dY = np.stack([draws[N : 2 * N], draws[2 * N :]], axis=-1)
    res = gpmod.fit_hyperparameters(
        X, Y, dY, init=Hyper(1.0, 1.0, noise=1e-6, grad_noise=1e-4), subset_size=None
    )
    assert res.converged, res.message
    assert res.nll_final < res.nll_initial
    np.testing.assert_allclose(res.hyper.variance, 2.0, rtol=0.35)
    np.testing.assert_allclose(res.hyper.lengthscale, [0.4, 0.8], rtol=0.2)


def test_fit_recovers_a_known_nugget():
    """Values with noise ν² = 0.05σ and gradients: the joint fit finds ν² within 30 %."""
    rng = np.random.default_rng(8)
    N, D = 150, 2
    true = Hyper(variance=1.5, lengthscale=np.array([0.5, 0.7]), noise=0.075, grad_noise=1e-4)
    X = rng.uniform(-1, 1, (N, D))
    K = gpmod.assemble_gram(jnp.asarray(X), true, (0, 1))
    draws = np.linalg.cholesky(K) @ rng.standard_normal((K.shape[0], 4))
    res = gpmod.fit_hyperparameters(
        X,
        draws[:N],
        np.stack([draws[N : 2 * N], draws[2 * N :]], axis=-1),
        init=Hyper(1.0, 1.0, noise=1e-8, grad_noise=1e-4),
        subset_size=None,
    )
    assert res.converged and res.noise_fitted, res.message
    np.testing.assert_allclose(res.hyper.noise, 0.075, rtol=0.3)
    np.testing.assert_allclose(res.noise_ratio, 0.05, rtol=0.35)
    np.testing.assert_allclose(res.hyper.lengthscale, [0.5, 0.7], rtol=0.2)


def test_fixed_nugget_stays_and_floor_holds(problem):
    X, Y, dY, dims = problem[:4]
    fixed = gpmod.fit_hyperparameters(
        X,
        Y,
        dY,
        grad_dims=dims,
        fit_noise=False,
        init=Hyper(noise=3e-4),
        max_steps=30,
        on_failure="ignore",
    )
    assert float(fixed.hyper.noise) == 3e-4 and not fixed.noise_fitted
    # Noise-free data push ν² down; the bound ν² ≥ floor·σ holds exactly.
    floor = gpmod.fit_hyperparameters(
        X, Y, dY, grad_dims=dims, noise_floor=1e-3, max_steps=60, on_failure="ignore"
    )
    assert floor.noise_ratio >= 1e-3 * (1 - 1e-12)
    with pytest.raises(ValueError, match="noise_floor < noise_init"):
        gpmod.fit_hyperparameters(X, Y, dY, grad_dims=dims, noise_floor=0.1, noise_init=0.01)


def test_fit_grad_noise_scale_and_subset(problem):
    X, Y, dY, dims, _, _ = problem
    init = Hyper(1.0, 1.0, noise=1e-6, grad_noise=gpmod.gradient_noise(dY, s=0.3))
    res = gpmod.fit_hyperparameters(
        X, Y, dY, grad_dims=dims, init=init, fit_grad_noise=True, subset_size=20, seed=3
    )
    assert res.subset.shape == (20,) and len(np.unique(res.subset)) == 20
    assert res.grad_noise_scale is not None
    # The fit ran to convergence and improved the likelihood; the gradients are exact, so the
    # fitted noise scale falls below the initial s = 0.3.
    assert res.converged, res.message
    assert res.nll_final < res.nll_initial
    assert res.grad_noise_scale < 0.3
    np.testing.assert_allclose(
        res.hyper.grad_noise, res.grad_noise_scale * gpmod.gradient_noise(dY, s=1.0), rtol=1e-12
    )


def test_fit_failure_is_reported(problem):
    X, Y, dY, dims, _, _ = problem
    with pytest.warns(FitWarning, match="did not converge"):
        res = gpmod.fit_hyperparameters(X, Y, dY, grad_dims=dims, max_steps=2)
    assert not res.converged and "maximum number of steps" in res.message
    with pytest.raises(FitError):
        gpmod.fit_hyperparameters(X, Y, dY, grad_dims=dims, max_steps=2, on_failure="raise")


def test_gradient_noise_rule(rng):
    dY = rng.normal(size=(40, 9, 7)) * np.arange(1, 8)
    want = 0.3 * np.array([np.var(dY[:, :, i]) for i in range(7)])
    np.testing.assert_allclose(gpmod.gradient_noise(dY, 0.3), want, rtol=1e-12)


def test_jit_equals_eager_and_traces_once(problem, caplog):
    X, Y, dY, dims, hyper, Xq = problem
    model = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    with jax.disable_jit():
        m_eager, v_eager = model.predict(Xq)
    m_jit, v_jit = model.predict(Xq)
    np.testing.assert_allclose(m_jit, m_eager, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(v_jit, v_eager, rtol=1e-10, atol=1e-14)
    other = np.asarray(Xq) * 0.5
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        for q in (Xq, other, Xq + 0.1, other - 0.1):
            model.predict(q)
    compiles = [r for r in caplog.records if "Compiling jit(_batch)" in r.getMessage()]
    assert len(compiles) <= 1  # zero if an earlier test compiled the same shapes


def test_vmap_over_batches(problem):
    X, Y, dY, dims, hyper, Xq = problem
    model = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    batch = jnp.stack([jnp.asarray(Xq), jnp.asarray(Xq[::-1])])
    mb, vb = jax.vmap(model.predict)(batch)
    for b in range(2):
        m, v = model.predict(batch[b])
        np.testing.assert_allclose(mb[b], m, rtol=1e-12)
        np.testing.assert_allclose(vb[b], v, rtol=1e-9, atol=1e-14)


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda X, Y, dY: (X, Y[:-1], dY), "Y has 24 rows"),
        (lambda X, Y, dY: (X, Y, dY[:, :1]), "dY must have shape"),
        (lambda X, Y, dY: (X[:, :, None], Y, dY), "X must have 2 dimensions"),
        (
            lambda X, Y, dY: (np.where(np.arange(25)[:, None] == 4, np.nan, X), Y, dY),
            "X holds NaN or inf in 1 row.*: 4",
        ),
        (
            lambda X, Y, dY: (X, np.where(np.arange(25)[:, None] == 9, np.inf, Y), dY),
            "Y holds NaN or inf.*: 9",
        ),
        (
            lambda X, Y, dY: (X, Y, np.where(np.arange(25)[:, None, None] == 3, np.nan, dY)),
            "dY holds NaN or inf.*: 3",
        ),
    ],
)
def test_bad_training_data(problem, mutate, match):
    X, Y, dY, dims, hyper, _ = problem
    X, Y, dY = mutate(X, Y, dY)
    with pytest.raises(ValueError, match=match):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)


@pytest.mark.parametrize(
    "dims, match", [((0, 3), "out of range"), ((0,), "names 1 dims"), ((1, 1), "repeats")]
)
def test_bad_grad_dims(problem, dims, match):
    X, Y, dY, _, hyper, _ = problem
    with pytest.raises(ValueError, match=match):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)


def test_gradients_without_dims_need_all_inputs(problem):
    X, Y, dY, _, hyper, _ = problem
    with pytest.raises(ValueError, match="pass grad_dims"):
        ExactGP.fit(X, Y, dY, hyper=hyper)
    with pytest.raises(ValueError, match="dY is None"):
        ExactGP.fit(X, Y, grad_dims=(0,), hyper=hyper)


@pytest.mark.parametrize(
    "field, value",
    [
        ("variance", 0.0),
        ("variance", -1.0),
        ("lengthscale", np.array([0.5, -0.1, 1.0])),
        ("noise", 0.0),
        ("grad_noise", np.array([1e-3, 0.0])),
        ("lengthscale", np.nan),
    ],
)
def test_non_positive_hyperparameters(problem, field, value):
    X, Y, dY, dims, hyper, _ = problem
    kwargs = dict(
        variance=hyper.variance,
        lengthscale=hyper.lengthscale,
        noise=hyper.noise,
        grad_noise=hyper.grad_noise,
    )
    kwargs[field] = value
    with pytest.raises(ValueError, match=f"hyper.{field}"):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=Hyper(**kwargs))


def test_hyper_shapes(problem):
    X, Y, dY, dims, _, _ = problem
    with pytest.raises(ValueError, match="hyper.lengthscale must be a scalar or have shape"):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=Hyper(lengthscale=np.ones(2)))
    with pytest.raises(ValueError, match="hyper.grad_noise"):
        ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=Hyper(grad_noise=np.ones(3)))


def test_not_positive_definite_is_reported():
    X = np.zeros((3, 2))  # three identical points, essentially no noise
    with pytest.raises(NotPositiveDefiniteError, match="not numerically positive definite"):
        ExactGP.fit(X, np.ones(3), hyper=Hyper(noise=1e-300))


def test_bad_queries(problem):
    X, Y, dY, dims, hyper, _ = problem
    model = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    with pytest.raises(ValueError, match=r"Xq must have shape \(Q, 3\)"):
        model.predict(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"Xq must have shape"):
        model.predict(np.zeros(3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(RuntimeError, match="Xq holds NaN or inf"):
            model.predict(np.array([[0.0, np.nan, 0.0]]))


def test_row_noise_is_each_case_own_value_noise(problem, rng):
    """``row_noise`` (heteroscedastic labels): the posterior and the likelihood of ``K + diag(ν²
    + n_i)`` on values, against the dense NumPy reference; with gradients, only value rows
    take it."""
    X, Y, dY, dims, hyper, Xq = problem
    n = X.shape[0]
    rn = rng.uniform(0.01, 0.2, n)
    gp = ExactGP.fit(X, Y, hyper=hyper, row_noise=rn)
    var0, ls = float(hyper.variance), np.asarray(hyper.lengthscale)
    K = np.array([[ref_cov(a, b, var0, ls, None, None) for b in X] for a in X])
    K = K + np.diag(float(hyper.noise) + rn)
    Kq = np.array([[ref_cov(xq, b, var0, ls, None, None) for b in X] for xq in Xq])
    mean, var = gp.predict_unclipped(Xq)
    np.testing.assert_allclose(mean, Kq @ np.linalg.solve(K, Y), rtol=1e-9, atol=1e-12)
    ref_var = float(hyper.variance) - np.einsum("qr,rq->q", Kq, np.linalg.solve(K, Kq.T))
    np.testing.assert_allclose(var, ref_var, rtol=1e-9, atol=1e-12)
    sign, logdet = np.linalg.slogdet(K)
    ref_lml = sum(
        -0.5 * Y[:, m] @ np.linalg.solve(K, Y[:, m]) - 0.5 * logdet - 0.5 * n * np.log(2 * np.pi)
        for m in range(Y.shape[1])
    )
    np.testing.assert_allclose(float(gp.log_marginal_likelihood), ref_lml, rtol=1e-10)
    lml = gpmod.log_marginal_likelihood(
        jnp.asarray(X), jnp.asarray(Y), hyper, (), row_noise=jnp.asarray(rn)
    )
    np.testing.assert_allclose(float(lml), ref_lml, rtol=1e-10)
    # with gradient rows: the value rows take it, the gradient rows keep λ²
    gpg_ = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper, row_noise=rn)
    _, _, Kg = ref_posterior(X, Y, dY, dims, hyper, Xq)
    values = np.arange(Kg.shape[0]) % (1 + len(dims)) == 0  # point-major: value row first
    Kg[np.flatnonzero(values), np.flatnonzero(values)] += rn
    sign, logdet = np.linalg.slogdet(Kg)
    T = np.concatenate([np.concatenate([Y[i][None], dY[i].T]) for i in range(n)])
    ref_g = sum(
        -0.5 * T[:, m] @ np.linalg.solve(Kg, T[:, m])
        - 0.5 * logdet
        - 0.5 * Kg.shape[0] * np.log(2 * np.pi)
        for m in range(Y.shape[1])
    )
    np.testing.assert_allclose(float(gpg_.log_marginal_likelihood), ref_g, rtol=1e-9)
    with pytest.raises(ValueError, match=r"row_noise must have shape \(25,\)"):
        ExactGP.fit(X, Y, hyper=hyper, row_noise=rn[:3])
    with pytest.raises(ValueError, match="finite and >= 0"):
        ExactGP.fit(X, Y, hyper=hyper, row_noise=-rn)
    with pytest.raises(ValueError, match="row_noise"):
        gpmod.fit_hyperparameters(X, Y, row_noise=rn[:3])
