"""The likelihood on all points without K̄ (gpg/gp/slq.py, the stochastic fit in
gpg/gp/fit.py): Lanczos quadrature against a closed form, the stochastic log likelihood and
its gradient against the dense ones, and the fit against the dense fit on the same points."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import cg, pic, slq
from gpg.gp.cg import NotConverged
from gpg.gp.fit import Stochastic, fit_hyperparameters
from gpg.gp.gram import log_marginal_likelihood, noisy_gram, stack_targets
from gpg.gp.hyper import Hyper

DIMS = (0, 2)


def problem(n=150, seed=0):
    rng = np.random.default_rng(seed)
    X = jnp.asarray(rng.uniform(-1, 1, (n, 3)))
    Ybar = jnp.asarray(rng.standard_normal((n * (1 + len(DIMS)), 2)))
    hyper = Hyper(1.3, jnp.array([0.7, 0.9, 1.2]), 1e-2, jnp.array([0.05, 0.1]))
    Z = jnp.asarray(pic.inducing_inputs(np.asarray(X), 30))
    return X, Ybar, hyper, Z


def test_lanczos_quadrature_is_exact_after_every_step():
    """With as many CG steps as rows, e₁ᵀ log(T) e₁ · ‖b‖² is bᵀ log(A) b exactly (NumPy
    eigendecomposition); a column that converged early pads T without changing it."""
    rng = np.random.default_rng(3)
    G = rng.standard_normal((12, 12))
    A = G @ G.T + 0.5 * np.eye(12)
    b = rng.standard_normal((12, 2))
    b[:, 1] = np.linalg.eigh(A)[1][:, :3] @ np.array([1.0, -2.0, 0.5])  # a 3-step Krylov space
    res = slq.pcg_lanczos(lambda v: jnp.asarray(A) @ v, jnp.asarray(b), lambda r: r,
                          tol=1e-9, max_iter=12)  # fmt: skip
    assert int(res.steps[1]) <= 4 < int(res.steps[0])
    quad = slq.lanczos_log_quadrature(res.alpha, res.beta, res.steps, 12) * res.rz0
    lam, U = np.linalg.eigh(A)
    ref = np.einsum("ik,i,ik->k", U.T @ b, np.log(lam), U.T @ b)
    np.testing.assert_allclose(quad, ref, rtol=1e-9)
    np.testing.assert_allclose(res.x, np.linalg.solve(A, b), atol=1e-10)


def test_traced_nystrom_equals_the_chunked_one_and_its_log_determinant():
    X, _, hyper, Z = problem(n=60)
    a = cg.Nystrom.create(X, hyper, DIMS, Z, chunk=16)
    b = cg.Nystrom.create(X, hyper, DIMS, Z, chunk=None)
    for x, y in ((a.V, b.V), (a.d_inv, b.d_inv), (a.chol, b.chol)):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12)
    P = np.asarray(b.V @ b.V.T) + np.diag(1.0 / np.asarray(b.d_inv))
    np.testing.assert_allclose(b.log_det(), np.linalg.slogdet(P)[1], rtol=1e-12)


def test_value_and_gradient_match_the_dense_likelihood():
    """200 fixed probes: the log likelihood to 5e-5 of its size (measured 1.5e-5), the
    log-determinant to 5e-4 (measured 1.9e-4: 0.23 of 1225 nats), every component of the
    gradient to 1 % (measured 0.3 %); forward mode gives what reverse does."""
    X, Ybar, hyper, Z = problem(n=80)
    probes = slq.Probes.draw(Ybar.shape[0], Z.shape[0] * 3, 200, 0)

    def f(h):
        out = slq.stochastic_log_marginal_likelihood(X, Ybar, h, DIMS, Z, probes, tol=1e-8)
        return out.value, out

    # compiled: op by op (CG's loops aside) each evaluation compiled hundreds of programs
    (value, out), grad = jax.jit(jax.value_and_grad(f, has_aux=True))(hyper)
    assert bool(out.converged) and int(out.steps) < 60
    dense = jax.value_and_grad(lambda h: log_marginal_likelihood(X, Ybar, h, DIMS))
    ref, ref_grad = jax.jit(dense)(hyper)
    assert abs(float(value - ref)) <= 5e-5 * abs(float(ref))
    sign, logdet = np.linalg.slogdet(np.asarray(noisy_gram(X, hyper, DIMS)))
    assert sign > 0 and abs(float(out.log_det) - logdet) <= 5e-4 * abs(logdet)
    for got, want in zip(jax.tree.leaves(grad), jax.tree.leaves(ref_grad), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-2)
    tangent = jax.tree.map(jnp.ones_like, hyper)
    forward = jax.jit(lambda h, t: jax.jvp(lambda h: f(h)[0], (h,), (t,))[1])(hyper, tangent)
    reverse = sum(float(jnp.sum(g)) for g in jax.tree.leaves(grad))
    assert float(forward) == pytest.approx(reverse, rel=1e-10)


def test_loose_probe_solves_change_the_likelihood_by_far_less_than_the_probes_do():
    """The probes' own CG to 1e-3 (the default) instead of the data solves' 1e-8: the
    log-determinant moves by 1.2e-4 nats of 1226 and the gradient by 1e-5 relative (measured
    on 150 points); the probes' sampling error is of order nats (the test above)."""
    X, Ybar, hyper, Z = problem()
    probes = slq.Probes.draw(Ybar.shape[0], Z.shape[0] * 3, 30, 0)

    def f(h, probe_tol):
        out = slq.stochastic_log_marginal_likelihood(
            X, Ybar, h, DIMS, Z, probes, tol=1e-8, probe_tol=probe_tol
        )
        return out.value, out

    # has_aux: the value, the log-determinant and the flag come from the same evaluation
    # as the gradient, not from three more.
    for_tol = {
        t: jax.jit(jax.value_and_grad(lambda h, t=t: f(h, t), has_aux=True))(hyper)
        for t in (None, 1e-3)
    }
    ((v0, out0), g0), ((v1, out1), g1) = for_tol[None], for_tol[1e-3]
    assert abs(float(out1.log_det - out0.log_det)) <= 1e-2
    assert abs(float(v1 - v0)) <= 1e-2
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g0), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-3)
    assert bool(out1.converged)


