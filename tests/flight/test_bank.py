"""gpg.flight.bank: online terms of different memories mixed by their predictions made ahead,
against each member run alone and a NumPy loop of the delayed scores written here."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight import bank as bk
from gpg.flight import correction as fc
from gpg.flight import tracking as tk
from tests.flight.test_correction import corrected, flights  # noqa: F401  (fixtures)

M = 8  # inducing inputs: the algebra is the same at 48
# labels each test runs through: one length, so that a bank's scan of one structure (members,
# ahead) compiles once for the module (with ahead 2, well past the ring's wrap)
N = 12
# a short memory with a narrow prior; longer ones, one per load output, with each δ's prior
MEMBERS = ((0.4, 0.05), ((20.0, 5.0, 60.0, 1.0, 2.0, 30.0), None))


def _offline_rows(sur, lab):
    """Each label's normalised input, residual against the offline model, noise and the
    offline model's band of the loads (what a bank's member is scored under)."""
    off = dataclasses.replace(sur, model=fc.offline_model(sur.model))

    @jax.jit
    def one(*row):
        x, y, r = fc.gp_rows(off, *row)
        mean, var = off.model.mean_var_one(x)
        return x, y - mean[:6], r, off.model.predictive_variance(var)[:6]

    out = [one(*(jnp.asarray(c[i]) for c in lab.columns()[1:])) for i in range(len(lab))]
    return tuple(np.stack([np.asarray(o[k]) for o in out]) for k in range(4))


@jax.jit
def _moments_now(o, x):
    """A term's mean, ``ψᵀΣψ`` and ``ψᵀψ`` at ``x``, as it stands."""
    return o.moments(o.features(x))


@jax.jit
def _moments(o, t, x):
    """The same of the term relaxed to ``t``."""
    return _moments_now(o.relaxed(t), x)


@jax.jit  # one program each: op by op these compiled hundreds
def _mean_band(m, x):
    """A model's mean and predictive variance at ``x``."""
    mean, var = m.mean_var_one(x)
    return mean, m.predictive_variance(var)


def test_one_member_is_the_term_adapt_builds(corrected, flights):  # noqa: F811
    """A bank of one member predicts, band included, what :func:`gpg.flight.adapt`'s term
    with its memory predicts, label by label, and ends in the same state."""
    lab = flights.take(slice(0, N))
    tau, var = 3.0, (0.1, 0.2, 0.3, 0.05, 0.05, 0.05)
    one = bk.adapt_bank(corrected, [(tau, var)], ahead=2, inducing=M, t0=lab.t[0])
    plain = fc.adapt(corrected, inducing=M, tau=tau, variance=var, t0=lab.t[0], band="shared")
    a, b = tk.prequential(one, lab), tk.prequential(plain, lab)
    # the same products in the same order, but the bank's weight (exactly one) multiplies
    # the mean and the band: rounding at a few ulp of the loads
    np.testing.assert_allclose(a.force, b.force, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.variance, b.variance, rtol=1e-12, atol=1e-15)
    end = fc.online_state(a.final).members
    np.testing.assert_allclose(end.mean[0], fc.online_state(b.final).mean, rtol=1e-12,
                               atol=1e-15)  # fmt: skip


