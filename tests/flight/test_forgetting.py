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


@jax.jit  # one program: op by op it compiled hundreds
def _bands(model, X):
    return jax.vmap(lambda x: model.predictive_variance(model.mean_var_one(x)[1]))(X)


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
    expect = np.asarray(_bands(own, jnp.asarray(Xo)))[:, :6]
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
    return (*rows, False, 1)


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


def _delayed_reference(theta, rows, shared, ahead):
    """NumPy: the term's weights per output relaxed row by row, each row predicted from the
    updates of the rows ``ahead`` and more before it (an update waits until the relaxation to
    the row ``ahead`` later, and is applied just before that row is predicted), restarting
    at each flight."""
    t, start, psi, prior, resid, gain_noise, held, noise = (np.asarray(a) for a in rows)
    tau, c = np.exp(np.asarray(theta))
    k, m = psi.shape[1:]
    mean, cov, pending, total, t_prev = np.zeros((k, m)), np.stack([np.eye(m)] * k), [], 0.0, t[0]

    def gain(mean, cov, p, e):
        sp = np.einsum("jmn,jn->jm", cov, p)
        return sp, np.einsum("jm,jm->j", p, sp), e - np.einsum("jm,jm->j", p, mean)

    for i in range(len(t)):
        a = np.exp(-max(t[i] - t_prev, 0.0) / tau)
        mean, cov, t_prev = a * mean, a**2 * cov + (1 - a**2) * np.eye(m), t[i]
        if start[i]:
            mean, cov, pending = np.zeros((k, m)), np.stack([np.eye(m)] * k), []
        if ahead > 1 and len(pending) == ahead:
            p, e, r = pending.pop(0)
            sp, q, err = gain(mean, cov, p, e)
            g = sp / (q + r)[:, None]
            mean, cov = mean + g * err[:, None], cov - g[:, :, None] * sp[:, None, :]
        p = np.sqrt(c) * psi[i]
        sp, q, err = gain(mean, cov, p, resid[i])
        s = (np.maximum(held[i] - c * prior[i], 0.0) if shared else held[i]) + q + noise[i]
        total += np.sum(-0.5 * (np.log(2 * np.pi * s) + err**2 / s))
        if ahead == 1:
            g = sp / (q + gain_noise[i])[:, None]
            mean, cov = mean + g * err[:, None], cov - g[:, :, None] * sp[:, None, :]
        else:
            pending.append((p, resid[i], gain_noise[i]))
    return -total / len(t)


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("ahead", [1, 2, 5])
def test_rows_predicted_ahead_match_a_numpy_filter(shared, ahead):
    """``ahead``: each row predicted from the rows that many before it (two flights, the
    second starting mid-way), against a NumPy loop of the same filter. Both sum the same
    few hundred terms of O(1) in another order: 1e-12."""
    rng = np.random.default_rng(5)
    n, k, m = 40, 2, 3
    psi = rng.normal(size=(n, k, m)) / np.sqrt(m)
    rows = (np.cumsum(rng.uniform(0.05, 0.3, n)), np.arange(n) % 23 == 0, psi,
            np.sum(psi * psi, -1), rng.normal(size=(n, k)), rng.uniform(0.05, 0.2, (n, k)),
            rng.uniform(1.0, 2.0, (n, k)), rng.uniform(0.02, 0.1, (n, k)))  # fmt: skip
    theta = np.log([1.5, 0.7])
    got = float(fg._rows_neg_loglik(jnp.asarray(theta), tuple(map(jnp.asarray, rows)),
                                    shared, ahead))  # fmt: skip
    np.testing.assert_allclose(got, _delayed_reference(theta, rows, shared, ahead), rtol=1e-12)