def test_a_stalled_line_search_ends_the_fit_at_the_optimum():
    """An objective seen only to a resolution (as the stochastic one is, to its CG
    tolerance; here its value is read on a 1e-6 grid of the parameters): once the line search
    rejects ``stall`` steps in a row below ``stall_step``, the fit ends, successfully, where
    optimistix's own test ends it many steps later (measured 17 against 46). Rejections far
    from the optimum (a curved valley's halvings) do not end it."""
    import optimistix as optx

    from gpg.gp.fit import _minimise_with_progress

    def valley(y):
        c = jnp.array([0.3, -0.2])
        return jnp.sum(jnp.array([1.0, 30.0]) * jnp.log(jnp.cosh(y - c))) + 0.5 * y[0] * y[1]

    def rosenbrock(y):
        return (1 - y[0]) ** 2 + 10 * (y[1] - y[0] ** 2) ** 2 + jnp.sum(y**4)

    solver = optx.BFGS(rtol=1e-12, atol=1e-12)
    saved = {}
    for f, y0 in ((valley, [2.0, 1.5]), (rosenbrock, [-1.0, 1.0])):

        def loss(y, args, f=f):
            seen = f(1e-6 * jnp.round(y / 1e-6))  # the value seen; the gradient is exact
            return f(y) + jax.lax.stop_gradient(seen - f(y))

        y0 = jnp.asarray(y0)
        y, status, n = _minimise_with_progress(loss, solver, y0, None, 300, False, stall=5)
        ref, ref_status, n_ref = _minimise_with_progress(loss, solver, y0, None, 300, False, 10**6)
        assert status == ref_status == optx.RESULTS.successful
        np.testing.assert_allclose(y, ref, atol=1e-4)
        saved[f.__name__] = n_ref - n
    assert saved["valley"] >= 10 and saved["rosenbrock"] >= 0


