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


def test_fit_options_one_object():
    """The fit's options are one object (gpg.gp.FitOptions), checked when made; keywords of
    fit_hyperparameters override its fields, and the model config builds it once."""
    import dataclasses

    import numpy as np
    import pytest

    from gpg.config import HyperConfig
    from gpg.gp import FitOptions, Stochastic, fit_hyperparameters

    with pytest.raises(ValueError, match="likelihood must be"):
        FitOptions(likelihood="exact")
    with pytest.raises(ValueError, match="on_failure must be"):
        FitOptions(on_failure="shout")
    with pytest.raises(ValueError, match="noise_floor and noise_init"):
        FitOptions(noise_floor=0.1, noise_init=0.01)
    h = HyperConfig(subset=50, max_steps=7, ard=False, full_max_steps=3, probes=4)
    opts = h.fit_options()
    assert (opts.subset_size, opts.max_steps, opts.ard) == (50, 7, False)
    full = h.full_options(0.05)
    assert full.likelihood == "stochastic" and full.subset_size is None
    assert full.noise_init == 0.05 and full.stochastic == Stochastic(
        probes=4, tol=h.cg_tol, max_iter=h.cg_max_iter, probe_tol=h.cg_probe_tol,
        ftol=h.full_ftol,
    )  # fmt: skip
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (20, 2))
    Y = np.sin(X @ [1.0, 2.0])[:, None]
    a = fit_hyperparameters(X, Y, options=dataclasses.replace(opts, max_steps=3),
                            on_failure="ignore")  # fmt: skip
    b = fit_hyperparameters(X, Y, options=opts, max_steps=3, on_failure="ignore")
    assert a.hyper.lengthscale.shape == () and a.num_steps == b.num_steps <= 3
    np.testing.assert_array_equal(a.hyper.lengthscale, b.hyper.lengthscale)
    with pytest.raises(TypeError, match="unexpected keyword argument 'steps'"):
        fit_hyperparameters(X, Y, steps=3)
