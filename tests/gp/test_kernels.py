"""gpg.gp.kernels against the closed forms of paper Eq. (kernel_gradient), isotropic and ARD."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import kernels

RTOL = 1e-12

# compiled: op by op (autodiff's included) each call compiled dozens of small programs
_blocks = jax.jit(kernels.gradient_blocks)
_query_rows = jax.jit(kernels.query_rows, static_argnums=4)


def closed_form(x, xp, variance, lengthscale):
    """Paper Eq. (kernel_gradient), generalised to one lengthscale per input (ARD)."""
    ls2 = np.broadcast_to(np.asarray(lengthscale, float) ** 2, x.shape)
    d = x - xp
    k = variance * np.exp(-0.5 * np.sum(d * d / ls2))
    kn0 = -d / ls2 * k
    k0m = d / ls2 * k
    knm = (np.diag(1.0 / ls2) - np.outer(d / ls2, d / ls2)) * k
    return k, k0m, kn0, knm


@pytest.mark.parametrize("lengthscale", [0.7, np.array([0.3, 1.1, 0.6, 2.0])])
@pytest.mark.parametrize("same", [False, True])
def test_blocks_match_closed_form(rng, lengthscale, same):
    x = rng.uniform(-1, 1, 4)
    xp = x.copy() if same else rng.uniform(-1, 1, 4)
    b = _blocks(x, xp, 1.7, lengthscale)
    k, k0m, kn0, knm = closed_form(x, xp, 1.7, lengthscale)
    np.testing.assert_allclose(b.k00, k, rtol=RTOL)
    np.testing.assert_allclose(b.k0m, k0m, rtol=RTOL, atol=1e-15)
    np.testing.assert_allclose(b.kn0, kn0, rtol=RTOL, atol=1e-15)
    np.testing.assert_allclose(b.knm, knm, rtol=RTOL, atol=1e-15)
    if same:
        # At x = x': no value-gradient covariance, gradient covariance σ/l_n² on the diagonal.
        np.testing.assert_array_equal(np.asarray(b.kn0), 0.0)
        np.testing.assert_allclose(np.diag(b.knm), 1.7 / np.broadcast_to(lengthscale, 4) ** 2)


def test_isotropic_paper_form(rng):
    """The paper's isotropic expressions verbatim: (l² - d_n²)/l⁴ k and -d_n d_m/l⁴ k."""
    x, xp, ell = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), 0.8
    b = _blocks(x, xp, 1.0, ell)
    d = x - xp
    k = np.exp(-np.sum(d**2) / (2 * ell**2))
    for n in range(3):
        for m in range(3):
            want = (ell**2 - d[n] ** 2) / ell**4 * k if n == m else -d[n] * d[m] / ell**4 * k
            np.testing.assert_allclose(b.knm[n, m], want, rtol=RTOL)


def test_gram_layout_matches_pair_blocks(rng):
    X1, X2 = rng.uniform(-1, 1, (5, 3)), rng.uniform(-1, 1, (4, 3))
    ls = np.array([0.5, 0.9, 1.3])
    dims1, dims2 = (0, 2), (1,)
    K = np.asarray(kernels.gram(jnp.asarray(X1), jnp.asarray(X2), 1.3, ls, dims1, dims2))
    assert K.shape == (5 * 3, 4 * 2)
    for i in range(5):
        for j in range(4):
            k, k0m, kn0, knm = closed_form(X1[i], X2[j], 1.3, ls)
            rows = [(i, None)] + [(i + 5 * (1 + a), d) for a, d in enumerate(dims1)]
            cols = [(j, None)] + [(j + 4 * (1 + b), d) for b, d in enumerate(dims2)]
            for r, dn in rows:
                for c, dm in cols:
                    if dn is None and dm is None:
                        want = k
                    elif dn is None:
                        want = k0m[dm]
                    elif dm is None:
                        want = kn0[dn]
                    else:
                        want = knm[dn, dm]
                    np.testing.assert_allclose(K[r, c], want, rtol=1e-12, atol=1e-15)


