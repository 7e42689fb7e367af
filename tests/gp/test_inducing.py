"""The inducing-point GP against the exact GP (every case inducing) and a NumPy reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp.exact import ExactGP
from gpg.gp.fit import fit_hyperparameters
from gpg.gp.hyper import Hyper
from gpg.gp.inducing import (
    JITTER,
    TRI_BANDS,
    InducingGP,
    StackedInducing,
    collapsed_bound,
    fit_collapsed,
    inducing_inputs,
    project,
)
from gpg.gp.likelihood import log_marginal_likelihood

HYPER = Hyper(variance=0.8, lengthscale=np.array([0.7, 0.9, 1.2]), noise=1e-2)


def _data(rng, n=60):
    X = rng.uniform(-1, 1, (n, 3))
    y = np.sin(2 * X[:, 0]) + X[:, 1] * X[:, 2] + 0.05 * rng.normal(size=n)
    return X, y, rng.uniform(1e-3, 2e-2, n)


def _reference(X, y, noise, Z, Xq):
    """The projected process in NumPy, from its textbook form (R&W eq. 8.26-8.27)."""
    ls, s = np.asarray(HYPER.lengthscale), float(HYPER.variance)

    def k(A, B):
        d2 = (((A[:, None, :] - B[None, :, :]) / ls) ** 2).sum(-1)
        return s * np.exp(-0.5 * d2)

    Kmm = k(Z, Z) + JITTER * s * np.eye(len(Z))
    Kmn, Kqm = k(Z, X), k(Xq, Z)
    lam = float(HYPER.noise) + noise
    Sigma = np.linalg.inv(Kmm + (Kmn / lam) @ Kmn.T)
    mean = Kqm @ Sigma @ (Kmn @ (y / lam))
    var = s - np.einsum("qm,mn,qn->q", Kqm, np.linalg.inv(Kmm) - Sigma, Kqm)
    Kt = Kmn.T @ np.linalg.solve(Kmm, Kmn) + np.diag(lam)
    return mean, var, Kt


def test_every_case_inducing_is_the_exact_gp(rng):
    X, y, noise = _data(rng)
    # the flight correction's discrepancies keep unit output scales (the fitted σ is theirs)
    exact = ExactGP.fit(X, y[:, None], hyper=HYPER, row_noise=noise).with_output_scale([1.0])
    ind = InducingGP.fit(X, y, X, hyper=HYPER, row_noise=noise)
    Xq = rng.uniform(-1.2, 1.2, (25, 3))
    me, ve = exact.predict_unclipped(Xq)
    mi, vi = ind.predict_unclipped(Xq)
    # The jitter JITTER·σ on K_mm is the only difference; with a well-conditioned K (the
    # nearest cases >= 0.05 apart on lengthscales near 1) it moves the results by
    # about cond(K_mm)·JITTER, well under 1e-4 here; the float64 rounding far below that.
    np.testing.assert_allclose(mi, me, atol=1e-4 * float(np.abs(me).max()))
    np.testing.assert_allclose(vi, ve, atol=1e-4 * float(HYPER.variance))
    np.testing.assert_allclose(exact.predictive_variance(ve), ind.predictive_variance(vi),
                               atol=1e-4)  # fmt: skip


def test_projection_matches_a_numpy_reference(rng):
    X, y, noise = _data(rng, 200)
    Z = inducing_inputs(X, 24, seed=0)
    assert Z.shape == (24, 3)
    Xq = rng.uniform(-1, 1, (20, 3))
    mean, var, Kt = _reference(X, y, noise, Z, Xq)
    H = np.column_stack([np.ones(len(X)), X[:, 0]])
    for chunk in (7, 4096):  # the cases read in chunks or at once: the same sums
        gp = InducingGP.fit(X, y, Z, hyper=HYPER, row_noise=noise, chunk=chunk)
        m, v = jax.vmap(gp.mean_var_one)(jnp.asarray(Xq))
        # Sums of 200 terms of O(1) in float64 through triangular solves of a K_mm with
        # condition number ~1e6: 1e-8 relative is a hundred times their rounding.
        np.testing.assert_allclose(m[:, 0], mean, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(v, var, rtol=1e-7, atol=1e-9)
        # its two triangles folded into one: the same reference, one product a query
        one = gp.variance_view()
        assert one.post.shape == (0, 24) and one.whiten.shape == (24, 24)
        mo, vo = jax.vmap(one.mean_var_one)(jnp.asarray(Xq))
        np.testing.assert_array_equal(mo, m)
        np.testing.assert_allclose(vo, var, rtol=1e-7, atol=1e-9)
        p = project(X, np.column_stack([H, y]), Z, hyper=HYPER, row_noise=noise, chunk=chunk)
        V = np.column_stack([H, y])
        np.testing.assert_allclose(p.gram, V.T @ np.linalg.solve(Kt, V), rtol=1e-7)
        np.testing.assert_allclose(float(p.logdet), np.linalg.slogdet(Kt)[1], rtol=1e-9)
        np.testing.assert_allclose(p.weights[:, 2], gp.weights[:, 0], rtol=1e-10, atol=1e-12)
    # the weights are linear in the targets
    lin = gp.with_weights(p.weights[:, 2:] - 0.5 * p.weights[:, :1])
    np.testing.assert_allclose(lin.predict_mean(Xq)[:, 0],
                               InducingGP.fit(X, y - 0.5, Z, hyper=HYPER, row_noise=noise)
                               .predict_mean(Xq)[:, 0], atol=1e-9)  # fmt: skip


def test_a_jax_function_and_its_mean_view(rng):
    X, y, noise = _data(rng, 80)
    gp = InducingGP.fit(X, y, inducing_inputs(X, 16), hyper=HYPER, row_noise=noise)
    x = jnp.asarray(rng.uniform(-1, 1, 3))
    f = jax.jit(lambda x: gp.mean_one(x)[0])
    g = jax.grad(f)(x)
    eps = 1e-6
    fd = [(f(x.at[i].add(eps)) - f(x.at[i].add(-eps))) / (2 * eps) for i in range(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)  # central differences, O(eps²)
    np.testing.assert_allclose(jax.jvp(f, (x,), (jnp.ones(3),))[1], g.sum(), rtol=1e-12)
    np.testing.assert_array_equal(gp.mean_view().mean_one(x), gp.mean_one(x))
    one = gp.variance_view()
    assert one.variance_view() is one  # folded once
    with pytest.raises(ValueError, match="not a mean_view"):
        gp.mean_view().variance_view()
    assert gp.describe()["inducing"] == 16 and gp.describe()["cases"] == 80


@pytest.mark.parametrize("m", [3, 13])  # fewer rows than bands; bands of unequal sizes
def test_stacked_latents_read_the_triangles_in_bands(rng, m):
    """StackedInducing keeps each folded triangle ``T`` as row bands of its non-zero columns
    only; its latent variances are the textbook projected process's (R&W eq. 8.27), and its
    means each GP's own, for a stack of GPs of one size but different data."""
    X, y, noise = _data(rng, 70)
    Z = inducing_inputs(X, m)
    gps = [InducingGP.fit(X, y * (1 + 0.5 * j), Z, hyper=HYPER, row_noise=noise) for j in range(3)]
    stack = StackedInducing.of(gps, variance=True)
    bands = [b.shape for b in stack.tri]
    assert len(bands) == min(TRI_BANDS, m)
    ends = np.cumsum([s[1] for s in bands])  # each band's rows end where its columns do
    assert ends[-1] == m and all(s[2] == c for s, c in zip(bands, ends, strict=True))
    assert StackedInducing.of(gps, variance=False).tri == ()
    Xq = rng.uniform(-1, 1, (5, 3))
    got = jax.vmap(stack.latents)(jnp.asarray(Xq))
    means = jax.vmap(stack.means)(jnp.asarray(Xq))
    for j in range(3):
        mean, var, _ = _reference(X, y * (1 + 0.5 * j), noise, np.asarray(gps[j].X), Xq)
        # the reference inverts K_mm and K_mm + K_mn Λ⁻¹ K_nm explicitly: the bounds of
        # test_projection_matches_a_numpy_reference, derived there from their conditioning
        np.testing.assert_allclose(got[:, j], var, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(means[:, j], mean, rtol=1e-8, atol=1e-9)


def test_bad_inputs_are_named(rng):
    X, y, noise = _data(rng, 20)
    with pytest.raises(ValueError, match="V must be"):
        project(X, y[:5, None], X, hyper=HYPER)
    with pytest.raises(ValueError, match="Z must be"):
        project(X, y[:, None], X[:, :2], hyper=HYPER)
    with pytest.raises(ValueError, match="row_noise must be"):
        project(X, y[:, None], X, hyper=HYPER, row_noise=noise[:3])
    with pytest.raises(ValueError, match="V holds NaN"):
        project(X, np.full((20, 1), np.nan), X, hyper=HYPER)
    with pytest.raises(ValueError, match="positive noise"):
        project(X, y[:, None], X, hyper=Hyper(noise=0.0), row_noise=-noise)
    with pytest.raises(ValueError, match="m must be"):
        inducing_inputs(X, 0)
    gp = InducingGP.fit(X, y, X[:4], hyper=HYPER)
    with pytest.raises(ValueError, match="weights must have shape"):
        gp.with_weights(np.zeros((3, 1)))


def test_collapsed_bound_matches_a_numpy_reference(rng):
    X, y, noise = _data(rng, 150)
    Z = inducing_inputs(X, 20, seed=0)
    _, _, Kt = _reference(X, y, noise, Z, X[:1])
    ls, s = np.asarray(HYPER.lengthscale), float(HYPER.variance)
    Kmn = s * np.exp(-0.5 * (((Z[:, None] - X[None]) / ls) ** 2).sum(-1))
    q = np.sum(Kmn * np.linalg.solve(_reference_kmm(Z), Kmn), 0)
    lam = float(HYPER.noise) + noise
    sign, logdet = np.linalg.slogdet(Kt)
    ref = -0.5 * (y @ np.linalg.solve(Kt, y) + logdet + len(y) * np.log(2 * np.pi))
    ref -= 0.5 * np.sum((s - q) / lam)
    for chunk in (7, 4096):
        b = collapsed_bound(X, y, Z, hyper=HYPER, row_noise=noise, chunk=chunk)
        # 150 terms of O(1..100) nats through a K_mm of condition ~1e6: 1e-9 relative.
        np.testing.assert_allclose(b, ref, rtol=1e-9)
    # Every case inducing: the trace term vanishes and the bound is the exact likelihood,
    # but for the jitter JITTER·σ on K_mm (its effect ~cond(K)·JITTER·N, under 1e-4 here).
    exact = log_marginal_likelihood(jnp.asarray(X), jnp.asarray(y[:, None]), HYPER, (),
                                    row_noise=jnp.asarray(noise))  # fmt: skip
    np.testing.assert_allclose(collapsed_bound(X, y, X, hyper=HYPER, row_noise=noise),
                               float(exact), atol=1e-4)  # fmt: skip
    # A bound: fewer inducing inputs explain the cases less, never more than the likelihood.
    assert b < float(exact)


def _reference_kmm(Z):
    ls, s = np.asarray(HYPER.lengthscale), float(HYPER.variance)
    return s * np.exp(-0.5 * (((Z[:, None] - Z[None]) / ls) ** 2).sum(-1)) + JITTER * s * np.eye(
        len(Z)
    )


def test_fit_collapsed_with_every_case_inducing_is_the_exact_fit(rng):
    X, y, noise = _data(rng, 60)
    init = Hyper(variance=0.5, lengthscale=np.full(3, 0.7), noise=5e-3)
    h, ok = fit_collapsed(X, y, X, init=init, row_noise=noise)
    dense = fit_hyperparameters(X, y[:, None], init=init, row_noise=noise, subset_size=None,
                                on_failure="raise").hyper  # fmt: skip

    def lml(h):
        return float(log_marginal_likelihood(jnp.asarray(X), jnp.asarray(y[:, None]), h, (),
                                             row_noise=jnp.asarray(noise)))  # fmt: skip

    assert ok
    # Both maximise the same function (the jitter's 1e-4 nats apart): the same maximum, and
    # the optimum's location to what a flat maximum in six parameters fixes.
    assert lml(h) > lml(init) + 1.0
    np.testing.assert_allclose(lml(h), lml(dense), atol=1e-3)
    np.testing.assert_allclose(h.lengthscale, dense.lengthscale, rtol=5e-2)
    # the start's bound is never the better one
    Z = X[::5]
    h5, _ = fit_collapsed(X, y, Z, init=init, row_noise=noise, max_steps=30)
    b = collapsed_bound(X, y, Z, hyper=h5, row_noise=noise)
    assert b >= collapsed_bound(X, y, Z, hyper=init, row_noise=noise)
    with pytest.raises(ValueError, match="init must have positive"):
        fit_collapsed(X, y, Z, init=Hyper(variance=0.0), row_noise=noise)
    with pytest.raises(ValueError, match="Z must be"):
        collapsed_bound(X, y, Z[:, :2], hyper=HYPER)