def test_a_flat_valley_ends_the_fit_once_steps_gain_less_than_ftol():
    """A steep direction and a nearly flat one (weight 1e-4), as the full-data refit's noise
    ratio is late in the fit: with ``ftol`` the fit ends, successfully, once three accepted
    steps each gained less than it, after the steep direction has converged and within a few
    ``ftol`` of the optimum's value, in fewer steps than optimistix's own test needs."""
    import optimistix as optx

    from gpg.gp.fit import _minimise_with_progress

    c = jnp.array([0.7, 6.0])

    def loss(y, args):
        return jnp.log(jnp.cosh(y[0] - c[0])) + 1e-4 * jnp.log(jnp.cosh(y[1] - c[1]))

    solver = optx.BFGS(rtol=1e-10, atol=1e-10)
    y0 = jnp.array([-1.5, 0.0])
    y, status, n = _minimise_with_progress(loss, solver, y0, None, 500, False, ftol=1e-6)
    ref, ref_status, n_ref = _minimise_with_progress(loss, solver, y0, None, 500, False)
    assert status == ref_status == optx.RESULTS.successful
    assert abs(float(y[0] - c[0])) <= 1e-2  # the steep direction is done
    assert float(loss(y, None) - loss(ref, None)) <= 1e-3  # what the flat one has left
    assert float(jnp.abs(ref - c).max()) <= 1e-4
    assert n < n_ref
    # patience: the same rule with one step ends no later
    _, _, n1 = _minimise_with_progress(loss, solver, y0, None, 500, False, ftol=1e-6, patience=1)
    assert n1 <= n


@pytest.mark.slow  # a whole fit (35 s); test_models' hyper.full test runs the same fit fast
def test_stochastic_fit_reaches_the_dense_optimum():
    """On 50 points (all of them), the fit that never forms K̄ ends where the dense fit does:
    from twice the signal variance, 1.5 times the lengthscales and three times the noise
    ratio of the dense optimum (2000 nats away: the optimum's noise sits at its floor), the
    dense likelihood at its hyperparameters is within 2 nats of the dense optimum (measured
    0.27, 57 BFGS steps; started from the defaults it took 120 steps and twice as long)."""
    rng = np.random.default_rng(1)
    X = rng.uniform(-1, 1, (50, 3))

    def f(X):
        return np.stack(
            [np.sin(2 * X[:, 0]) * X[:, 1] + X[:, 2] ** 2, np.cos(X[:, 0] + X[:, 2])], 1
        )

    Y = f(X) + 0.01 * rng.standard_normal((50, 2))
    e = 1e-5 * np.eye(3)
    dY = np.stack([(f(X + e[i]) - f(X - e[i])) / 2e-5 for i in range(3)], 2)
    dense = fit_hyperparameters(X, Y, dY, subset_size=None)
    h = dense.hyper
    start = Hyper(2 * h.variance, 1.5 * h.lengthscale, h.noise, h.grad_noise)
    opts = Stochastic(points=15, probes=20, progress=False)
    stoch = fit_hyperparameters(
        X, Y, dY, subset_size=None, likelihood="stochastic", stochastic=opts, init=start,
        noise_init=3 * float(h.noise / h.variance),
    )  # fmt: skip
    assert dense.converged and stoch.converged
    Ybar = stack_targets(jnp.asarray(Y), jnp.asarray(dY))

    def nll(h):
        return -float(log_marginal_likelihood(jnp.asarray(X), Ybar, h, (0, 1, 2)))

    assert nll(stoch.hyper) - nll(dense.hyper) <= 2.0
    assert nll(start) - nll(dense.hyper) > 100
    np.testing.assert_allclose(stoch.hyper.lengthscale[0], dense.hyper.lengthscale[0], rtol=0.1)


def test_unreachable_tolerance_and_bad_options_are_clear_errors():
    X, Ybar, _, _ = problem(n=40)
    Y, dY = np.asarray(Ybar[:40]), np.asarray(Ybar[40:]).reshape(2, 40, 2).transpose(1, 2, 0)
    opts = Stochastic(tol=1e-12, max_iter=1, progress=False)
    with pytest.raises(NotConverged, match=r"relative residual 1e-12 \(probes 0.001\) in 1 it"):
        fit_hyperparameters(X, Y, dY, grad_dims=DIMS, subset_size=None,
                            likelihood="stochastic", stochastic=opts)  # fmt: skip
    with pytest.raises(ValueError, match="likelihood must be"):
        fit_hyperparameters(X, Y, dY, grad_dims=DIMS, likelihood="exact")
    with pytest.raises(ValueError, match="stochastic.probes"):
        Stochastic(probes=0)
    with pytest.raises(ValueError, match="stochastic.ftol"):
        Stochastic(ftol=-1e-5)
