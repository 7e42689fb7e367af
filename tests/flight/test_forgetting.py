"""gpg.flight.forgetting: the inducing-point term's forgetting time and prior, fitted on
held-out flights, against the term :func:`gpg.flight.adapt` builds run label by label."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight import correction as fc
from gpg.flight import forgetting as fg
from gpg.flight import tracking as tk
from tests.flight.test_correction import N_LABELS
from tests.flight.test_tracking import corrected, flights  # noqa: F401  (fixtures)

M = 8  # inducing inputs: the algebra is the same at 48


@jax.jit
def _step(on, t, x, e, r, b, start):
    """One row through the library's own term: reset or relaxed, scored (the band ``b``
    plus η's, or with ``on.shared`` η's prior taken out of it first), then measured."""
    m = on.mean.shape[1]
    fresh = dataclasses.replace(on, mean=jnp.zeros_like(on.mean),
                                cov=jnp.broadcast_to(jnp.eye(m), on.cov.shape), t=t)  # fmt: skip
    on = jax.tree.map(lambda a, b_: jnp.where(start, a, b_), fresh, on.relaxed(t))
    mu, q = on.mean_var(x)
    if on.shared:
        b = jnp.maximum(b - on.prior_var(x), 0.0)
    s = b + r + q
    ll = jnp.sum(-0.5 * (jnp.log(2 * jnp.pi * s) + (e - mu) ** 2 / s))
    return on.measured(x, e, r), ll


@pytest.mark.parametrize(("band", "per_output"), [("added", False), ("shared", False),
                                                  ("shared", True)])  # fmt: skip
def test_fit_scores_the_term_adapt_builds(corrected, flights, band, per_output):  # noqa: F811
    """The fitted (τ, c) is at least as likely as every grid point, inside its ranges, and
    its likelihood is that of the term ``adapt(tau=, variance=, band=)`` builds, run over the
    same held-out rows with its own ``relaxed``/``measured``/``mean_var``/``prior_var``: the
    fit scores the term a user then flies (the factor on the variance is the whitened
    features' √c; per output, each output relaxes with its own τ)."""
    f = fg.fit_forgetting(corrected, flights, inducing=M, max_steps=20, band=band,
                          per_output=per_output)  # fmt: skip
    assert f.labels == N_LABELS and f.inducing == M and f.band == band
    assert np.shape(f.tau) == np.shape(f.factor) == ((6,) if per_output else ())
    # inside the ranges up to exp(log(.))'s rounding (a few ulp: the bounds are reached)
    for v, (lo, hi) in ((f.tau, tk.TAU_RANGE), (f.factor, fg.FACTOR_RANGE)):
        assert np.all((np.asarray(v) >= lo * (1 - 1e-12)) & (np.asarray(v) <= hi * (1 + 1e-12)))
    if per_output:  # the outputs' residuals differ: so do their fitted pairs
        assert len(set(f.tau)) > 1 and len(set(f.factor)) > 1
    own = np.array([float(d.hyper.variance) for d in corrected.model.delta])
    np.testing.assert_allclose(f.variance, f.factor * own, rtol=1e-12)
    assert f.log_likelihood >= max(ll for *_, ll in f.grid) - 1e-12
    assert len({(a, b) for a, b, _ in f.grid}) == len(fg._TAU_GRID) * len(fg._FACTOR_GRID)

    data, _, (X, held) = tk._held_out_sequences(corrected, flights, 1500, inputs=True)
    t, start, _, resid, noise = (np.asarray(a) for a in data[:5])
    on = fc.adapt(corrected, inducing=M, tau=f.tau, variance=f.variance, band=band).model.online
    total = 0.0
    for i in range(len(t)):
        on, ll = _step(on, t[i], X[i], resid[i], noise[i], held[i], start[i])
        total += float(ll)
    # the scan and this loop add the same terms in another order, and the loop's features come
    # from whitening c K_ZZ where the scan scales K_ZZ's by √c: each differs by the rounding
    # of K_ZZ's factor, u cond(K_ZZ) (cond at most 1.6e3 here: 4e-13), summed over N_LABELS
    # rows, about 2e-11; 3e-16 seen
    np.testing.assert_allclose(total / len(t), f.log_likelihood, rtol=1e-10)


def test_held_out_band_is_the_calibrated_held_out_variance(corrected, flights):  # noqa: F811
    """The band the fit scores η beside: each part's held-out variance (``δ``'s latent, its
    ``ν²`` and the coefficients'), times the calibration factor ``δ`` carries; for a part the
    model did not take, the model's own predictive variance on the loads."""
    _, _, (X, band) = tk._held_out_sequences(corrected, flights, 1500, inputs=True)
    assert X.shape == (N_LABELS, corrected.model.n_inputs) and np.all(band > 0)
    other = dataclasses.replace(flights[1], name="not corrected on")
    _, _, (X2, band2) = tk._held_out_sequences(corrected, [flights[0], other], 1500, inputs=True)
    own = corrected.model
    Xo = fc.training_rows(corrected, other)[0]
    var = jax.vmap(lambda x: own.mean_var_one(x)[1])(jnp.asarray(Xo))
    expect = np.asarray(own.predictive_variance(var))[:, :6]
    np.testing.assert_allclose(band2[-len(other) :], expect, rtol=1e-12)
    np.testing.assert_allclose(X2[-len(other) :], Xo, rtol=1e-12)
    # the first part, held out either way, has the same band in both
    np.testing.assert_allclose(band2[: len(flights[0])], band[: len(flights[0])], rtol=1e-12)


def _constant_feature_args(resid, dt=0.1):
    """One load output of a term whose one feature is 1 at every state: a bias that
    forgets; the others with zero residual. Unit band beside it, small label noise."""
    n = resid.size
    psi = np.zeros((n, 6, 1))
    psi[:, 0, 0] = 1.0
    e = np.zeros((n, 6))
    e[:, 0] = resid
    start = np.zeros(n, bool)
    start[0] = True
    noise = np.full((n, 6), 0.01)
    prior = np.sum(psi * psi, -1)
    rows = (np.arange(n) * dt, start, psi, prior, e, noise, noise, noise)
    rows = tuple(jnp.asarray(a) for a in rows)
    return (*rows, False)


def test_search_follows_what_the_flights_show():
    """A residual that stays is best followed by a term that never forgets; one that flips
    every two seconds by one that forgets within about that: the fitted τ says which."""
    rng = np.random.default_rng(3)
    n = 400
    steady = 1.0 + 0.1 * rng.normal(size=n)
    t = np.arange(n) * 0.1
    flipping = np.where(np.sin(np.pi * t / 2.0) >= 0, 1.0, -1.0) + 0.1 * rng.normal(size=n)
    theta_s, *_ = fg._search(_constant_feature_args(steady), 40)
    theta_f, *_ = fg._search(_constant_feature_args(flipping), 40)
    tau_s, tau_f = float(fg._unpack(theta_s)[0]), float(fg._unpack(theta_f)[0])
    assert tau_s > 100.0 and tau_f < 5.0, (tau_s, tau_f)
    # the optimum's likelihood beats its neighbours along τ
    for theta, args in ((theta_f, _constant_feature_args(flipping)),):
        best = float(fg._neg_loglik(theta, args))
        for d in (-0.3, 0.3):
            assert best <= float(fg._neg_loglik(theta + jnp.array([d, 0.0]), args)) + 1e-9


def test_fit_forgetting_and_adapt_refuse_bad_input(synthetic_surrogate, corrected, flights):  # noqa: F811
    with pytest.raises(ValueError, match="inducing must be >= 1"):
        fg.fit_forgetting(corrected, flights, inducing=0)
    with pytest.raises(ValueError, match="fit_forgetting needs labels of two or more"):
        fg.fit_forgetting(corrected, flights[:1])
    with pytest.raises(ValueError, match="corrected by gpg.flight.correct"):
        fg.fit_forgetting(synthetic_surrogate, flights)
    with pytest.raises(ValueError, match="one non-empty part per part of labels"):
        fg.fit_forgetting(corrected, flights, read=flights[:1])
    with pytest.raises(ValueError, match="band must be 'added' or 'shared'"):
        fg.fit_forgetting(corrected, flights, band="both")
    for bad in ([1.0, 2.0], [1.0, 1.0, 1.0, 1.0, 1.0, -1.0], 0.0):
        with pytest.raises(ValueError, match="variance must be one or 6 positive"):
            fc.adapt(corrected, inducing=M, variance=bad)
    for bad in ([1.0, 2.0], [1.0, 1.0, 1.0, 1.0, 1.0, np.nan], -1.0):
        with pytest.raises(ValueError, match="tau must be one or 6 positive"):
            fc.adapt(corrected, inducing=M, tau=bad)
    six = np.linspace(0.1, 0.6, 6)
    on = fc.adapt(corrected, inducing=M, variance=six, tau=six).model.online
    np.testing.assert_allclose(np.asarray(on.variance), six, rtol=0)
    np.testing.assert_allclose(np.asarray(on.tau), six, rtol=0)