@pytest.mark.parametrize("ahead", [1, 2])
def test_weights_score_each_member_ahead(corrected, flights, ahead):  # noqa: F811
    """The bank's log weights are, per load output, the sum of each label's log density under
    the member as it was ``ahead`` labels before (decayed by e^{−Δt/τ_w} between labels),
    written here from each member run alone; its mean and band are the mixture's moments."""
    lab = flights.take(slice(0, N))
    tw = 0.7
    sur = bk.adapt_bank(corrected, MEMBERS, ahead=ahead, weight_tau=tw, inducing=M,
                        t0=lab.t[0])  # fmt: skip
    pre = tk.prequential(sur, lab)
    X, resid, r, band = _offline_rows(corrected, lab)
    n = len(lab)
    # each member alone: its state before each label (the state "ahead" labels behind)
    alone = [fc.adapt(corrected, inducing=M, tau=t, variance=v, t0=lab.t[0], band="shared")
             for t, v in MEMBERS]  # fmt: skip
    states = []
    for sur_k in alone:
        st, seq = fc.online_state(sur_k), []
        for i in range(n):
            seq.append(st)
            row = (c[i] for c in lab.columns())
            st = fc.update_jit(fc.with_online(sur_k, st), *row).model.online
        states.append(seq + [st])
    log_w = np.zeros((2, 6))
    for i in range(n):
        if i:
            log_w *= np.exp(-(lab.t[i] - lab.t[i - 1]) / tw)
        for k in range(2):
            # the member with the labels up to i - ahead: its state before label i - ahead + 1
            o = states[k][max(i - ahead + 1, 0)]
            mu, q, q0 = (np.asarray(a) for a in _moments(o, lab.t[i], jnp.asarray(X[i])))
            s = np.maximum(band[i] - q0, 0.0) + q + r[i]
            log_w[k] += -0.5 * (np.log(2 * np.pi * s) + (resid[i] - mu) ** 2 / s)
    final = fc.online_state(pre.final)
    w_ref = np.exp(log_w - log_w.max(0))
    w_ref /= w_ref.sum(0)
    # a sum of n log densities of size ~10: rounding ~n·10·1e-16 relative to the weights
    np.testing.assert_allclose(np.asarray(final.weights()), w_ref, rtol=1e-9, atol=1e-12)
    for k in range(2):  # the members themselves run as they run alone
        np.testing.assert_allclose(final.members.mean[k], states[k][-1].mean, rtol=1e-10,
                                   atol=1e-13)  # fmt: skip
    # the mixture at a new state: Σ w η̄, and Σ w band_k + spread, per output (normalised)
    x = jnp.asarray(X[3])
    off = fc.offline_model(corrected.model)
    b = np.asarray(_mean_band(off, x)[1][:6])
    w = np.asarray(final.weights())
    mus, bands = [], []
    for k in range(2):
        mu, q, q0 = (np.asarray(a) for a in _moments_now(states[k][-1], x))
        mus.append(mu)
        bands.append(np.maximum(b - q0, 0.0) + q)
    mus, bands = np.stack(mus), np.stack(bands)
    mix = np.sum(w * mus, 0)
    want = np.sum(w * (bands + mus**2), 0) - mix**2
    m = fc.with_online(corrected, final).model
    mean, band = _mean_band(m, x)
    np.testing.assert_allclose(np.asarray(mean)[:6] - np.asarray(_mean_band(off, x)[0])[:6],
                               mix, rtol=1e-9, atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.asarray(band)[:6], want, rtol=1e-9)


def test_identical_members_keep_equal_weights_and_the_scan_is_the_loop(corrected, flights):  # noqa: F811
    """Two copies of one memory score alike: their weights stay one half, and the bank
    predicts as one member. ``online_step`` once a step from Python ends where
    ``prequential``'s scan ends."""
    lab = flights.take(slice(0, N))
    sur = bk.adapt_bank(corrected, [(2.0, None), (2.0, None)], ahead=2, inducing=M,
                        t0=lab.t[0])  # fmt: skip
    pre = tk.prequential(sur, lab)
    np.testing.assert_allclose(fc.online_state(pre.final).weights(), 0.5, rtol=1e-12)
    single = tk.prequential(bk.adapt_bank(corrected, [(2.0, None)], ahead=2, inducing=M,
                                          t0=lab.t[0]), lab)  # fmt: skip
    np.testing.assert_allclose(pre.force, single.force, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(pre.variance, single.variance, rtol=1e-12, atol=1e-15)
    step, st = fc.online_step(sur), fc.online_state(sur)
    for i in range(len(lab)):
        st = step(st, *(c[i] for c in lab.columns()))
    end = fc.online_state(pre.final)
    for a, b in zip(jax.tree.leaves(st), jax.tree.leaves(end), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-13)


def test_online_step_returns_only_what_moves_and_donates_only_its_own(corrected, flights):  # noqa: F811
    """The step hands back the arrays an update moves (weights, covariances, the ring, the
    log weights) and shares the rest with the state passed in (inducing inputs, factors,
    forgetting times). With ``donate`` it ends where the plain step does, the start state and
    an earlier state stay readable, and only the state it returned last is used up when
    passed back in. A state of another structure is refused by name."""
    lab = flights.take(slice(0, 6))
    sur = bk.adapt_bank(corrected, MEMBERS, ahead=2, inducing=M, t0=lab.t[0])
    rows = [tuple(c[i] for c in lab.columns()) for i in range(len(lab))]
    plain, donated = fc.online_step(sur), fc.online_step(sur, donate=True)
    start = fc.online_state(sur)
    a = plain(start, *rows[0])
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(start), strict=True):
        assert jax.typeof(x) == jax.typeof(y) and x.weak_type == y.weak_type  # one program
    for name in ("Z", "whiten", "tau", "lengthscale"):
        for part in ("members", "lagged"):
            assert getattr(getattr(a, part), name) is getattr(getattr(start, part), name)
    assert a.members.cov is not start.members.cov and a.ring_x is not start.ring_x
    b = donated(start, *rows[0])
    first = b
    b = donated(b, *rows[1])
    assert first.members.cov.is_deleted() and not start.members.cov.is_deleted()
    for row in rows[2:]:
        b = donated(b, *row)
    for row in rows[1:]:
        a = plain(a, *row)
    # the same updates, but XLA fuses a program that writes over its inputs otherwise: the
    # rounding of six rank-one updates, held as the scan against the loop above
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-10, atol=1e-13)
    again = donated(start, *rows[0])  # a state from elsewhere is copied, not used up
    assert not start.members.cov.is_deleted() and not again.members.cov.is_deleted()
    tracked = fc.online_state(tk.track(corrected, tk.default_drift(corrected), t0=lab.t[0]))
    with pytest.raises(ValueError, match="not of the structure of Bank"):
        plain(tracked, *rows[0])


