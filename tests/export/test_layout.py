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
