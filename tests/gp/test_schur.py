"""Schur precompute: global and direct routes agree; one bin and ε → 0 give the exact GP-G;
the k_qf = 0 mean/variance match an independent dense computation; local = GP on the near set."""

import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import ExactGP, Hyper, assemble_gram, local, partition, schur, stack_targets
from gpg.gp.binned import pack


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(11)
    N, D, M = 48, 3, 2
    X = rng.uniform(-1, 1, (N, D))
    W = rng.normal(size=(D, M))
    Y = np.sin(X @ W)
    dims = (0, 2)
    dY = np.stack([np.cos(X @ W) * W[d] for d in dims], axis=-1)
    hyper = Hyper(1.2, np.array([0.5, 0.8, 0.6]), 1e-6, np.array([1e-3, 2e-3]))
    Xq = rng.uniform(-1, 1, (30, D))
    return X, Y, dY, dims, hyper, Xq


def binned(problem, n_bins=4, route="global", mean="exact", **near):
    X, Y, dY, dims, hyper, _ = problem
    part = partition.slab(X, n_bins, dim=0)
    ns = partition.near_sets(X, part, hyper.lengthscale, **(near or {"budget": 0.4}))
    Ybar = stack_targets(Y, dY)
    if route == "local":  # no Schur correction: gpg.gp.local
        f = local.precompute(X, Ybar, hyper, dims, ns)
    else:
        f = schur.precompute(X, Ybar, hyper, dims, ns, route=route, mean=mean)
    return pack(X, f, ns, part, hyper, dims), f, ns


@pytest.mark.parametrize("mean", ["exact", "paper"])
def test_global_and_direct_routes_agree(problem, mean):
    _, fg, _ = binned(problem, route="global", mean=mean)
    _, fd, _ = binned(problem, route="direct", mean=mean)
    for a, b in zip(fg, fd, strict=True):
        Sa, Sb = a.factor.T @ a.factor, b.factor.T @ b.factor  # both equal S⁻¹
        np.testing.assert_allclose(Sa, Sb, rtol=1e-8, atol=1e-8 * np.abs(Sb).max())
        np.testing.assert_allclose(a.coef, b.coef, rtol=1e-8, atol=1e-8 * np.abs(b.coef).max())