def test_bank_predict_is_a_jax_function(corrected, flights, tmp_path):  # noqa: F811
    """jit, vmap and both derivatives of a bank model's prediction (after some labels, the
    weights unequal); the derivative matches central differences; a checkpoint keeps the
    bank (its state and weights: the same predictions)."""
    from gpg import checkpoint

    lab = flights.take(slice(0, N))
    sur = tk.prequential(bk.adapt_bank(corrected, MEMBERS, ahead=2, inducing=M,
                                       t0=lab.t[0]), lab).final  # fmt: skip
    rpm, euler, v = (jnp.asarray(a[10:14]) for a in (flights.rpm, flights.euler, flights.v_air))
    want = sur.predict_batch(rpm, euler, v)

    def f(vv):
        p = sur.predict(rpm[0], euler[0], vv)
        return jnp.sum(p.force) + jnp.sum(p.variance[:3])

    # one compiled program (jit of vmap: a second jit(vmap(predict)) would compile the model
    # again for nothing): the value and reverse derivative (vmapped) at the state and its
    # central differences' neighbours, and the forward derivative at the state
    h = 1e-5
    pts = jnp.concatenate([v[:1], v[0] + h * jnp.eye(3), v[0] - h * jnp.eye(3)])
    both = jax.jit(lambda p: (jax.vmap(jax.value_and_grad(f))(p),
                              jax.jvp(f, (p[0],), (jnp.ones(3),))[1]))  # fmt: skip
    (vals, grads), jv = both(pts)
    # the vmapped value is predict_batch's (two programs: rounding apart)
    np.testing.assert_allclose(vals[0], jnp.sum(want.force[0]) + jnp.sum(want.variance[0, :3]),
                               rtol=1e-12)  # fmt: skip
    g, fd = grads[0], (vals[1:4] - vals[4:7]) / (2 * h)
    # central differences of a smooth function of size ~10 at h: h² terms and 1e-16/h rounding
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(jv, np.sum(g), rtol=1e-10)
    checkpoint.save(tmp_path / "ckpt", sur)
    back = checkpoint.load(tmp_path / "ckpt")
    assert isinstance(fc.online_state(back), bk.Bank)
    # the same program on the restored arrays (jit of vmap above is another program, whose
    # fusion may round differently: equal only to rounding)
    again = back.predict_batch(rpm, euler, v)
    np.testing.assert_array_equal(again.force, want.force)
    np.testing.assert_array_equal(again.variance, want.variance)


