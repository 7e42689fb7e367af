"""The export layout (gpg/export/layout.py): from every exportable kind's arrays, without
padding, a float64 NumPy evaluation (the computation every writer emits) equals the JAX
model's mean and latent variance at normalised queries."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.export import layout
from tests.export.models import CONFIGS, fitted


@pytest.mark.parametrize(
    "kind",
    [
        k if k in ("gpg", "gpgs_hybrid") else pytest.param(k, marks=pytest.mark.slow)
        for k in sorted(CONFIGS)
    ],
)  # the other kinds' fits in the slow set, for the fast budget
def test_layout_reproduces_the_model(kind):
    """Mean to 1e-12 (float64 arithmetic, both). Latent variance to 1e-12 where the factor is
    float64; the hybrid's and PIC's are float32, whose product JAX sums in float32: 1e-5 of
    ``σ`` (a few float32 roundings of a sum of terms bounded by ``σ``)."""
    sur = fitted(kind)
    s = layout.spec(sur)
    m = sur.model
    assert s.has_variance and s.record["model"] == kind.removesuffix("_body")
    tol = 1e-12 if s.bins.factor_dtype == np.float64 else 1e-5 * s.sigma
    X = np.random.default_rng(0).uniform(-1, 1, (40, s.dim))
    means, variances = (np.asarray(a) for a in jax.jit(jax.vmap(m.mean_var_one))(jnp.asarray(X)))
    bins = set()
    for xn, mean, var in zip(X, means, variances, strict=True):
        ref_mean, ref_var = layout.reference(s, xn)
        np.testing.assert_allclose(ref_mean, mean, rtol=0, atol=1e-12)
        assert abs(ref_var - float(var)) <= tol
        bins.add(s.bins.lookup(xn))
    assert len(bins) == s.bins.n_bins  # every bin's rows were used
    assert s.constant_bytes(8, variance=True) > s.constant_bytes(8, variance=False)


def test_layout_refuses_what_is_not_a_surrogate():
    with pytest.raises(ValueError, match="export takes a gpg.Surrogate"):
        layout.spec(fitted("gpg").model)


def test_exact_variance_over_max_bytes_is_refused_before_the_factor_is_made_dense(monkeypatch):
    """The exact kinds' variance is the dense ``L⁻¹`` of every row: at data=default 256 MB in
    float32, which would be allocated only to be refused. The size follows from the shapes."""
    sur = fitted("gpg")
    n = sur.model.X.shape[0] * (1 + len(sur.model.grad_dims))
    least = n * (n + 1) // 2 * 4  # the triangle at float32 (stored float64 here)

    def never(self):
        raise AssertionError("the factor was made dense before the size check")

    monkeypatch.setattr(type(sur.model.chol_inv), "to_dense", never)
    with pytest.raises(ValueError, match=r"at least .* MiB of constants, over max_bytes"):
        layout.spec(sur, max_bytes=least - 1)
    assert layout.spec(sur, variance=False, max_bytes=least - 1).bins is None
    with pytest.raises(AssertionError, match="made dense"):  # under the limit it goes on
        layout.spec(sur, max_bytes=least)


def test_old_name_spec_reads_with_a_warning():
    """``Spec`` was the export layout's name (``gpg.models.Spec`` is the registry's): it still
    reads, for one release, with the new name in the warning."""
    import gpg.export

    with pytest.warns(DeprecationWarning, match="gpg.export.Layout"):
        assert gpg.export.Spec is layout.Layout
    with pytest.warns(DeprecationWarning, match="layout.Layout"):
        assert layout.Spec is layout.Layout
    with pytest.raises(AttributeError):
        gpg.export.Nothing  # noqa: B018


def test_an_inducing_discrepancys_two_triangles_are_one():
    """``Discrepancy.variance_factor`` against the DTC latent variance in NumPy:
    ``‖T k‖² = ‖W k‖² − ‖P k‖²`` with ``W = L⁻¹`` of ``K_mm`` and ``P = L_B⁻¹ W``,
    ``B = I + A Aᵀ``, ``A = W K_mn / ν``, and ``T`` lower triangular. The tolerance is a
    rounding of the largest terms the two forms pass through, ``‖W‖₂² ‖k‖²`` (64 unit
    roundoffs of it); an exact GP's factor is its ``W``."""
    rng = np.random.default_rng(0)
    Z, X = rng.uniform(-1, 1, (30, 3)), rng.uniform(-1, 1, (300, 3))

    def k(a, b):
        return np.exp(-0.5 * np.sum((a[:, None] - b[None]) ** 2, -1) / 0.5**2)

    W = np.linalg.inv(np.linalg.cholesky(k(Z, Z) + 1e-8 * np.eye(30)))
    A = W @ k(Z, X) / 0.1
    P = np.linalg.inv(np.linalg.cholesky(np.eye(30) + A @ A.T)) @ W
    d = layout.Discrepancy(points=Z, weights=np.zeros(30), lengthscale=np.full(3, 0.5),
                           sigma=1.0, noise=1e-4, output_scale=1.0, whiten=W, post=P)  # fmt: skip
    T = d.variance_factor()
    np.testing.assert_array_equal(T, np.tril(T))
    kq = k(rng.uniform(-1.2, 1.2, (50, 3)), Z)
    want = np.sum((kq @ W.T) ** 2, 1) - np.sum((kq @ P.T) ** 2, 1)
    got = np.sum((kq @ T.T) ** 2, 1)
    bound = 64 * np.finfo(float).eps * np.linalg.norm(W, 2) ** 2 * np.sum(kq**2, 1)
    assert np.all(np.abs(got - want) <= bound)
    assert want.max() > 1e3 * bound.max()  # the data tell the variance apart from rounding
    exact = layout.Discrepancy(**{**d.__dict__, "post": None})
    assert exact.variance_factor() is W