def test_predicting_ahead_does_not_follow_correlated_noise():
    """A residual that stays, seen through noise that correlates over about ten rows (and is
    larger than the labels' stated noise): scored one row ahead the fit follows the noise,
    forgetting within a minute (a shorter memory predicts more of the next row's noise);
    scored twenty rows ahead, beyond the correlation, it never forgets (τ at a day, its
    range's end: 27.6 s and 86 400 s seen)."""
    rng = np.random.default_rng(4)
    n, phi = 1500, 0.9
    w = rng.normal(scale=0.3 * np.sqrt(1 - phi**2), size=n)
    ar = np.zeros(n)
    for i in range(1, n):
        ar[i] = phi * ar[i - 1] + w[i]
    args = _constant_feature_args(1.0 + ar)
    theta_1, *_ = fg._search(args, 40)
    theta_20, *_ = fg._search((*args[:-1], 20), 40)
    tau_1, tau_20 = float(fg._unpack(theta_1)[0]), float(fg._unpack(theta_20)[0])
    assert tau_1 < 60.0 and tau_20 > 1000.0, (tau_1, tau_20)


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
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="ahead must be a whole number >= 1"):
            fg.fit_forgetting(corrected, flights, ahead=bad)
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


def _bank_reference(tau, factor, rows, shared, ahead):
    """NumPy: each member's weights run row by row alone (restarting at each flight), its
    state after every row kept; row i scored by the state after row i − ahead (the prior
    where the flight has fewer rows), relaxed to row i; and each member's own prediction at
    row i (its error, its band with the label's noise)."""
    t, start, psi, prior, resid, gain_noise, held, noise = (np.asarray(a) for a in rows)
    n, k, m = len(t), len(factor), psi.shape[-1]
    out, err1, var1 = np.zeros((n, k, 6)), np.zeros((n, k, 6)), np.zeros((n, k, 6))
    for j in range(k):
        tj, c = np.broadcast_to(tau[j], (6, m)), np.asarray(factor[j])[:, None]
        fresh = (np.zeros((6, m)), np.stack([np.eye(m)] * 6))
        after, flight0, mean, cov, t_prev = [], 0, *fresh, t[0]

        def relax(mean, cov, dt, tj=tj):
            a = np.exp(-dt / tj)
            cov = a[:, :, None] * cov * a[:, None, :] + (1 - a**2)[:, :, None] * np.eye(m)
            return a * mean, cov

        for i in range(n):
            if start[i]:
                flight0, (mean, cov), t_prev = i, fresh, t[i]
            mean, cov = relax(mean, cov, t[i] - t_prev)
            back = i - ahead
            lm, lc, tl = (*after[back][:2], after[back][2]) if back >= flight0 else (*fresh, t[i])
            lm, lc = relax(lm, lc, t[i] - tl)
            p = np.sqrt(c) * psi[i]
            sp = np.einsum("jmn,jn->jm", lc, p)
            q, err = np.einsum("jm,jm->j", p, sp), resid[i] - np.einsum("jm,jm->j", p, lm)
            b = np.maximum(held[i] - factor[j] * prior[i], 0) if shared else held[i]
            s = b + q + noise[i]
            out[i, j] = -0.5 * (np.log(2 * np.pi * s) + err**2 / s)
            sp = np.einsum("jmn,jn->jm", cov, p)
            q, err = np.einsum("jm,jm->j", p, sp), resid[i] - np.einsum("jm,jm->j", p, mean)
            err1[i, j], var1[i, j] = err, b + q + noise[i]
            g = sp / (q + gain_noise[i])[:, None]
            mean, cov = mean + g * err[:, None], cov - g[:, :, None] * sp[:, None, :]
            after.append((mean, cov, t[i]))
            t_prev = t[i]
    return out, err1, var1


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("ahead", [1, 3])
def test_bank_rows_and_mixture_match_numpy(shared, ahead):
    """fit_bank's members' scores (each row under each member ``ahead`` rows behind, two
    flights) against a NumPy run of each member alone; the mixture's score against a NumPy
    loop of the decayed weights. Sums of a few hundred O(1) terms in another order: 1e-11."""
    rng = np.random.default_rng(7)
    n, m = 40, 3
    psi = rng.normal(size=(n, 6, m)) / np.sqrt(m)
    rows = (np.cumsum(rng.uniform(0.05, 0.3, n)), np.arange(n) % 23 == 0, psi,
            np.sum(psi * psi, -1), rng.normal(size=(n, 6)), rng.uniform(0.05, 0.2, (n, 6)),
            rng.uniform(1.0, 2.0, (n, 6)), rng.uniform(0.02, 0.1, (n, 6)))  # fmt: skip
    tau = np.stack([np.full((6, m), 0.7), np.broadcast_to(np.geomspace(1, 50, 6)[:, None], (6, m))])
    factor = np.stack([np.full(6, 0.3), np.linspace(0.5, 2.0, 6)])
    rows_j = tuple(map(jnp.asarray, rows))
    got = [np.asarray(a) for a in fg._bank_rows_loglik(jnp.asarray(tau), jnp.asarray(factor),
                                                       rows_j, shared, ahead)]  # fmt: skip
    ref, err1, var1 = _bank_reference(tau, factor, rows, shared, ahead)
    for a, b in zip(got, (ref, err1, var1), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12)
    tw = 0.8
    lw, total = np.zeros((2, 6)), 0.0
    mean, band = np.zeros((n, 6)), np.zeros((n, 6))
    t, start = rows[0], rows[1]
    for i in range(n):
        lw = np.zeros((2, 6)) if start[i] else lw * np.exp(-(t[i] - t[i - 1]) / tw)
        w = np.exp(lw - lw.max(0))
        w /= w.sum(0)
        total += np.sum(np.log(np.sum(w * np.exp(ref[i]), 0)))
        mean[i] = np.sum(w * err1[i], 0)
        band[i] = np.sum(w * (var1[i] + err1[i] ** 2), 0) - mean[i] ** 2
        lw += ref[i]
    args = [jnp.asarray(a) for a in (got[0], t, start)]
    mix = float(fg._mixture_neg_loglik(jnp.log(jnp.asarray([tw])), tuple(args)))
    np.testing.assert_allclose(mix, -total / n, rtol=1e-11)
    # the bank's band at each row: its mixture's moments of the members' own predictions
    moments = fg._mixture_moments(jnp.log(jnp.asarray(tw)), *map(jnp.asarray, got), *args[1:])
    np.testing.assert_allclose(moments[0], mean, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(moments[1], band, rtol=1e-11, atol=1e-12)
    assert np.all(band > np.min(var1, 1) * (1 - 1e-12))  # never below its narrowest member


def test_fit_bank_on_flights(corrected, flights):  # noqa: F811
    """fit_bank on held-out flights: τ_w inside its range and at least as likely as its grid;
    each member's own score is the mixture's at one member (a bank of one is its member)."""
    members = [(0.5, 0.05), (30.0, None)]
    f = fg.fit_bank(corrected, flights, members, ahead=3, inducing=M, max_steps=10)
    lo, hi = fg.WEIGHT_TAU_RANGE
    assert lo * (1 - 1e-12) <= f.weight_tau <= hi * (1 + 1e-12)
    assert f.log_likelihood >= max(ll for _, ll in f.grid) - 1e-12
    assert f.labels == N_LABELS and f.ahead == 3 and len(f.members) == 2
    assert len(f.coverage95) == 6 and all(0.0 <= c <= 1.0 for c in f.coverage95)
    assert max(f.coverage95) > 0.5  # labels from the model's own family: inside, mostly
    one = fg.fit_bank(corrected, flights, members[1:], ahead=3, inducing=M, max_steps=2)
    np.testing.assert_allclose(one.log_likelihood, one.members[0], rtol=1e-12)
    np.testing.assert_allclose(one.members[0], f.members[1], rtol=1e-12)
