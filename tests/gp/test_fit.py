"""gpg.gp.fit: fits of one shape share their traced and compiled optimiser (the likelihood is
a module-level function with the data as arguments, not a closure made per call)."""

import numpy as np
import pytest

from gpg.gp import fit as fit_module
from gpg.gp.fit import _Host, fit_hyperparameters


@pytest.fixture
def traces(monkeypatch):
    """How often the dense likelihood's Python body runs: once per eager call and once per
    trace of a program that contains it."""
    count = {"n": 0}
    inner = fit_module.log_marginal_likelihood

    def counted(*args, **kwargs):
        count["n"] += 1
        return inner(*args, **kwargs)

    monkeypatch.setattr(fit_module, "log_marginal_likelihood", counted)
    return count


def _data(seed, n=14):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 2))
    dY = np.stack([2 * np.cos(2 * X[:, :1]), np.zeros((n, 1))], -1)
    return X, np.sin(2 * X[:, :1]), dY


def test_fits_of_one_shape_share_the_optimiser(traces):
    """A second fit on other data of the same shape and layout does not run the likelihood's
    Python at all: neither the optimiser nor the loss at the first and last point (one
    compiled program, not run op by op) is traced again. Another layout of observed
    gradients is another program, and the results are the data's own."""
    X, Y, dY = _data(0)
    observed = np.ones((14, 2), bool)
    observed[::3, 1] = False
    first = fit_hyperparameters(X, Y, dY, observed=observed, max_steps=5, on_failure="ignore")
    n_first = traces["n"]
    assert n_first >= 2  # the start's and end's loss, and the solve's own trace(s)
    X2, Y2, dY2 = _data(1)
    second = fit_hyperparameters(X2, Y2, dY2, observed=observed.copy(), max_steps=5,
                                 on_failure="ignore")  # fmt: skip
    assert traces["n"] == n_first
    assert not np.allclose(np.asarray(first.hyper.lengthscale),
                           np.asarray(second.hyper.lengthscale))  # fmt: skip
    other = observed.copy()
    other[1, 1] = False
    n_before = traces["n"]
    fit_hyperparameters(X2, Y2, dY2, observed=other, max_steps=5, on_failure="ignore")
    assert traces["n"] - n_before >= 2  # another row layout: both traced anew


def test_host_arrays_compare_by_content():
    """The static wrapper of host layouts: equal bytes, shape and dtype are equal and hash
    alike; any difference (a value, the shape, the dtype, None) is not equal."""
    a = np.array([True, False, True])
    assert _Host(a) == _Host(a.copy()) and hash(_Host(a)) == hash(_Host(a.copy()))
    assert _Host(a) != _Host(~a)
    assert _Host(a) != _Host(a.reshape(3, 1))
    assert _Host(a) != _Host(a.astype(np.int8))
    assert _Host(None) == _Host(None) and _Host(a) != _Host(None)
