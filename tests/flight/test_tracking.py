"""gpg.flight.tracking: the physical basis's coefficients followed online, against a batch
posterior and a Kalman filter written here in NumPy."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight import correction as fc
from gpg.flight import tracking as tk
from gpg.flight.basis import PRIORS, TERMS
from gpg.flight.labels import Labels
from tests.flight.test_correction import N_LABELS, _states, assert_c_predicts

FIT = {"subset_size": N_LABELS // 2, "max_steps": 15}  # these tests check the filter's algebra


def _labels(sur, rng, n, *, drag, t0=0.0, name="f"):
    """Labels of a vehicle whose loads are the prior's plus an airframe drag of area ``drag``
    (m², every axis, world frame), noise known."""
    rpm, euler, v_air = _states(rng, n)
    p = sur.predict_batch(rpm, euler, v_air, mean_only=True)
    M = np.asarray(sur.simple.values(np.concatenate([rpm, euler], 1)))
    speed = np.linalg.norm(v_air, axis=1, keepdims=True)
    force = np.asarray(p.force) - 0.5 * 1.225 * drag * speed * v_air
    fvar, tvar = np.full((n, 3), 0.05**2), np.full((n, 3), 0.005**2)
    return Labels(
        t=t0 + np.arange(n) * 0.1,
        rpm=rpm,
        euler=euler,
        v_air=v_air,
        force=force + 0.05 * rng.normal(size=force.shape),
        torque=np.asarray(p.torque) + 0.005 * rng.normal(size=(n, 3)),
        force_var=fvar,
        torque_var=tvar,
        model_force=M[:, :3],
        model_torque=M[:, 3:],
        name=name,
    )


@pytest.fixture(scope="module")
def flights(synthetic_surrogate):
    rng = np.random.default_rng(4)
    return [_labels(synthetic_surrogate, rng, N_LABELS // 2, drag=a, name=f"w{a}")
            for a in (0.0, 0.03)]  # fmt: skip


@pytest.fixture(scope="module")
def corrected(synthetic_surrogate, flights):
    return fc.correct(synthetic_surrogate, flights, basis="physical", **FIT)


def _rows(sur, lab, i):
    """The GP row of label ``i``, the residual against the offline mean and the columns."""
    out = _rows_jit(sur, *(jnp.asarray(c[i]) for c in lab.columns()[1:]))
    return tuple(np.asarray(a) for a in out)


@jax.jit
def _mean_var(model, x):  # compiled: op by op it took seconds
    return model.mean_var_one(x)


@jax.jit  # compiled, as _mean_var
def _offline_means(model, X):
    return jax.vmap(lambda x: model.offline_mean(x, model.prior.mean_one(x)))(X)


@jax.jit
def _rows_jit(sur, *row):
    m = sur.model
    x, y, r = fc.gp_rows(sur, *row)
    pm = m.prior.mean_one(x)
    return x, y - m.offline_mean(x, pm)[:6], r, m.tracker_columns(x, pm)


def test_filter_is_the_batch_posterior(corrected, flights):
    """Without drift (τ far beyond the flight), label-by-label updates give the Bayesian linear
    regression's batch posterior of the residuals on the columns, prior N(0, C₀ + S) (C₀ the
    offline posterior's covariance of the basis's coefficients, S = diag(s² σ_B², s_b²)), noise
    the labels' own plus v; inside lax.scan and once a step from Python alike; the prediction
    adds hᵀw̄ to the offline mean, and its band on the loads is hᵀΣh + v plus each δ's latent
    variance (the offline model's, times its output scale)."""
    drift = tk.Drift(tau=1e12, spread=0.5, noise=(0.01,) * 6, bias_tau=1e12, bias_sd=0.7)
    sur = tk.track(corrected, drift, t0=0.0)
    lab = flights[1]
    n = 20
    cols = [jnp.asarray(c[:n]) for c in lab.columns()]
    scanned, _ = jax.lax.scan(lambda s, x: (fc.update(s, *x), None), sur, tuple(cols))
    rows = [_rows(sur, lab, i) for i in range(n)]
    sd = np.array([PRIORS[c] for c in ("prior", "simple", *TERMS)])
    S = np.diag(np.concatenate([(0.5 * sd) ** 2, [0.7**2]]))
    e = corrected.model.explicit
    assert e.columns == ("prior", "simple", *TERMS)
    C0 = np.zeros((6, sd.size + 1, sd.size + 1))
    C0[:, :-1, :-1] = np.einsum("jpq,jrq->jpr", e.cov_chol, e.cov_chol)
    tr = scanned.model.tracker
    for j in range(6):
        Hm = np.stack([h[j] for *_, h in rows])
        y = np.array([r[1][j] for r in rows])
        w = 1.0 / (np.array([r[2][j] for r in rows]) + 0.01)
        A = np.linalg.inv(C0[j] + S) + Hm.T @ (Hm * w[:, None])
        cov = np.linalg.inv(A)
        mean = cov @ (Hm.T @ (w * y))
        np.testing.assert_allclose(tr.mean[0, j], mean, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(tr.cov[0, j], cov, rtol=1e-6, atol=1e-12)
    step = fc.online_step(sur)
    st = fc.online_state(sur)
    for i in range(n):
        st = step(st, *(c[i] for c in cols))
    np.testing.assert_allclose(st.mean, tr.mean, rtol=1e-10, atol=1e-12)
    for a, b in zip(jax.tree.leaves(st), jax.tree.leaves(fc.online_state(sur)), strict=True):
        # fixed memory, and one compiled program: the same types, weak or not
        assert jax.typeof(a) == jax.typeof(b) and a.weak_type == b.weak_type
    # the prediction: the offline model's plus the drift's share, in mean and variance
    q = [np.asarray(a[0]) for a in (lab.rpm, lab.euler, lab.v_air)]
    tracked = fc.with_online(sur, st)
    x, _, _, h = _rows(tracked, lab, 0)
    mean, var = _mean_var(tracked.model, jnp.asarray(x))
    mean0, var0 = _mean_var(corrected.model, jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(mean - mean0)[:6], np.sum(h * st.mean[0], 1), rtol=1e-9)
    pv = np.asarray(tracked.model.predictive_variance(var))
    latent = np.array([float(var0[1 + j]) * float(d.output_scale[0])
                       for j, d in enumerate(corrected.model.delta)])  # fmt: skip
    assert np.all(latent > 0)
    band = np.einsum("jp,jpq,jq->j", h, st.cov[0], h) + 0.01 + latent
    np.testing.assert_allclose(pv[:6], band, rtol=1e-9)
    pv0 = np.asarray(corrected.model.predictive_variance(var0))
    np.testing.assert_allclose(pv[6:], pv0[6:], rtol=1e-12)  # the levels keep the prior's
    p = tracked.predict(*q)
    assert np.all(np.isfinite(np.asarray(p.variance)))


def _bank_reference(sur, lab, n, tau, spread, noise, share, bias_taus, bias_sd):
    """The bank written out in NumPy: per member the OU step (the basis's coefficients at
    ``τ``, the bias at the member's own rate, back to the offline posterior plus the drift)
    and the Kalman update, the weights by Bayes' rule on the members' predictive densities
    (summed over outputs), then the fixed share."""
    sd = np.array([PRIORS[c] for c in ("prior", "simple", *TERMS)])
    k, p = len(bias_taus), sd.size + 1
    e = sur.model.explicit
    S = np.zeros((6, p, p))
    S[:, :-1, :-1] = np.einsum("jpq,jrq->jpr", e.cov_chol, e.cov_chol)
    S += np.diag(np.concatenate([(spread * sd) ** 2, [bias_sd**2]]))
    mean, cov = np.zeros((k, 6, p)), np.broadcast_to(S, (k, 6, p, p)).copy()
    w, t_prev = np.full(k, 1.0 / k), lab.t[0]
    for i in range(n):
        _, y, r, h = _rows(sur, lab, i)
        dens = np.zeros(k)
        for m, bias_tau in enumerate(bias_taus):
            dt = lab.t[i] - t_prev
            a = np.concatenate([np.full(p - 1, np.exp(-dt / tau)), [np.exp(-dt / bias_tau)]])
            for j in range(6):
                mean[m, j] = a * mean[m, j]
                cov[m, j] = np.outer(a, a) * (cov[m, j] - S[j]) + S[j]
                Sh = cov[m, j] @ h[j]
                s = h[j] @ Sh + r[j] + noise
                e = y[j] - h[j] @ mean[m, j]
                dens[m] += -0.5 * (np.log(2 * np.pi * s) + e**2 / s)
                kg = Sh / s
                mean[m, j] = mean[m, j] + kg * e
                cov[m, j] = cov[m, j] - np.outer(kg, Sh)
        t_prev = lab.t[i]
        w = w * np.exp(dens - dens.max())
        w = (1 - share) * w / w.sum() + share / k
    return mean, cov, w, S


def test_bank_against_numpy_and_relaxes_to_the_stationary_law(corrected, flights):
    """A bank of two members (the coefficients' τ 0.3 s, the biases' 2 s and 0.1 s) against
    NumPy written here: each member's Ornstein-Uhlenbeck step (mean ×a, covariance
    (a aᵀ)⊙(Σ − Σ_∞) + Σ_∞) and update, the weights and the prediction's mixture; ten τ
    without labels return the basis block to Σ_∞; a time before the last update does not
    run it back."""
    drift = tk.Drift(tau=0.3, spread=2.0, noise=(0.02,) * 6, fast=(0.1,), share=0.05,
                     bias_tau=2.0, bias_sd=0.5)  # fmt: skip
    sur = tk.track(corrected, drift, t0=flights[1].t[0])
    lab = flights[1]
    s = sur
    for i in range(6):
        s = fc.update_jit(s, *(c[i] for c in lab.columns()))
    mean, cov, w, S = _bank_reference(sur, lab, 6, 0.3, 2.0, 0.02, 0.05, (2.0, 0.1), 0.5)
    tr = s.model.tracker
    np.testing.assert_allclose(tr.mean, mean, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(tr.cov, cov, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(np.exp(tr.log_weight), w, rtol=1e-6)
    h = _rows(s, lab, 7)[3]
    m_k = np.einsum("jp,kjp->kj", h, mean)
    v_k = np.einsum("jp,kjpq,jq->kj", h, cov, h)
    mix = np.sum(w[:, None] * m_k, 0)
    got_m, got_v = tr.mean_var(jnp.asarray(h))
    np.testing.assert_allclose(got_m, mix, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(got_v, np.sum(w[:, None] * (v_k + m_k**2), 0) - mix**2,
                               rtol=1e-6, atol=1e-12)  # fmt: skip
    later = tr.relaxed(float(tr.t) + 3.0)  # ten τ of the coefficients
    b = slice(0, -1)  # the basis block (the bias relaxes at its own rate)
    np.testing.assert_allclose(later.mean[1, :, b], np.exp(-10.0) * np.asarray(tr.mean[1, :, b]),
                               rtol=1e-9)  # fmt: skip
    # what is left of the covariance after ten τ is e^-20 of it
    left = 2 * np.exp(-20.0) * float(np.abs(tr.cov[1]).max())
    np.testing.assert_allclose(later.cov[1][:, b, b], S[:, b, b], rtol=1e-9, atol=left)
    same = tr.relaxed(float(tr.t) - 5.0)  # a = 1: (Σ − Σ_∞) + Σ_∞, a rounding of Σ_∞'s size
    np.testing.assert_allclose(same.cov, tr.cov, rtol=0, atol=4 * np.finfo(float).eps * S.max())


def test_fit_drift_from_held_out_flights(synthetic_surrogate, corrected, flights):
    """The drift fitted on flights of different drag (each predicted from the other) against
    its likelihood written here: the fitted θ is at least as likely as the grid's start, as
    one spread for every column and as the default, and the likelihood is the filter's
    prequential one (a NumPy filter over the same held-out residuals gives the same number)."""
    # ρ fitted: the physical terms' prior as PRIORS states it ("auto"), which fit_drift holds
    # out with
    assert corrected.config["flight_correction"]["basis_prior"]["factors"] == [1.0] * 6
    drift = tk.fit_drift(corrected, flights)
    assert drift.source == "fitted" and drift.labels == N_LABELS
    assert drift.fast in tk.BANKS
    assert tk.TAU_RANGE[0] <= drift.tau <= tk.TAU_RANGE[1]
    # a spread per column, named as the tracker orders them
    assert drift.columns == ("prior", "simple", *TERMS) and len(drift.spread) == len(drift.columns)
    spread = np.asarray(drift.spread)
    data, v0 = tk._held_out_sequences(corrected, flights, 1500)
    args = (data, jnp.asarray(drift.fast), drift.share)
    theta = tk._pack(drift.tau, drift.bias_tau, drift.bias_sd, drift.noise, spread)
    # score_drift gives any drift the fit's number: the fitted one its own likelihood; one
    # spread for all (their geometric mean) or twice the spreads (the fit's optimum, so no
    # higher) likelihoods of their own
    ll = tk.score_drift(corrected, flights, drift)
    np.testing.assert_allclose(ll, drift.log_likelihood, rtol=1e-9)
    uniform = dataclasses.replace(drift, spread=float(np.exp(np.log(spread).mean())), columns=())
    for other in (uniform, dataclasses.replace(drift, spread=tuple(2 * spread))):
        assert tk.score_drift(corrected, flights, other) < ll
    np.testing.assert_allclose(  # one number is every column's
        np.asarray(tk.track(corrected, uniform).model.tracker.spread), uniform.spread
    )
    with pytest.raises(ValueError, match="wind state"):
        tk.score_drift(corrected, flights, tk.gusts(drift))
    with pytest.raises(ValueError, match="spread and bias_sd"):
        tk.score_drift(corrected, flights, dataclasses.replace(drift, spread=1e3, columns=()))
    with pytest.raises(ValueError, match="score_drift needs labels of two or more"):
        tk.score_drift(corrected, flights[:1], drift)
    with pytest.raises(ValueError, match="one per column named in drift.columns"):
        tk.track(corrected, dataclasses.replace(drift, columns=drift.columns[:-1]))
    with pytest.raises(ValueError, match="but the model tracks"):
        tk.track(corrected, dataclasses.replace(drift, columns=drift.columns[::-1]))
    assert ll >= -float(tk._neg_loglik(tk._grid_start(args, v0, spread.size), args)) - 1e-9
    # one member (no fast ones): the likelihood is the filter's, written out here, each
    # label's law the held-out posterior of its part plus the drift
    one = (data, jnp.zeros(0), 0.0)
    t, start, H, y, r, c0, sd, dl = (np.asarray(a) for a in data)
    D = np.diag(np.concatenate([(spread * sd) ** 2, [drift.bias_sd**2]]))
    total = 0.0
    for j in range(6):
        for i in range(len(t)):
            S = c0[i, j] + D
            if start[i]:
                m, C = np.zeros(sd.size + 1), S.copy()
            else:
                dt = max(t[i] - t[i - 1], 0.0)
                a = np.full(sd.size + 1, np.exp(-dt / drift.tau))
                a[-1] = np.exp(-dt / drift.bias_tau)
                m, C = a * m, np.outer(a, a) * (C - S) + S
            s = H[i, j] @ C @ H[i, j] + r[i, j] + drift.noise[j]
            e = y[i, j] - H[i, j] @ m
            band = s + dl[i, j]  # the density is the band's, δ's latent variance in it
            total += -0.5 * (np.log(2 * np.pi * band) + e**2 / band)
            k = C @ H[i, j] / s
            m, C = m + k * e, C - np.outer(k, C @ H[i, j])
    np.testing.assert_allclose(-float(tk._neg_loglik(theta, one)), total / len(t), rtol=1e-7)
    # a part the model was not corrected on (by its name) is predicted by the model itself
    other = dataclasses.replace(flights[1], name="not corrected on")
    seq, _ = tk._held_out_sequences(corrected, [flights[0], other], 1500)
    X, Y, V = fc.training_rows(corrected, other)
    own = corrected.model
    expect = Y - np.asarray(_offline_means(own, jnp.asarray(X)))[:, :6]
    np.testing.assert_allclose(seq[3][-len(flights[1]) :], expect, rtol=1e-9, atol=1e-12)
    # its labels' noise, and the model's δ latent variances there (in the band's density)
    parts = np.asarray(jax.vmap(_mean_var, in_axes=(None, 0))(own, jnp.asarray(X))[1])
    latent = parts[:, 1:7] * np.array([float(d.output_scale[0]) for d in own.delta])
    np.testing.assert_allclose(seq[4][-len(flights[1]) :], V, rtol=1e-12)
    np.testing.assert_allclose(seq[7][-len(flights[1]) :], latent, rtol=1e-9)
    assert np.all(np.asarray(seq[7]) > 0)  # the held-out part's too
    with pytest.raises(ValueError, match="two or more"):
        tk.fit_drift(corrected, flights[:1])
    with pytest.raises(ValueError, match="corrected by gpg.flight.correct"):
        tk.fit_drift(synthetic_surrogate, flights)


def test_fit_drift_reads_a_stream(synthetic_surrogate, corrected, flights):
    """``read``: the filter's likelihood over every sample of the held-out flights, each
    predicted by the model fitted on the other flights' labels. The labels read as their own
    stream give the sequences without it, bit for bit; a stream holding half of a flight's
    labels between new samples gives those labels' rows as before (the model that predicts
    a flight does not see it) and the new samples' rows from the same model; ``max_labels``
    keeps the stream over the labels' span; fit and score agree on the stream's likelihood."""
    rng = np.random.default_rng(11)
    half = N_LABELS // 4
    streams = []
    for f, a in zip(flights, (0.0, 0.03), strict=True):
        new = _labels(synthetic_surrogate, rng, half, drag=a, t0=0.05)
        both = Labels.concatenate([f.take(slice(0, half)), new])
        streams.append(dataclasses.replace(both.take(np.argsort(both.t, kind="stable")),
                                           name=f.name))  # fmt: skip
    plain, v0 = tk._held_out_sequences(corrected, flights, 1500)
    same, v1 = tk._held_out_sequences(corrected, flights, 1500, read=list(flights))
    for a, b in zip(plain, same, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(v0, v1)
    seq, _ = tk._held_out_sequences(corrected, flights, 1500, read=streams)
    n = len(flights[0])
    old = np.concatenate([np.arange(half), n + np.arange(half)])  # each flight's first labels
    pairs = enumerate(zip(streams, flights, strict=True))
    mine = np.concatenate([np.flatnonzero(np.isin(s.t, f.t[:half])) + i * 2 * half
                           for i, (s, f) in pairs])  # fmt: skip
    assert np.array_equal(np.asarray(seq[0])[mine], np.asarray(plain[0])[old])
    for k in (2, 3, 4, 5, 7):  # columns, residual, noise, coefficients' covariance, δ's variance
        np.testing.assert_allclose(np.asarray(seq[k])[mine], np.asarray(plain[k])[old],
                                   rtol=1e-9, atol=1e-12)  # fmt: skip
    assert np.all(np.isfinite(np.asarray(seq[3]))) and len(seq[0]) == 4 * half
    assert list(np.flatnonzero(np.asarray(seq[1]))) == [0, 2 * half]  # each flight starts anew
    # over the span of the labels kept: the first 10 labels of each flight, to t = 0.9 s
    cut, _ = tk._held_out_sequences(corrected, flights, 20, read=streams)
    span = np.concatenate([s.t[s.t <= f.t[9]] for s, f in zip(streams, flights, strict=True)])
    assert span.size == 2 * 19 and np.array_equal(np.asarray(cut[0]), span)
    drift = tk.fit_drift(corrected, flights, read=streams, fast=(), max_steps=5)
    assert drift.labels == 4 * half
    np.testing.assert_allclose(tk.score_drift(corrected, flights, drift, read=streams),
                               drift.log_likelihood, rtol=1e-9)  # fmt: skip
    with pytest.raises(ValueError, match="one non-empty part per part of labels"):
        tk.fit_drift(corrected, flights, read=streams[:1])
    with pytest.raises(ValueError, match="one non-empty part per part of labels"):
        tk.score_drift(corrected, flights, drift, read=[streams[0], streams[1].take(slice(0, 0))])


def test_prequential_predicts_before_it_updates(corrected, flights):
    """prequential's one compiled scan: the i-th prediction is the model after i updates,
    as a once-a-step loop from Python gives it; a model without an online state predicts."""
    sur = tk.track(corrected, tk.Drift(tau=5.0, spread=1.0, noise=(0.01,) * 6),
                   t0=flights[1].t[0])  # fmt: skip
    lab = flights[1].take(slice(0, 5))
    pre = tk.prequential(sur, lab)
    step, st = fc.online_step(sur), fc.online_state(sur)
    for i in range(len(lab)):
        p = fc.with_online(sur, st).predict(lab.rpm[i], lab.euler[i], lab.v_air[i])
        np.testing.assert_allclose(pre.force[i], p.force, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(pre.variance[i], np.asarray(p.variance)[:6], rtol=1e-9)
        st = step(st, *(c[i] for c in lab.columns()))
    np.testing.assert_allclose(fc.online_state(pre.final).mean, st.mean, rtol=1e-10, atol=1e-12)
    plain = tk.prequential(corrected, lab)
    np.testing.assert_allclose(
        plain.force, corrected.predict_batch(lab.rpm, lab.euler, lab.v_air).force, rtol=1e-12
    )
    with pytest.raises(ValueError, match="labels of one flight"):
        tk.prequential(sur, lab.take(slice(0, 0)))


def test_label_offset_widens_the_band_only(corrected, flights):
    """A drift's ``label_offset`` (σ_F, σ_τ): the same filter (the state after the labels is
    bit for bit the one without it: the gain does not see it) and the same mean, and the
    band wider by σ_F² on each world force axis and σ_τ² on each torque axis (the offset is
    isotropic, so it is the same in the GP's frame and the world's), to the rounding of the
    bands it is added to. (The labels and drift of the test above: its scan serves the first.)"""
    lab = flights[1].take(slice(0, 5))
    base = tk.Drift(tau=5.0, spread=1.0, noise=(0.01,) * 6)
    sig = (0.3, 0.02)
    pre = [tk.prequential(tk.track(corrected, d, t0=lab.t[0]), lab)
           for d in (base, dataclasses.replace(base, label_offset=sig))]  # fmt: skip
    a, b = (fc.online_state(p.final) for p in pre)
    assert np.array_equal(np.asarray(a.mean), np.asarray(b.mean))
    assert np.array_equal(np.asarray(a.cov), np.asarray(b.cov))
    assert a.offset is None and b.offset is not None
    np.testing.assert_array_equal(pre[1].force, pre[0].force)
    np.testing.assert_array_equal(pre[1].torque, pre[0].torque)
    want = pre[0].variance + np.repeat(np.square(sig), 3)
    tol = 8 * np.finfo(float).eps * want  # a few roundings: the sum, the rotation, the scale
    assert np.all(np.abs(pre[1].variance - want) <= tol)
    desc = pre[1].final.model.describe()["flight_correction"]["tracker"]["offset"]
    y_std = np.asarray(corrected.normalizer.y_std)[:6]
    np.testing.assert_allclose(np.asarray(desc) * y_std**2, np.repeat(np.square(sig), 3),
                               rtol=1e-12)  # fmt: skip


def test_track_checks_and_composes(synthetic_surrogate, corrected, flights):
    """track takes a prior (its mean and M become columns) or a corrected model, refuses a bad
    drift and an adapted model; a tracked model is a JAX function (jit, vmap, forward and
    reverse derivatives of its prediction against central differences)."""
    with pytest.raises(ValueError, match="must be > 0"):
        tk.track(corrected, tk.Drift(tau=0.0, spread=1.0, noise=(0.0,) * 6))
    with pytest.raises(ValueError, match="6 numbers"):
        tk.track(corrected, tk.Drift(tau=1.0, spread=1.0, noise=(0.0,) * 5))
    with pytest.raises(ValueError, match="inducing-point term"):
        tk.track(fc.adapt(corrected, inducing=4))
    with pytest.raises(ValueError, match="already follows"):
        fc.adapt(tk.track(corrected))
    with pytest.raises(ValueError, match="prepared by gpg.flight.adapt or gpg.flight.track"):
        fc.online_step(corrected)
    plain = tk.track(synthetic_surrogate)
    assert plain.model.tracker.mean.shape == (1, 6, 3 + len(TERMS))
    with pytest.raises(ValueError, match="share must be"):
        tk.track(corrected, tk.Drift(tau=1.0, spread=1.0, noise=(0.0,) * 6, share=1.0))
    for bad in ((0.1,), (-0.1, 0.0), (float("nan"), 0.0)):
        with pytest.raises(ValueError, match="label_offset must be two numbers"):
            tk.track(corrected, tk.Drift(tau=1.0, spread=1.0, noise=(0.0,) * 6,
                                         label_offset=bad))  # fmt: skip
    d = tk.default_drift(corrected)
    d0 = corrected.model.delta[0]
    assert d.noise[0] == pytest.approx(
        float((d0.hyper.variance + d0.hyper.noise) * d0.output_scale[0])
    )
    lab = flights[0]
    s = fc.update_jit(plain, *(c[0] for c in lab.columns()))
    v = jnp.asarray(lab.v_air[:4])
    f = jax.jit(jax.vmap(lambda a: s.predict(lab.rpm[0], lab.euler[0], a).force[0]))
    assert np.all(np.isfinite(np.asarray(f(v))))
    g = jax.jit(jax.grad(lambda a: s.predict(lab.rpm[0], lab.euler[0], a).force[0]))(v[0])
    eps = 1e-5
    e = jnp.array([eps, 0.0, 0.0])
    fd = (f(jnp.stack([v[0] + e] * 4))[0] - f(jnp.stack([v[0] - e] * 4))[0]) / (2 * eps)
    np.testing.assert_allclose(float(g[0]), float(fd), rtol=1e-5, atol=1e-7)
    fwd = jax.jit(jax.jacfwd(lambda a: s.predict(lab.rpm[0], lab.euler[0], a).force))(v[0])
    np.testing.assert_allclose(np.asarray(fwd)[0], np.asarray(g), rtol=1e-8, atol=1e-10)
    assert dataclasses.is_dataclass(d)


def test_tracked_update_in_c_equals_jax(corrected, flights, tmp_path):
    """A tracked model's C (``gpg.export.to_c``, a bank of two filters): its state after a
    10-minute stream at 10 Hz (the labels replayed, time moving on) equals ``lax.scan`` of
    :func:`fc.update` to 1e-9 (double: the same float64 relax-then-Kalman steps, the C's
    covariance exactly symmetric where the library symmetrises after each step), and
    ``online_predict`` then equals ``predict`` of the updated model: force and torque to 1e-9
    of their scale, the filter's band on the loads to 1e-7 relative. A label with NaN is
    refused, the state kept. CasADi and ONNX take the updated model at its state: CasADi's
    values to 1e-10 and band to 1e-9 (double throughout), ONNX's to 1e-5 (float32 inputs and
    frame). The drift states a labels' offset: every export's band holds it."""
    import ctypes

    from gpg.export import to_casadi, to_onnx
    from tests.export.test_c_source import compiled
    from tests.flight.test_correction import _export_states, onnx_outputs

    # a labels' offset in the band (exported as a constant beside v)
    drift = dataclasses.replace(tk.default_drift(corrected), tau=30.0, bias_tau=5.0, fast=(0.5,),
                                label_offset=(0.3, 0.02))  # fmt: skip
    tracked = tk.track(corrected, drift)
    lab = Labels.concatenate(flights)
    n = 6000
    cols = [np.asarray(c, float)[np.arange(n) % len(lab)] for c in lab.columns()]
    cols[0] = np.arange(n) * 0.1
    final, _ = jax.jit(lambda s, xs: jax.lax.scan(lambda c, r: (fc.update(c, *r), None), s, xs))(
        tracked, tuple(jnp.asarray(c) for c in cols)
    )
    compiled(tracked, tmp_path, "double")
    lib = ctypes.CDLL(str(tmp_path / "quad.so"))
    r = final.model.tracker
    k, p = r.mean.shape[0], r.mean.shape[2]
    start = tracked.model.tracker  # the stream moved every part of the state
    assert np.abs(r.mean).min() < np.abs(r.mean).max() and np.abs(r.mean).max() > 1e-3
    assert np.abs(r.log_weight - start.log_weight).max() > 1e-3

    class State(ctypes.Structure):
        _fields_ = [
            ("mean", ctypes.c_double * (k * 6 * p)),
            ("cov", ctypes.c_double * (k * 6 * p * p)),
            ("log_weight", ctypes.c_double * k),
            ("t", ctypes.c_double),
        ]

    D = ctypes.POINTER(ctypes.c_double)
    rows = np.column_stack([c.reshape(n, -1) for c in cols])

    def update(st, row, t):  # one row: t, rpm, euler, v_air, force, torque, their variances
        cuts = ((1, 5), (5, 8), (8, 11), (11, 14), (14, 17), (17, 20), (20, 23))
        a = [np.ascontiguousarray(row[i:j]).ctypes.data_as(D) for i, j in cuts]
        return lib.quad_online_update(ctypes.byref(st), ctypes.c_double(t), *a)

    st = State()
    lib.quad_online_init(ctypes.byref(st))
    assert all(update(st, row, row[0]) == 1 for row in rows)
    got = np.ctypeslib.as_array(st.mean).reshape(k, 6, p)
    np.testing.assert_allclose(got, r.mean, rtol=0, atol=1e-9 * max(1.0, np.abs(r.mean).max()))
    got = np.ctypeslib.as_array(st.cov).reshape(k, 6, p, p)
    np.testing.assert_allclose(got, r.cov, rtol=0, atol=1e-9 * max(1.0, np.abs(r.cov).max()))
    np.testing.assert_allclose(np.ctypeslib.as_array(st.log_weight), r.log_weight, atol=1e-9)
    assert st.t == float(r.t)
    bad = rows[0].copy()
    bad[12] = np.nan
    before = np.ctypeslib.as_array(st.mean).copy()
    assert update(st, bad, 1e4) == 0
    assert np.array_equal(np.ctypeslib.as_array(st.mean), before) and st.t == float(r.t)
    rpm, euler, v = _export_states(lab, 8)
    ref = final.predict_batch(rpm, euler, v)
    assert_c_predicts(lib.quad_online_predict, st, ref, rpm, euler, v, 1e-7)
    # CasADi (double) and ONNX (float32 outside the correction) at the updated state
    f = to_casadi(final)
    for i in range(4):
        res = [np.asarray(a).ravel() for a in f(rpm[i], euler[i], v[i])]
        want = np.concatenate([ref.force[i], ref.torque[i]])
        assert np.abs(np.concatenate(res[:2]) - want).max() <= 1e-10 * max(1, np.abs(want).max())
        np.testing.assert_allclose(res[3][:6], ref.variance[i, :6], rtol=1e-9)
    got = onnx_outputs(to_onnx(final, tmp_path / "m.onnx")["onnx"], rpm, euler, v)
    scale = np.abs(np.concatenate([ref.force, ref.torque], 1)).max()
    for key in ("force", "torque"):
        np.testing.assert_allclose(got[key], getattr(ref, key), atol=1e-5 * max(1.0, scale))
    # the band: the filter's in float64, rotated in float32 (a few roundings of it)
    np.testing.assert_allclose(got["variance"][:, :6], ref.variance[:, :6], rtol=1e-5)


def test_wind_state_update_in_c_equals_jax(corrected, flights, tmp_path):
    """A model tracking a wind state in C: in double, after a 10-minute stream at 10 Hz (the
    labels replayed with a wind of 1.5 m/s along x and −1 along y that the logged air
    velocity misses, time moving on) the coefficients' and the wind's state equal
    ``lax.scan`` of :func:`fc.update`. The C's Jacobian in the wind is fourth-order central
    differences at 1e-3 m/s where the library's is ``jax.jacfwd``: ~1e-11 of the residual
    (truncation and rounding), which the filter's contraction keeps near that over the
    stream (1e-12 seen); bound 1e-9 of each array's scale, as the tracked update's.
    ``online_predict`` then equals ``predict``: force and torque to 1e-9 of their scale (the
    same mean at v_air + ḡ), the band to 1e-9 (its diag(J P_g Jᵀ), a few per cent of it and
    more, from the same differences). In float (the state stored in float) the stream ends
    within 1e-5 of the scale. The export's record hashes the tracked state. Without the
    variance, and through CasADi or ONNX, the model is refused by name."""
    import ctypes

    from gpg.export import spec, to_c, to_casadi, to_onnx
    from tests.export.test_c_source import compiled
    from tests.flight.test_correction import _export_states

    drift = dataclasses.replace(tk.default_drift(corrected), tau=30.0, bias_tau=5.0,
                                fast=(0.5,))  # fmt: skip
    sur = tk.track(corrected, tk.gusts(drift, sd=(1.0, 1.0, 0.5), tau=20.0))
    lab = Labels.concatenate(flights)
    n = 6000
    cols = [np.asarray(c, float)[np.arange(n) % len(lab)] for c in lab.columns()]
    cols[0] = np.arange(n) * 0.1
    true = np.array([1.5, -1.0, 0.0])
    # each flight's labels, as the constant wind's test makes them (its compiled program), the
    # stream their repeats
    ps = [corrected.predict_batch(f.rpm, f.euler, f.v_air + true, mean_only=True) for f in flights]
    rng = np.random.default_rng(3)
    for k, key in ((4, "force"), (5, "torque")):
        cols[k] = np.concatenate([np.asarray(getattr(p, key)) for p in ps])[np.arange(n) % len(lab)]
    cols[4] = cols[4] + 0.05 * rng.normal(size=(n, 3))
    cols[5] = cols[5] + 0.005 * rng.normal(size=(n, 3))
    final, _ = jax.jit(lambda s, xs: jax.lax.scan(lambda c, r: (fc.update(c, *r), None), s, xs))(
        sur, tuple(jnp.asarray(c) for c in cols)
    )
    r = final.model.tracker
    assert np.abs(np.asarray(r.wind_mean)[:2] - true[:2]).max() < 0.5  # it found the wind
    compiled(sur, tmp_path, "double")
    lib = ctypes.CDLL(str(tmp_path / "quad.so"))
    k, q = r.mean.shape[0], r.mean.shape[2]

    class State(ctypes.Structure):
        _fields_ = [
            ("mean", ctypes.c_double * (k * 6 * q)),
            ("cov", ctypes.c_double * (k * 6 * q * q)),
            ("log_weight", ctypes.c_double * k),
            ("t", ctypes.c_double),
            ("wind_mean", ctypes.c_double * 3),
            ("wind_cov", ctypes.c_double * 9),
        ]

    D = ctypes.POINTER(ctypes.c_double)
    rows = np.column_stack([c.reshape(n, -1) for c in cols])
    cuts = ((1, 5), (5, 8), (8, 11), (11, 14), (14, 17), (17, 20), (20, 23))

    def streamed(lib, st, bound):  # the stream through the C, its state held to the scan's
        lib.quad_online_init(ctypes.byref(st))
        np.testing.assert_array_equal(st.wind_cov, np.diag([1.0, 1.0, 0.25]).ravel())
        for row in rows:
            a = [np.ascontiguousarray(row[i:j]).ctypes.data_as(D) for i, j in cuts]
            assert lib.quad_online_update(ctypes.byref(st), ctypes.c_double(row[0]), *a) == 1
        for key, want in (("mean", r.mean), ("cov", r.cov), ("log_weight", r.log_weight),
                          ("wind_mean", r.wind_mean), ("wind_cov", r.wind_cov)):  # fmt: skip
            want = np.asarray(want)
            got = np.ctypeslib.as_array(getattr(st, key)).reshape(want.shape)
            np.testing.assert_allclose(
                got, want, rtol=0, atol=bound * max(1.0, np.abs(want).max()), err_msg=key
            )
        return st

    st = streamed(lib, State(), 1e-9)
    rpm, euler, v = _export_states(lab, 8)
    ref = final.predict_batch(rpm, euler, v)
    still = eqx.tree_at(lambda s: s.model, final, final.model.without_wind())
    calm = still.predict_batch(rpm, euler, v + np.asarray(r.wind_mean))
    extra = np.asarray(ref.variance - calm.variance)[:, :6]  # diag(J P_g Jᵀ)
    assert np.median(extra / np.asarray(calm.variance)[:, :6]) > 0.01  # a share worth testing
    # the band to 1e-9: 1e-11 seen, its other terms to rounding and the differences' ~1e-11 of J
    assert_c_predicts(lib.quad_online_predict, st, ref, rpm, euler, v, 1e-9)
    # float: the state's means and covariances stored in float, the sums in double
    compiled(sur, tmp_path / "f", "float")
    libf = ctypes.CDLL(str(tmp_path / "f" / "quad.so"))

    class StateF(ctypes.Structure):
        _fields_ = [(a, ctypes.c_float * b._length_) if a in ("mean", "cov") else (a, b)
                    for a, b in State._fields_]  # fmt: skip

    # each step rounds the stored state to float (ε 6e-8; 6e-7 of the scale seen after the
    # stream): within the exports' float tolerance
    streamed(libf, StateF(), 1e-5)
    with pytest.raises(ValueError, match="variance=True only"):
        to_c(sur, tmp_path / "mean_only", variance=False)
    # the record's hash reads the tracked state: the stream's end is another model
    assert spec(sur).record["arrays_sha256"] != spec(final).record["arrays_sha256"]
    for export in (lambda: to_casadi(sur), lambda: to_onnx(sur, tmp_path / "m.onnx")):
        with pytest.raises(ValueError, match="wind state"):
            export()


def _wind_drift(tau=2.0, **kw):
    base = tk.Drift(tau=1e12, spread=0.5, noise=(0.01,) * 6, bias_tau=1e12, bias_sd=0.7)
    return tk.gusts(dataclasses.replace(base, **kw), sd=(1.0, 0.8, 0.5), tau=tau)


def _shifted(lab, i, g):
    """Label ``i``'s update row with its air velocity shifted by ``g``."""
    row = [np.asarray(c[i], float) for c in lab.columns()]
    row[3] = row[3] + np.asarray(g, float)
    return row


def test_wind_state_is_the_linearised_kalman_step(corrected, flights):
    """gusts(): the wind state g relaxes as an OU process (τ_g) and conditions on a label by
    the Kalman step linearised at ḡ: H the prediction's derivative in g (central
    differences of the residual here, step 1e-4 m/s: truncation ~1e-8 of H), the innovation's
    covariance H P Hᵀ plus the label's noise, v, the coefficients' band hᵀΣh and each δ's
    latent variance; the
    coefficients are then updated at v_air + ḡ; online_step's update is the same. A wind_sd
    that is not three numbers >= 0 is refused by name, and so is the export."""
    sur = tk.track(corrected, _wind_drift(), t0=float(flights[1].t[0]) - 0.3)
    lab = flights[1]
    new = fc.update_jit(sur, *_shifted(lab, 0, 0.0)).model.tracker
    tr = sur.model.tracker
    P = np.diag(np.asarray(tr.wind_sd) ** 2)  # the start is the stationary law: relaxing keeps it
    eps = 1e-4
    x, e, r, h = _rows(sur, lab, 0)
    os = np.array([float(d.output_scale[0]) for d in corrected.model.delta])
    latent = np.asarray(_mean_var(corrected.model, jnp.asarray(x))[1])[1:7] * os
    J = np.zeros((6, 3))
    for k in range(3):
        d = np.eye(3)[k] * eps
        up, dn = (_rows_jit(sur, *(jnp.asarray(c) for c in _shifted(lab, 0, s)[1:]))[1]
                  for s in (d, -d))  # fmt: skip
        J[:, k] = (np.asarray(up) - np.asarray(dn)) / (2 * eps)
    H = -J
    cov = np.asarray(tr.cov[0])  # stationary, so the relaxed coefficients' law too
    band = np.einsum("jp,jpq,jq->j", h, cov, h)
    S = H @ P @ H.T + np.diag(r + 0.01 + band + latent)
    gain = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(new.wind_mean, gain @ e, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(new.wind_cov, P - gain @ H @ P, rtol=1e-6, atol=1e-9)
    # once a step from Python: the offline model's mean view keeps δ's variance for the wind
    once = fc.online_step(sur)(fc.online_state(sur), *_shifted(lab, 0, 0.0))
    for u, w in zip(jax.tree.leaves(once), jax.tree.leaves(fc.online_state(sur)), strict=True):
        assert jax.typeof(u) == jax.typeof(w) and u.weak_type == w.weak_type  # one program
    # two compiled programs of the same float64 step: rounding apart, as the scan's check
    np.testing.assert_allclose(once.wind_mean, new.wind_mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(once.mean, new.mean, rtol=1e-10, atol=1e-12)
    # relaxing from the label's posterior: ḡ ← a ḡ, P_g ← a² (P_g − S) + S, a = e^{−Δt/τ_g}
    later = new.relaxed(float(new.t) + 0.7)
    a = np.exp(-0.7 / 2.0)
    np.testing.assert_allclose(later.wind_mean, a * np.asarray(new.wind_mean), rtol=1e-12)
    np.testing.assert_allclose(later.wind_cov, a**2 * (np.asarray(new.wind_cov) - P) + P,
                               rtol=1e-12, atol=1e-15)  # fmt: skip
    # the coefficients: one Kalman step per output at the shifted air velocity
    shifted = _shifted(lab, 0, np.asarray(new.wind_mean))[1:]
    _, e2, r2, h2 = (np.asarray(v) for v in _rows_jit(sur, *(jnp.asarray(c) for c in shifted)))
    for j in range(6):
        Sh = cov[j] @ h2[j]
        w = Sh * e2[j] / (h2[j] @ Sh + r2[j] + 0.01)
        np.testing.assert_allclose(new.mean[0, j], w, rtol=1e-7, atol=1e-10)
    with pytest.raises(ValueError, match="wind_sd must be"):
        tk.track(corrected, tk.gusts(tk.default_drift(corrected), sd=(1.0, 1.0)))
    with pytest.raises(ValueError, match="wind_tau > 0"):
        tk.track(corrected, tk.gusts(tk.default_drift(corrected), tau=0.0))


def test_wind_state_prediction_and_a_constant_wind_found(corrected, flights):
    """A model tracking a wind state predicts as its wind-free self at v_air + ḡ, its loads'
    variance widened by diag(J P_g Jᵀ) (J by central differences of that model); it stays a
    JAX function (vmap, jit, reverse derivative against central differences). Labels made by
    the corrected model at a wind 1.2 m/s along x and -0.6 along y beyond the logged one (its
    coefficients held: spread and bias at 1e-6) give the wind state that wind within four of
    its own posterior standard deviations (plus the 1e-3 m/s the linearisation leaves), τ_g long."""
    lab = flights[1].take(slice(0, 40))
    true = np.array([1.2, -0.6, 0.0])
    p = corrected.predict_batch(lab.rpm, lab.euler, lab.v_air + true, mean_only=True)
    rng = np.random.default_rng(8)
    made = dataclasses.replace(
        lab,
        force=np.asarray(p.force) + 0.05 * rng.normal(size=(len(lab), 3)),
        torque=np.asarray(p.torque) + 0.005 * rng.normal(size=(len(lab), 3)),
    )
    drift = _wind_drift(tau=1e6, spread=1e-6, bias_sd=1e-6)  # a wind that stays
    pre = tk.prequential(tk.track(corrected, drift, t0=float(lab.t[0])), made)
    st = pre.final.model.tracker
    sd = np.sqrt(np.diag(np.asarray(st.wind_cov)))
    assert np.all(np.abs(np.asarray(st.wind_mean) - true) <= 4 * sd + 1e-3), (st.wind_mean, sd)
    assert sd[0] < 0.5 and sd[1] < 0.4  # the labels told it: half the start's 1.0 and 0.8
    # the prediction
    tracked = pre.final
    still = dataclasses.replace(tracked, model=tracked.model.without_wind())
    q = (lab.rpm[3], lab.euler[3], lab.v_air[3])
    got = tracked.predict(*q)
    base = still.predict(q[0], q[1], q[2] + np.asarray(st.wind_mean))
    np.testing.assert_allclose(got.force, base.force, rtol=1e-12, atol=1e-12)
    eps = 1e-4
    J = np.zeros((6, 3))
    for k in range(3):
        d = np.eye(3)[k] * eps
        up, dn = (still.predict(q[0], q[1], q[2] + np.asarray(st.wind_mean) + s)
                  for s in (d, -d))  # fmt: skip
        J[:, k] = (np.r_[up.force, up.torque] - np.r_[dn.force, dn.torque]) / (2 * eps)
    extra = np.einsum("ia,ab,ib->i", J, np.asarray(st.wind_cov), J)
    np.testing.assert_allclose(np.asarray(got.variance)[:6],
                               np.asarray(base.variance)[:6] + extra, rtol=1e-6)  # fmt: skip
    np.testing.assert_allclose(np.asarray(got.variance)[6:], np.asarray(base.variance)[6:])
    # one compiled program: jit of vmap of the value and its reverse derivative, at a state and
    # at its central differences' two neighbours
    vg = jax.jit(jax.vmap(jax.value_and_grad(lambda v: tracked.predict(q[0], q[1], v).force[0])))
    v0, e = jnp.asarray(lab.v_air[0]), jnp.array([eps, 0.0, 0.0])
    val, g = vg(jnp.stack([v0, v0 + e, v0 - e]))
    fd = (val[1] - val[2]) / (2 * eps)
    np.testing.assert_allclose(float(g[0, 0]), float(fd), rtol=1e-5, atol=1e-7)
