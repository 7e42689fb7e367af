"""Hyperparameters (gpg/gp/hyper.py): the names of earlier releases."""

import numpy as np
import pytest

from gpg.gp import Hyper


def test_old_jitter_names_still_work_with_a_warning():
    """ν² was called ``jitter`` before gpg 0.2: the constructor keyword, the attribute and the
    fit's keywords still work for one release, each with a DeprecationWarning."""
    import warnings

    import jax.numpy as jnp

    from gpg.gp import fit_hyperparameters

    with pytest.warns(DeprecationWarning, match=r"Hyper\(jitter=...\) is deprecated"):
        h = Hyper(1.0, 0.5, jitter=3e-4)
    assert float(h.noise) == 3e-4
    with pytest.warns(DeprecationWarning, match="Hyper.jitter is deprecated; use Hyper.noise"):
        assert float(h.jitter) == 3e-4
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (12, 2))
    Y = np.sin(X[:, :1] * 2)
    with pytest.warns(DeprecationWarning, match="fit_jitter=...") as rec:
        old = fit_hyperparameters(X, Y, fit_jitter=False, init=h, max_steps=5, on_failure="ignore")
    assert any("fit_noise" in str(w.message) for w in rec)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = fit_hyperparameters(X, Y, fit_noise=False, init=h, max_steps=5, on_failure="ignore")
    np.testing.assert_array_equal(jnp.asarray(old.hyper.lengthscale), new.hyper.lengthscale)
    with pytest.raises(TypeError, match="unexpected keyword argument 'fit_jiter'"):
        fit_hyperparameters(X, Y, fit_jiter=False)