def test_adapt_bank_refuses_bad_input(corrected, flights):  # noqa: F811
    with pytest.raises(ValueError, match="members is empty"):
        bk.adapt_bank(corrected, [])
    with pytest.raises(ValueError, match=r"members\[1\] must be"):
        bk.adapt_bank(corrected, [(1.0, None), 3.0])
    with pytest.raises(ValueError, match="ahead must be a whole number"):
        bk.adapt_bank(corrected, [(1.0, None)], ahead=0)
    with pytest.raises(ValueError, match="weight_tau must be a positive"):
        bk.adapt_bank(corrected, [(1.0, None)], weight_tau=0.0)
    with pytest.raises(ValueError, match="tau"):
        bk.adapt_bank(corrected, [(-1.0, None)])
    from gpg.flight.forgetting import Forgetting

    fo = Forgetting(tau=3.0, factor=1.0, variance=(0.1,) * 6, inducing=M, band="added",
                    log_likelihood=0.0, grid=(), labels=1)  # fmt: skip
    with pytest.raises(ValueError, match=r"members\[0\] was fitted with band='added'"):
        bk.adapt_bank(corrected, [fo], inducing=M)
    with pytest.raises(ValueError, match="fitted with 8 inducing inputs, the bank places 4"):
        bk.adapt_bank(corrected, [fo], inducing=4, band="added")
    assert bk.adapt_bank(corrected, [fo], inducing=M, band="added").model.online.size == 1


