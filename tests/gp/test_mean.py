"""gpg.gp.mean: the folded exact mean equals ``k̄_qᵀ α`` written out in NumPy."""

import numpy as np
import pytest

from gpg.gp.mean import GlobalMean


def numpy_mean(Xq, X, alpha, sigma, ls, dims):
    """``k̄(x_q, X)ᵀ α`` from the paper's closed forms (value rows, then ``k0m`` rows)."""
    n, g = X.shape[0], len(dims)
    out = np.zeros((Xq.shape[0], alpha.shape[1]))
    for q, x in enumerate(Xq):
        d = x - X
        k = sigma * np.exp(-0.5 * np.sum(d**2 / ls**2, axis=1))
        row = [k] + [k * d[:, j] / ls[j] ** 2 for j in dims]
        out[q] = np.concatenate(row) @ alpha
        assert len(row) == 1 + g and row[0].shape == (n,)
    return out


@pytest.mark.parametrize("dims", [(), (0,), (2, 0)])
def test_folded_mean_matches_numpy(rng, dims):
    X = rng.uniform(-1, 1, (25, 3))
    alpha = rng.normal(size=(25 * (1 + len(dims)), 4))
    ls = np.array([0.4, 0.9, 0.7])
    mean = GlobalMean.from_alpha(X, alpha, 1.7, ls, dims)
    Xq = rng.uniform(-1.2, 1.2, (8, 3))
    got = np.stack([np.asarray(mean(x)) for x in Xq])
    np.testing.assert_allclose(got, numpy_mean(Xq, X, alpha, 1.7, ls, dims), rtol=1e-11, atol=1e-12)


def test_bad_alpha_shape(rng):
    with pytest.raises(ValueError, match=r"alpha must have shape \(30, M\)"):
        GlobalMean.from_alpha(rng.uniform(size=(10, 3)), np.zeros((20, 2)), 1.0, 1.0, (0, 1))