def test_gram_symmetric_psd(rng):
    X = jnp.asarray(rng.uniform(-1, 1, (30, 4)))
    K = np.asarray(kernels.gram(X, X, 1.0, 0.6, (0, 1, 3), (0, 1, 3)))
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-14)
    assert np.linalg.eigvalsh(K).min() > -1e-10


@pytest.mark.parametrize("lengthscale", [0.4, np.array([0.4, 1.1])], ids=["iso", "ard"])
def test_correlation(rng, lengthscale):
    X = rng.uniform(-1, 1, (6, 2))
    C = np.asarray(kernels.correlation(jnp.asarray(X), jnp.asarray(X), lengthscale))
    np.testing.assert_allclose(np.diag(C), 1.0)
    assert np.all((C > 0) & (C <= 1))
    # Closed form exp(-½‖Δ/l‖²), also for two different point sets.
    X2 = rng.uniform(-1, 1, (4, 2))
    for A, B in ((X, X), (X, X2)):
        r = (A[:, None, :] - B[None, :, :]) / lengthscale
        want = np.exp(-0.5 * np.sum(r * r, axis=-1))
        got = np.asarray(kernels.correlation(jnp.asarray(A), jnp.asarray(B), lengthscale))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("dims", [(0, 5), (-1,), (1, 1), ("a",)])
def test_check_dims_rejects(dims):
    with pytest.raises(ValueError, match="grad_dims"):
        kernels.check_dims(dims, 4)


@pytest.mark.parametrize("dims", [(), (0, 2), (1, 0, 3)])
@pytest.mark.parametrize("lengthscale", [0.7, np.array([0.3, 1.1, 0.6, 2.0])])
def test_query_rows_match_autodiff_gram(rng, dims, lengthscale):
    """The closed-form query rows equal the autodiff Gram matrix (value queries)."""
    Xq, X = rng.uniform(-1, 1, (6, 4)), rng.uniform(-1, 1, (9, 4))
    X[0] = Xq[0]  # a coincident pair: r² rounds to about zero, k must equal σ
    want = kernels.gram(jnp.asarray(Xq), jnp.asarray(X), 1.3, lengthscale, (), dims)
    got = _query_rows(jnp.asarray(Xq), jnp.asarray(X), 1.3, lengthscale, dims)
    assert got.shape == want.shape == (6, 9 * (1 + len(dims)))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    assert float(got[0, 0]) == pytest.approx(1.3, rel=1e-14)


@pytest.mark.parametrize("lengthscale", [0.7, np.array([0.3, 1.1, 0.6, 2.0])])
def test_row_gram_is_the_autodiff_gram_on_any_rows(rng, lengthscale):
    """Rows picked from the layout (values and any derivatives, in any order) equal the same
    rows and columns of the autodiff Gram matrix."""
    dims = (0, 2, 3)
    X1, X2 = rng.uniform(-1, 1, (7, 4)), rng.uniform(-1, 1, (5, 4))
    X2[1] = X1[2]  # a coincident pair: the knm diagonal term 1/l² must be there
    full = np.asarray(kernels.gram(jnp.asarray(X1), jnp.asarray(X2), 1.3, lengthscale, dims, dims))
    i1 = rng.permutation(7 * 4)[:13]
    i2 = rng.permutation(5 * 4)[:9]
    deriv = np.array([-1, *dims])
    got = kernels.row_gram(
        jnp.asarray(X1[i1 % 7]), jnp.asarray(deriv[i1 // 7]),
        jnp.asarray(X2[i2 % 5]), jnp.asarray(deriv[i2 // 5]), 1.3, lengthscale,
    )  # fmt: skip
    np.testing.assert_allclose(got, full[np.ix_(i1, i2)], rtol=1e-12, atol=1e-14)