def test_bank_in_c_equals_the_scan(corrected, flights, tmp_path):  # noqa: F811
    """The bank's C (``gpg.export.to_c``): after a minute of labels (the flights' replayed,
    0.1 s apart, a 3 s gap in the middle so that every filter and weight relaxes), its state, the
    members, their lagged copies, the ring and the log weights, equals ``lax.scan`` of
    :func:`fc.update` (double: the same float64 Kalman steps, summed in another order: to
    1e-9), and its ``online_predict`` then equals ``predict`` of the updated model, band
    included, as CasADi's and ONNX's exports of it do at that state. The labels go in from
    Python (``gpg.export.to_native``), as a user's loop gives them. A bank is refused by
    name without the variance."""
    from gpg.export import to_casadi, to_onnx
    from tests.export.test_c_source import compiled
    from tests.flight.test_correction import _export_states, assert_c_predicts

    L, n = 3, 600
    sur = bk.adapt_bank(corrected, MEMBERS, ahead=L, inducing=M, t0=0.0)
    idx = np.arange(n) % len(flights)
    cols = [np.asarray(c, float)[idx] for c in flights.columns()]
    cols[0] = np.arange(n) * 0.1 + np.where(np.arange(n) >= n // 2, 3.0, 0.0)
    final, _ = jax.jit(lambda s, xs: jax.lax.scan(lambda c, r: (fc.update(c, *r), None), s, xs))(
        sur, tuple(jnp.asarray(c) for c in cols)
    )
    want = fc.online_state(final)
    pairs = {"mean": want.members.mean, "cov": want.members.cov, "lag_mean": want.lagged.mean,
             "lag_cov": want.lagged.cov, "lag_t": want.lagged.t, "ring_x": want.ring_x,
             "ring_y": want.ring_y, "ring_r": want.ring_r, "ring_t": want.ring_t,
             "log_weight": want.log_weight}  # fmt: skip
    assert np.ptp(np.asarray(want.weights()), axis=0).max() > 0.05  # the members told apart
    # float: the same steps with the filters' state stored in float, rounded at each label
    # (6e-8 each, amplified by the whitened weights' conditioning, and forgotten over the
    # members' memories); 1e-3 of each array's scale, which a step left out exceeds
    for dtype, tol in (("float", 1e-3), ("double", 1e-9)):
        nat, st = _c_bank(sur, tmp_path / dtype, dtype, len(MEMBERS), L, corrected.model.n_inputs)
        rows = np.column_stack([c.reshape(n, -1) for c in cols])
        spans = ((1, 5), (5, 8), (8, 11), (11, 14), (14, 17), (17, 20), (20, 23))
        for r in rows:  # from Python through gpg.export.to_native, as a user calls it
            assert nat.update(r[0], *(r[i:j] for i, j in spans)) is True
        for key, w in pairs.items():
            w = np.asarray(w)
            got = np.ctypeslib.as_array(getattr(st, key)).reshape(w.shape)
            np.testing.assert_allclose(got, w, rtol=0, err_msg=f"{dtype} {key}",
                                       atol=tol * max(1.0, float(np.abs(w).max())))  # fmt: skip
        assert np.array_equal(np.ctypeslib.as_array(st.ring_live).astype(bool),
                              np.asarray(want.ring_live))  # fmt: skip
        assert st.count == n and st.t == float(want.t)
    rpm, euler, v = _export_states(flights, 8)
    ref = final.predict_batch(rpm, euler, v)
    assert_c_predicts(nat.lib.quad_online_predict, st, ref, rpm, euler, v, 1e-7)
    for i in range(len(rpm)):  # the same call through Native.predict
        p = nat.predict(rpm[i], euler[i], v[i])
        np.testing.assert_allclose(p.force, ref.force[i], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(p.variance[:6], ref.variance[i, :6], rtol=1e-7)
    nat.reset()  # back to the exported state: the members' start, the weights equal
    assert st.count == 0 and np.all(np.ctypeslib.as_array(st.log_weight) == 0.0)
    with pytest.raises(ValueError, match="exports with variance=True only"):
        compiled(sur, tmp_path, "double", variance=False)
    # CasADi (double) and ONNX (the prior in float32, the correction in double) at the updated
    # state: the means to 1e-10 and 1e-5 of their scale, the band to the prior's variance
    # bound of each, relative to the band plus the offline one (the shared band takes each
    # member's prior out of it: the difference cancels, its error is the terms')
    from tests.flight.test_correction import onnx_outputs
    from tests.helpers import variance_rtol

    rpm, euler, v = (np.asarray(a, np.float32).astype(float) for a in (rpm, euler, v))
    ref = final.predict_batch(rpm, euler, v)
    offline = corrected.predict_batch(rpm, euler, v)
    scale = np.asarray(ref.variance) + np.asarray(offline.variance)
    loads = np.abs(np.concatenate([ref.force, ref.torque], 1)).max()
    pytest.importorskip("casadi")
    f = to_casadi(final)
    vtol = variance_rtol(fc.base(final), rpm, euler, v, None)
    for i in range(len(rpm)):
        res = [np.asarray(a).ravel() for a in f(rpm[i], euler[i], v[i])]
        want = np.concatenate([ref.force[i], ref.torque[i]])
        assert np.abs(np.concatenate(res[:2]) - want).max() <= 1e-10 * max(1.0, loads), i
        assert np.all(np.abs(res[3] - ref.variance[i]) <= (vtol[i] + 1e-9) * scale[i]), i
    got = onnx_outputs(to_onnx(final, tmp_path / "bank.onnx")["onnx"], rpm, euler, v)
    for key in ("force", "torque"):
        np.testing.assert_allclose(got[key], getattr(ref, key), atol=1e-5 * max(1.0, loads))
    v32 = variance_rtol(fc.base(final), rpm, euler, v, 2.0**-24)
    assert np.all(np.abs(got["variance"] - ref.variance) <= (v32[:, None] + 16 * 2.0**-24) * scale)


def _c_bank(sur, directory, dtype: str, k: int, ahead: int, d: int):
    """The bank's C built in ``dtype`` (:func:`gpg.export.to_native`), and its state seen as
    the struct the header declares, in ctypes (its size the compiler's)."""
    import ctypes

    from gpg.export import to_native

    directory.mkdir()
    nat = to_native(sur, directory, name="quad", dtype=dtype, flags=("-O2", "-std=c99", "-Wall",
                    "-Wextra", "-Werror"))  # fmt: skip
    f, g = ctypes.c_double, ctypes.c_float if dtype == "float" else ctypes.c_double

    class State(ctypes.Structure):
        _fields_ = [("mean", g * (k * 6 * M)), ("cov", g * (k * 6 * M * M)),
                    ("lag_mean", g * (k * 6 * M)), ("lag_cov", g * (k * 6 * M * M)),
                    ("lag_t", f * k), ("ring_x", f * (ahead * d)), ("ring_y", f * (ahead * 6)),
                    ("ring_r", f * (ahead * 6)), ("ring_t", f * ahead),
                    ("ring_live", ctypes.c_int * ahead), ("count", ctypes.c_long),
                    ("log_weight", f * (k * 6)), ("t", f)]  # fmt: skip

    assert ctypes.sizeof(State) == len(nat.state)
    return nat, State.from_buffer(nat.state)