def test_one_bin_is_exact_gpg(problem):
    X, Y, dY, dims, hyper, Xq = problem
    exact = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    for mean in ("exact", "paper"):
        model, _, ns = binned(problem, n_bins=1, mean=mean)
        assert ns.near[0].size == X.shape[0]
        m, v = model.predict(Xq)
        me, ve = exact.predict(Xq)
        np.testing.assert_allclose(m, me, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(v, ve, rtol=1e-7, atol=1e-10)


def test_epsilon_to_zero_is_exact_gpg(problem):
    X, Y, dY, dims, hyper, Xq = problem
    exact = ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)
    model, _, ns = binned(problem, n_bins=4, epsilon=1e-300)
    assert np.all(ns.fraction == 1.0)
    m, v = model.predict(Xq)
    me, ve = exact.predict(Xq)
    np.testing.assert_allclose(m, me, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(v, ve, rtol=1e-7, atol=1e-10)


def dense_reference(problem, ns, part, mean):
    """k_qf = 0 with an explicit inverse of K̄, written out independently."""
    X, Y, dY, dims, hyper, Xq = problem
    N, G = X.shape[0], len(dims)
    ls2 = np.asarray(hyper.lengthscale) ** 2
    var = float(hyper.variance)
    K = np.asarray(assemble_gram(jnp.asarray(X), hyper, dims))
    Kinv = np.linalg.inv(K)
    T = np.concatenate([Y] + [dY[:, :, g] for g in range(G)])
    alpha = Kinv @ T
    bins = np.asarray(part.lookup_batch(jnp.asarray(Xq)))
    means, vars_ = [], []
    for q, b in zip(Xq, bins, strict=True):
        nb = ns.near[b]
        rows = np.concatenate([nb + k * N for k in range(1 + G)])
        d = q[None] - X[nb]
        k0 = var * np.exp(-0.5 * np.sum(d * d / ls2, 1))
        kq = np.concatenate([k0] + [d[:, dd] / ls2[dd] * k0 for dd in dims])  # Cov(f(q), ∂f(x))
        Sinv = Kinv[np.ix_(rows, rows)]
        coef = alpha[rows] if mean == "exact" else Sinv @ T[rows]
        means.append(kq @ coef)
        vars_.append(var - kq @ Sinv @ kq)
    return np.array(means), np.array(vars_)


@pytest.mark.parametrize("mean", ["exact", "paper"])
def test_matches_dense_computation_with_kqf_zero(problem, mean):
    model, _, ns = binned(problem, mean=mean)
    m, v = model.predict(problem[5])
    rm, rv = dense_reference(problem, ns, model.partition, mean)
    np.testing.assert_allclose(m, rm, rtol=1e-7, atol=1e-7 * np.abs(rm).max())
    np.testing.assert_allclose(
        v, np.maximum(rv, 0), rtol=1e-6, atol=1e-6 * max(1.0, np.abs(rv).max())
    )


def test_local_precompute_is_gp_on_the_near_set(problem):
    X, Y, dY, dims, hyper, Xq = problem
    model, _, ns = binned(problem, route="local")
    bins = np.asarray(model.partition.lookup_batch(jnp.asarray(Xq)))
    m, v = model.predict(Xq)
    for b in range(ns.n_bins):
        local = ExactGP.fit(
            X[ns.near[b]], Y[ns.near[b]], dY[ns.near[b]], grad_dims=dims, hyper=hyper
        )
        sel = bins == b
        if sel.any():
            lm, lv = local.predict(Xq[sel])
            np.testing.assert_allclose(m[sel], lm, rtol=1e-8, atol=1e-10)
            np.testing.assert_allclose(v[sel], lv, rtol=1e-7, atol=1e-10)


def test_batched_variance_rule_matches_single_queries(problem):
    model, _, _ = binned(problem)
    m, v = model.predict_unclipped(problem[5])  # vmap: per-bin matrix products
    for i, q in enumerate(problem[5][:8]):
        mi, vi = model.mean_var_one(jnp.asarray(q))  # one query: a switch on the bin
        np.testing.assert_allclose(mi, m[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(vi, v[i], rtol=1e-10, atol=1e-12)


def test_bad_options(problem):
    X, Y, dY, dims, hyper, _ = problem
    ns = partition.near_sets(X, partition.slab(X, 2, dim=0), hyper.lengthscale, budget=0.5)
    with pytest.raises(
        ValueError, match=r"unknown mean form 'median'; valid: \['exact', 'paper'\]"
    ):
        schur.precompute(X, stack_targets(Y, dY), hyper, dims, ns, mean="median")
    with pytest.raises(ValueError, match=r"unknown precompute route 'lu'"):
        schur.precompute(X, stack_targets(Y, dY), hyper, dims, ns, route="lu")
    with pytest.raises(ValueError, match=r"route 'local'.*no Schur correction is gpg.gp.local"):
        schur.precompute(X, stack_targets(Y, dY), hyper, dims, ns, route="local")


def test_diagnostics_flag_a_correlated_far_set(problem):
    """Long lengthscales on uniform inputs: far points correlate strongly with the bins."""
    X = problem[0]
    part = partition.slab(X, 4, dim=0)
    ls = np.full(3, 2.0)
    ns = partition.near_sets(X, part, ls, budget=0.3)
    with pytest.warns(schur.SchurAssumptionWarning, match="median query's most correlated"):
        d = schur.diagnose(X, part, ns, ls)
    assert d["kqf_violated"] and d["far_correlation_median"] > 0.5
    assert d["far_correlation_p90"] >= d["far_correlation_median"]


def test_diagnostics_silent_when_the_far_set_is_far(rng, recwarn):
    """Two clusters far apart at a short lengthscale: each bin's far set is the other cluster."""
    X = np.concatenate([rng.normal(-0.8, 0.05, (20, 2)), rng.normal(0.8, 0.05, (20, 2))])
    part = partition.slab(X, 2, dim=0)
    ls = np.full(2, 0.1)
    ns = partition.near_sets(X, part, ls, budget=0.5)
    d = schur.diagnose(X, part, ns, ls)
    assert not d["kqf_violated"] and d["far_correlation_max"] < 1e-20
    assert not [w for w in recwarn if issubclass(w.category, schur.SchurAssumptionWarning)]


def test_schur_model_reports_diagnostics(problem):
    """Built models carry the measurement; predict_unclipped exposes negative variances."""
    model, _, ns = binned(problem, n_bins=4)
    _, v = model.predict_unclipped(problem[5])
    _, vc = model.predict(problem[5])
    np.testing.assert_array_equal(np.asarray(vc), np.maximum(np.asarray(v), 0.0))
