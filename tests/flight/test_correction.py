"""gpg.flight.correction: the prior corrected by flights (co-kriging), and adaptation while flying,
against NumPy references written here."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import checkpoint
from gpg.flight import correction as fc
from gpg.flight.labels import Labels

N_LABELS = 60
FIT = {"subset_size": N_LABELS, "max_steps": 40}  # a short fit: these tests check the algebra


def _states(rng, n):
    """In-box states: rotors near hover, small angles, flying along the nose at 3-12 m/s."""
    rpm = rng.uniform(2500, 5500, (n, 4))
    euler = np.column_stack(
        [rng.uniform(-0.5, 0.5, n), rng.uniform(-0.3, 0.1, n), rng.uniform(-0.2, 0.2, n)]
    )
    speed = rng.uniform(3, 12, n)
    v_air = np.column_stack([speed * np.cos(euler[:, 0]), speed * np.sin(euler[:, 0]), np.zeros(n)])
    return rpm, euler, v_air


@pytest.fixture(scope="module")
def flights(synthetic_surrogate):
    """Labels of a 'real' vehicle whose loads are the prior's times 1.2 plus a drag-like
    term, with known noise."""
    sur = synthetic_surrogate
    rng = np.random.default_rng(0)
    rpm, euler, v_air = _states(rng, N_LABELS)
    p = sur.predict_batch(rpm, euler, v_air, mean_only=True)
    M = np.asarray(sur.simple.values(np.concatenate([rpm, euler], 1)))
    drag = -0.05 * np.linalg.norm(v_air, axis=1, keepdims=True) * v_air
    force = M[:, :3] + 1.2 * (np.asarray(p.force) - M[:, :3]) + drag
    torque = np.asarray(p.torque) + 0.02
    fvar, tvar = np.full((N_LABELS, 3), 0.05**2), np.full((N_LABELS, 3), 0.005**2)
    force = force + 0.05 * rng.normal(size=force.shape)
    torque = torque + 0.005 * rng.normal(size=torque.shape)
    return Labels(
        t=np.arange(N_LABELS) * 0.1,
        rpm=rpm,
        euler=euler,
        v_air=v_air,
        force=force,
        torque=torque,
        force_var=fvar,
        torque_var=tvar,
        model_force=M[:, :3],
        model_torque=M[:, 3:],
        dropped={"total": N_LABELS},
        name="synthetic",
    )


@pytest.fixture(scope="module")
def corrected(synthetic_surrogate, flights):
    return fc.correct(synthetic_surrogate, flights, basis="physical", **FIT)


@pytest.fixture(scope="module")
def regression(synthetic_surrogate, flights):
    return fc.correct(synthetic_surrogate, flights, **FIT)


def _rbf(A, B, var, ls):
    d = (A[:, None, :] - B[None, :, :]) / ls
    return var * np.exp(-0.5 * np.sum(d * d, -1))


def test_training_rows_are_the_gp_frame_residuals(synthetic_surrogate, flights):
    """A world-frame label read as the GP's target: the prior's own mean prediction at a
    state, given as a label, comes back as the prior's normalised GP mean there."""
    sur = synthetic_surrogate
    p = sur.predict_batch(flights.rpm, flights.euler, flights.v_air, mean_only=True)
    own = dataclasses.replace(flights, force=np.asarray(p.force), torque=np.asarray(p.torque))
    X, Y, V = fc.training_rows(sur, own)
    np.testing.assert_allclose(Y, np.asarray(sur.model.predict_mean(X))[:, :6], atol=1e-9)
    # isotropic noise stays isotropic under the rotation into the GP's frame
    np.testing.assert_allclose(
        V[:, :3] * np.asarray(sur.normalizer.y_std[:3]) ** 2, 0.05**2, rtol=1e-12
    )


def test_corrected_mean_and_variance_compose(regression, flights):
    """``ρ ⊙ μ_prior + κ ⊙ m + δ`` and ``ρ² c var_prior + c_δ (var_δ + ν_δ²)``: each δ
    evaluated here in NumPy from its training inputs, α and hyperparameters (``m`` has a test
    of its own below); ``ρ`` and ``κ`` as point estimates (``basis="regression"``)."""
    m = regression.model
    assert isinstance(m, fc.Corrected) and len(m.delta) == 6 and m.explicit is None
    X, _, _ = fc.training_rows(regression, flights)
    Xq = X[:7] + 0.01
    mean, var = m.predict_unclipped(Xq)
    p_mean, p_var = m.prior.predict_unclipped(Xq)
    dm = []
    for d in m.delta:
        h = d.hyper
        kq = _rbf(Xq, np.asarray(d.X), float(h.variance), np.asarray(h.lengthscale))
        dm.append(kq @ np.asarray(d.alpha)[:, 0])
    expect = np.asarray(m.scale) * np.asarray(p_mean)
    expect[:, :6] += np.stack(dm, 1) + np.asarray(m.kappa) * np.asarray(jax.vmap(m.basis)(Xq))
    np.testing.assert_allclose(mean, expect, atol=1e-9)
    pv = np.asarray(m.predictive_variance(var))
    prior_part = np.maximum(np.asarray(p_var), 0)[:, None] * np.asarray(m.prior.output_scale)
    prior_part = prior_part * np.asarray(m.scale) ** 2
    delta_part = np.stack(
        [
            (np.maximum(np.asarray(var)[:, 1 + j], 0) + float(d.hyper.noise))
            for j, d in enumerate(m.delta)
        ],
        1,
    )
    np.testing.assert_allclose(pv[:, :6], prior_part[:, :6] + delta_part, rtol=1e-10)
    np.testing.assert_allclose(pv[:, 6:], prior_part[:, 6:], rtol=1e-10)


def test_band_split_into_its_terms(synthetic_surrogate, corrected):
    """``Surrogate.variance_parts``: the band's terms, world frame, summing to
    ``predict_batch``'s variance. Each taken back to the GP's frame (a diagonal ``d`` there is
    ``(R_WH ∘ R_WH) d`` in the world, inverted here with ``R_WH`` from ``to_airflow_frame``)
    is the term as the model forms it: the prior's ``ρ²`` times the prior surrogate's own
    latent term, each δ's noise ``c ν²`` the same at every state. A plain surrogate's terms
    are its latent variance and noise; an adapted model is refused by name."""
    from gpg.quadrotor.frames import to_airflow_frame

    rpm, euler, v = _states(np.random.default_rng(11), 20)
    parts = {k: np.asarray(a) for k, a in corrected.variance_parts(rpm, euler, v).items()}
    assert set(parts) == {"prior", "discrepancy", "discrepancy_noise", "basis"}
    assert all(np.all(a >= 0) for a in parts.values()) and parts["basis"].max() > 0
    # sums of a few non-negative terms: the order of the sums apart
    total = np.asarray(corrected.predict_batch(rpm, euler, v).variance)
    np.testing.assert_allclose(sum(parts.values()), total, rtol=1e-13)
    base = {k: np.asarray(a) for k, a in synthetic_surrogate.variance_parts(rpm, euler, v).items()}
    assert set(base) == {"latent", "noise"}
    want = np.asarray(synthetic_surrogate.predict_batch(rpm, euler, v).variance)
    np.testing.assert_allclose(base["latent"] + base["noise"], want, rtol=1e-13)
    m = corrected.model
    y2 = np.asarray(corrected.normalizer.y_std) ** 2
    noise = [float(d.hyper.noise * d.output_scale[0]) * y2[j] for j, d in enumerate(m.delta)]
    for i in range(len(rpm)):
        S = np.asarray(to_airflow_frame(euler[i], v[i], corrected.hover_speed)[2]) ** 2
        # |yaw| <= 0.5 rad: det S = cos 2ψ >= 0.54, so a solve loses a few roundings at most
        h = lambda w: np.r_[np.linalg.solve(S, w[:3]), np.linalg.solve(S, w[3:6]), w[6:]]  # noqa: B023, E731
        got, ref = h(parts["prior"][i]), np.asarray(m.scale) ** 2 * h(base["latent"][i])
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(h(parts["discrepancy_noise"][i])[:6], noise, rtol=1e-10)
    with pytest.raises(ValueError, match="an adapted model's band is not a sum"):
        fc.adapt(corrected, inducing=4, tau=2.0, t0=0.0).variance_parts(rpm, euler, v)


def test_correction_fits_the_real_vehicle(synthetic_surrogate, corrected, flights):
    """At the labels' states the corrected model is much closer
    to the 'real' loads than the prior, and its 95 % band covers them."""
    rpm, euler, v_air = flights.rpm, flights.euler, flights.v_air
    truth = flights.force  # noisy, σ = 0.05 N
    e0 = synthetic_surrogate.predict_batch(rpm, euler, v_air).force - truth
    p = corrected.predict_batch(rpm, euler, v_air)
    e1 = np.asarray(p.force) - truth
    assert np.sqrt(np.mean(e1**2)) < 0.25 * np.sqrt(np.mean(np.asarray(e0) ** 2))
    assert np.mean(np.abs(e1) <= 1.96 * np.sqrt(np.asarray(p.variance)[:, :3] + 0.05**2)) > 0.85
    # the scale: across the airflow (the GP frame's y) the real residual is 1.2 times the
    # prior's exactly; along it the drag adds (the scale and κ take some of it)
    rho = np.asarray(corrected.model.scale)
    assert abs(rho[1] - 1.2) < 0.05 and rho[0] > 1.0
    np.testing.assert_array_equal(np.asarray(corrected.model.scale[6:]), 1.0)


def test_values_only_baseline_has_no_prior(synthetic_surrogate, corrected, flights):
    # corrected again from a corrected one: from its prior, not on top of it
    vo = fc.correct(corrected, flights, use_prior=False, simple_term=False, **FIT)
    np.testing.assert_array_equal(np.asarray(vo.model.scale[:6]), 0.0)
    assert vo.model.kappa is None and vo.model.basis is None  # δ carries it all
    assert vo.config["flight_correction"]["use_prior"] is False
    assert vo.model_name == "gpgs_hybrid+flight"
    assert not isinstance(vo.model.prior, fc.Corrected)
    assert fc.base(vo).model_name == "gpgs_hybrid"
    assert type(fc.base(vo).model) is type(synthetic_surrogate.model)


def test_corrected_is_a_jax_function(corrected, flights):
    """Reverse derivatives through the corrected prediction against finite differences, and
    its float32 copy (jit and vmap: predict_batch, in the test above; forward mode: the
    precision walk below traces it)."""
    r, e, v = (jnp.asarray(a[:5]) for a in (flights.rpm, flights.euler, flights.v_air))

    @jax.jit  # compiled: op by op the derivative took seconds
    def fx(vv):
        return corrected.predict(r[0], e[0], vv).force[0]

    g_rev = jax.jit(jax.grad(fx))(v[0])
    h = 1e-5
    fd = np.array(
        [(fx(v[0] + h * np.eye(3)[i]) - fx(v[0] - h * np.eye(3)[i])) / (2 * h) for i in range(3)]
    )
    np.testing.assert_allclose(g_rev, fd, rtol=1e-5, atol=1e-7)
    # float32: the prior's part as accurate as float32 storage allows (1e-4 of the loads), and
    # each discrepancy's sum Σ α_i k_i off by a few roundings (8 ε₃₂) of its terms' total size
    # Σ|α_i| σ: an ill-conditioned δ has large, cancelling α
    f32 = corrected.astype(jnp.float32)
    p32 = f32.predict_batch(
        np.float32(flights.rpm), np.float32(flights.euler), np.float32(flights.v_air)
    )
    p64 = corrected.predict_batch(flights.rpm, flights.euler, flights.v_air)
    scale = np.abs(np.asarray(p64.force)).max()
    eps = float(np.finfo(np.float32).eps)
    m = corrected.model
    std = np.asarray(corrected.normalizer.y_std[:3])
    sums = [float(np.abs(np.asarray(d.alpha)).sum() * d.hyper.variance) for d in m.delta[:3]]
    bound = 8 * eps * float(np.max(std * np.asarray(sums)))
    np.testing.assert_allclose(p32.force, p64.force, atol=1e-4 * scale + bound)


def test_corrected_checkpoint_and_export(corrected, regression, flights, tmp_path):
    from gpg.export import to_c

    path = checkpoint.save(tmp_path / "c", corrected)
    back = checkpoint.load(path)
    # at every label: the batch other tests predict, so that its program is compiled once
    a = corrected.predict_batch(flights.rpm, flights.euler, flights.v_air)
    b = back.predict_batch(flights.rpm, flights.euler, flights.v_air)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert "flight_correction" in checkpoint.read_metadata(path)
    from gpg.flight.tracking import track

    # a tracked physical basis exports to C (tests/flight/test_tracking.py); the regression
    # form's tracked columns have no physical terms in the export
    with pytest.raises(ValueError, match="without the physical basis"):
        to_c(track(regression), tmp_path / "c_src")
    assert not (tmp_path / "c_src").exists()


def _export_states(flights, n=40):
    """The labels' states, half moved a little (inside), a quarter twice as fast with rotors
    2.5 times faster (outside the box: where the physical basis extrapolates)."""
    rng = np.random.default_rng(7)
    i = rng.integers(0, len(flights), n)
    rpm, euler, v = (np.array(a)[i] for a in (flights.rpm, flights.euler, flights.v_air))
    rpm[: n // 2] *= rng.uniform(0.97, 1.03, (n // 2, 4))
    v[-n // 4 :] *= 2.0
    rpm[-n // 4 :] *= 2.5
    return rpm, euler, v


def onnx_outputs(path, rpm, euler, v) -> dict:
    """The ONNX file's outputs by name, run by ONNX Runtime on the states in float32."""
    ort = pytest.importorskip("onnxruntime")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {"rpm": rpm, "euler": euler, "v_air": v}
    res = sess.run(None, {k: np.asarray(a, np.float32) for k, a in feeds.items()})
    return dict(zip([o.name for o in sess.get_outputs()], res, strict=True))


def _float_triangles_bound(sur, rpm, euler, v) -> np.ndarray:
    """Per query, a bound on what storing each discrepancy's triangle ``T`` in float (a float
    C export) moves a load's variance: ``T (1 + ε)`` with ``|ε| <= u`` moves ``‖T k‖²`` by at
    most ``2 u ‖|T| |k|‖²`` (to first order; the sums are double), times the discrepancy's
    output scale and ``y_std²``; a world component is a convex mix of the six (rotation²)."""
    from gpg.export.layout import spec

    u32 = 2.0**-24
    c = spec(sur, variance=True).correction
    z3 = jnp.zeros(3)
    rows = jax.jit(jax.vmap(lambda r, e, a: fc.gp_rows(sur, r, e, a, z3, z3, z3, z3)[0]))
    X = np.asarray(rows(jnp.asarray(rpm), jnp.asarray(euler), jnp.asarray(v)))
    y_std = np.asarray(sur.normalizer.y_std)[:6]
    out = np.zeros(len(X))
    for j, d in enumerate(c.deltas):
        k = d.sigma * np.exp(
            -0.5 * (((X[:, None, :] - d.points[None]) / d.lengthscale) ** 2).sum(-1)
        )
        Tk = k @ np.abs(d.variance_factor()).T  # |T| |k| (k > 0)
        out = np.maximum(out, 2 * u32 * np.sum(Tk**2, 1) * d.output_scale * y_std[j] ** 2)
    return out


def _exports_equal_predict(sur, flights, tmp_path, dtype, *, n=40, n_casadi=8, jacobians=0,
                           onnx=True):  # fmt: skip
    """The corrected model's exports against ``predict``, at ``n`` states rounded to float32
    (what ONNX reads: every export then sees the same states, and one prediction serves all).

    * C in ``dtype``: force and torque to 1e-10 of their scale in double, 1e-5 in float (the
      prior's arrays in float; the correction's stay double); the variance to the prior's
      ``variance_rtol`` plus 1e-9 relative (the correction's double sums, positive terms:
      the prior's relative bound holds for the sum), in float plus the discrepancies'
      triangles stored in float (:func:`_float_triangles_bound`); ``in_domain`` equal, met
      both ways.
    * CasADi at the first ``n_casadi`` states: values to 1e-10, the variance as C's double,
      ``in_domain`` equal; its Jacobian of the force against ``jax.jacrev`` of ``predict`` to
      1e-8 of its largest entry at the first ``jacobians`` states.
    * ONNX (float32 inside the frame): force and torque to 1e-5 of their scale; the variance
      to ``variance_rtol`` at float32's unit roundoff plus 16 u (the last products)."""
    from gpg.export import to_casadi, to_onnx
    from tests.export.test_c_source import compiled
    from tests.helpers import variance_rtol

    u32 = 2.0**-24
    rpm, euler, v = (np.asarray(a, np.float32).astype(float) for a in _export_states(flights, n))
    ref = sur.predict_batch(rpm, euler, v)
    want_var = np.asarray(ref.variance)
    vtol = variance_rtol(fc.base(sur), rpm, euler, v, None if dtype == "double" else u32)
    out, call = compiled(sur, tmp_path, dtype)
    assert out["variance"] and out["record"]["model"].endswith("+flight")
    rtol = 1e-10 if dtype == "double" else 1e-5
    atol = np.zeros(n) if dtype == "double" else _float_triangles_bound(sur, rpm, euler, v)
    inside = []
    for i in range(n):
        ok, f, t, lv, var = call(rpm[i], euler[i], v[i])
        for got, want in ((f, ref.force[i]), (t, ref.torque[i]), (lv, ref.levels[i])):
            assert np.abs(got - want).max() <= rtol * max(1.0, np.abs(want).max()), (i, got, want)
        assert np.all(np.abs(var - want_var[i]) <= (vtol[i] + 1e-9) * want_var[i] + atol[i]), (
            i, var)  # fmt: skip
        assert ok == bool(ref.in_domain[i])
        inside.append(ok)
    assert 0 < sum(inside) < len(inside)
    ca = pytest.importorskip("casadi")
    f = to_casadi(sur)
    syms = [ca.MX.sym(k, d) for k, d in (("rpm", 4), ("euler", 3), ("v", 3))]
    jf = ca.Function("j", syms, [ca.jacobian(f(*syms)[0], ca.vertcat(*syms))])
    jac = jax.jit(jax.jacrev(lambda *a: sur.predict(*a).force, argnums=(0, 1, 2)))
    # CasADi is double: the float export's bound is looser than it needs, and still a bound
    vtol64 = vtol
    for i in range(n_casadi):
        res = [np.asarray(a).ravel() for a in f(rpm[i], euler[i], v[i])]
        want = np.concatenate([ref.force[i], ref.torque[i], ref.levels[i]])
        assert np.abs(np.concatenate(res[:3]) - want).max() <= 1e-10 * max(1, np.abs(want).max())
        assert np.all(np.abs(res[3] - want_var[i]) <= (vtol64[i] + 1e-9) * want_var[i])
        assert float(res[4][0]) == float(ref.in_domain[i])
        if i < jacobians:
            Jj = np.concatenate([np.asarray(a) for a in jac(rpm[i], euler[i], v[i])], axis=1)
            Jc = np.asarray(jf(rpm[i], euler[i], v[i]))
            assert np.abs(Jc - Jj).max() <= 1e-8 * np.abs(Jj).max()
    if not onnx:
        return
    got = onnx_outputs(to_onnx(sur, tmp_path / "c.onnx")["onnx"], rpm, euler, v)
    for key in ("force", "torque"):
        want = np.asarray(getattr(ref, key))
        scale = np.maximum(1.0, np.abs(want).max(axis=1))
        assert np.all(np.abs(got[key] - want).max(axis=1) <= 1e-5 * scale), key
    v32 = vtol if dtype != "double" else variance_rtol(fc.base(sur), rpm, euler, v, u32)
    tol = (v32[:, None] + 16 * u32) * want_var
    assert np.all(np.abs(got["variance"] - want_var) <= tol)
    assert np.array_equal(got["in_domain"], np.asarray(ref.in_domain))


def test_corrected_model_outside_python(corrected, flights, tmp_path):
    """Prior, ρ, κ M, the physical basis with its integrated band and exact discrepancies, in
    double C, CasADi and ONNX (the inducing-point discrepancies in float C and CasADi:
    test_every_label_...)."""
    _exports_equal_predict(corrected, flights, tmp_path, "double", jacobians=2)


@pytest.mark.slow
def test_corrected_flies_in_env_and_mpc(corrected, vehicle):
    """The RL environment and the MPC's dynamics take a corrected surrogate like any other
    (slow: both compile the six discrepancy GPs with the prior)."""
    from gpg.envs.quadrotor import QuadrotorEnv
    from gpg.mpc import Dynamics

    env = QuadrotorEnv.create(vehicle, corrected)
    obs, state = env.reset(jax.random.PRNGKey(0))
    obs, state, reward, done, _ = env.step(jax.random.PRNGKey(1), state, jnp.zeros(4))
    assert np.all(np.isfinite(np.asarray(obs)))
    dyn = Dynamics.create(vehicle, corrected, 0.01)
    x = jnp.concatenate(
        [
            jnp.zeros(3),
            jnp.array([5.0, 0, 0]),
            jnp.array([1.0, 0, 0, 0]),
            jnp.zeros(3),
            jnp.full(4, 3600.0),
        ]
    )
    lin = dyn.linearize(x, jnp.full(4, 3600.0), 0.0)
    assert np.all(np.isfinite(np.asarray(lin.A))) and np.all(np.asarray(lin.variance) > 0)


def test_correct_refuses_bad_labels(synthetic_surrogate, flights):
    with pytest.raises(ValueError, match="at least one flight"):
        fc.correct(synthetic_surrogate, [])
    with pytest.raises(ValueError, match="at least 8 labels"):
        fc.correct(synthetic_surrogate, flights.take(slice(0, 5)))
    bad = dataclasses.replace(flights, force=flights.force.copy())
    bad.force[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite GP Y rows"):
        fc.correct(synthetic_surrogate, bad)


def _online_reference(adapted, flights, n):
    """The batch posterior of the whitened weights given the first ``n`` labels, in NumPy:
    ``w | y ~ N(A⁻¹ Ψᵀ R⁻¹ y, A⁻¹)``, ``A = Ψᵀ R⁻¹ Ψ + I``, per output."""
    on = adapted.model.online
    offline = eqx.tree_at(lambda s: s.model.online, adapted, None, is_leaf=lambda x: x is None)
    X, Y, V = fc.training_rows(adapted, flights.take(slice(0, n)))
    resid = Y - np.asarray(offline.model.predict_mean(X))[:, :6]
    Z = np.asarray(on.Z)
    means, covs = [], []
    for j in range(6):
        ls, var = np.asarray(on.lengthscale[j]), float(on.variance[j])
        K = _rbf(Z, Z, var, ls) + 1e-8 * var * np.eye(Z.shape[0])
        L = np.linalg.cholesky(K)
        Psi = np.linalg.solve(L, _rbf(Z, X, var, ls)).T  # (n, m)
        r = V[:, j] + float(on.noise[j])
        A = Psi.T @ (Psi / r[:, None]) + np.eye(Z.shape[0])
        means.append(np.linalg.solve(A, Psi.T @ (resid[:, j] / r)))
        covs.append(np.linalg.inv(A))
    return np.stack(means), np.stack(covs)


def test_online_filter_is_the_batch_posterior(corrected, flights):
    """Without forgetting (τ far beyond the flight), label-by-label updates give the batch
    posterior; inside lax.scan and once a step from Python alike."""
    adapted = fc.adapt(corrected, inducing=12, tau=1e12, t0=0.0)
    cols = [jnp.asarray(c) for c in flights.columns()]
    n = 25
    scanned, _ = jax.lax.scan(
        lambda s, x: (fc.update(s, *x), None), adapted, tuple(c[:n] for c in cols)
    )
    mean, cov = _online_reference(adapted, flights, n)
    np.testing.assert_allclose(scanned.model.online.mean, mean, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(scanned.model.online.cov, cov, rtol=1e-6, atol=1e-9)
    step = fc.online_step(adapted)
    on = adapted.model.online
    for i in range(n):
        on = step(on, *(c[i] for c in cols))
    np.testing.assert_allclose(on.mean, scanned.model.online.mean, rtol=1e-10, atol=1e-12)
    # fixed memory: the state's arrays keep their shapes; and their types, weak or not (else
    # the second call of the compiled step compiles a second program)
    for a, b in zip(jax.tree.leaves(on), jax.tree.leaves(adapted.model.online), strict=True):
        assert jax.typeof(a) == jax.typeof(b) and a.weak_type == b.weak_type
    # the adapted surrogate predicts with the online term
    p0 = corrected.predict(flights.rpm[0], flights.euler[0], flights.v_air[0])
    p1 = fc.with_online(adapted, on).predict(flights.rpm[0], flights.euler[0], flights.v_air[0])
    assert not np.allclose(p0.force, p1.force)


def test_forgetting_relaxes_to_the_prior(corrected, flights):
    adapted = fc.adapt(corrected, inducing=8, tau=2.0, t0=0.0)
    cols = [np.asarray(c) for c in flights.columns()]
    s = adapted
    for i in range(10):
        s = fc.update_jit(s, *(c[i] for c in cols))
    on = s.model.online
    assert np.abs(np.asarray(on.mean)).max() > 1e-3
    # after 10 τ without labels: the mean shrinks by e^-10, the covariance returns to I
    later = on.relaxed(float(on.t) + 20.0)
    np.testing.assert_allclose(later.mean, np.exp(-10.0) * np.asarray(on.mean), rtol=1e-9)
    eye = np.broadcast_to(np.eye(on.Z.shape[0]), later.cov.shape)
    np.testing.assert_allclose(later.cov, eye, atol=1e-8)
    # time never runs backwards: an older label does not un-forget
    same = on.relaxed(float(on.t) - 5.0)
    np.testing.assert_allclose(same.cov, on.cov, rtol=0, atol=0)
    # one forgetting time per output: each output's weights relax at their own rate, in
    # closed form a_j = e^{-Δt/τ_j}, Σ_j ← a_j² Σ_j + (1 − a_j²) I
    taus = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 2.0])
    own = dataclasses.replace(on, tau=jnp.asarray(taus)).relaxed(float(on.t) + 3.0)
    a = np.exp(-3.0 / taus)
    np.testing.assert_allclose(own.mean, a[:, None] * np.asarray(on.mean), rtol=1e-12)
    want = a[:, None, None] ** 2 * np.asarray(on.cov) + (1 - a[:, None, None] ** 2) * eye
    np.testing.assert_allclose(own.cov, want, rtol=1e-12, atol=1e-15)
    # one per weight (an OU process each: a term of several time scales): Σ ← AΣA + I − A²
    per = np.linspace(1.0, 9.0, on.mean.size).reshape(on.mean.shape)
    own = dataclasses.replace(on, tau=jnp.asarray(per)).relaxed(float(on.t) + 3.0)
    a = np.exp(-3.0 / per)
    np.testing.assert_allclose(own.mean, a * np.asarray(on.mean), rtol=1e-12)
    want = a[:, :, None] * np.asarray(on.cov) * a[:, None, :] + (1 - a**2)[:, :, None] * eye
    np.testing.assert_allclose(own.cov, want, rtol=1e-12, atol=1e-15)


def _c_predict(predict, st, rpm, euler, v):
    """An export's ``<name>_online_predict`` (``predict``, from ctypes) at each state: (N, 6)
    loads, (N, 12) variances (the loads' first) and whether each is in the domain."""
    import ctypes

    D = ctypes.POINTER(ctypes.c_double)
    loads, var, ok = np.zeros((len(rpm), 6)), np.zeros((len(rpm), 12)), []
    for i in range(len(rpm)):
        f, t, lv, vv = np.zeros(3), np.zeros(3), np.zeros(8), np.zeros(12)
        args = [np.ascontiguousarray(x).ctypes.data_as(D) for x in (rpm[i], euler[i], v[i], f,
                                                                      t, lv, vv)]  # fmt: skip
        ok.append(predict(ctypes.byref(st), *args))
        loads[i], var[i] = np.concatenate([f, t]), vv
    return loads, var, np.asarray(ok, bool)


def assert_c_predicts(predict, st, ref, rpm, euler, v, var_rtol: float) -> None:
    """:func:`_c_predict` against the library's ``ref`` (a batch of predictions at the same
    states): ``in_domain`` equal, force and torque to 1e-9 of their scale, the loads'
    variance to ``var_rtol``."""
    loads, var, ok = _c_predict(predict, st, rpm, euler, v)
    for i in range(len(rpm)):
        assert ok[i] == bool(ref.in_domain[i])
        want = np.concatenate([ref.force[i], ref.torque[i]])
        assert np.abs(loads[i] - want).max() <= 1e-9 * max(1, np.abs(want).max())
        np.testing.assert_allclose(var[i, :6], ref.variance[i, :6], rtol=var_rtol)


def test_shared_band_takes_the_online_prior_out_of_the_offline_band(corrected, flights, tmp_path):
    """``adapt(band="shared")``: the loads' band is ``max(b − ψᵀψ, 0) + ψᵀΣψ`` (``b`` the
    offline model's, normalised), written here from the state's arrays; before any label it is
    ``max(b, ψᵀψ)``, the offline band where η's prior fits inside it; the mean is the added
    band's. C (to_c), CasADi and ONNX predict the same band; a checkpoint keeps the mode."""
    import ctypes
    import subprocess

    from gpg import checkpoint
    from gpg.export import to_c, to_casadi, to_onnx

    cols = tuple(jnp.asarray(c[:30]) for c in flights.columns())
    scan = jax.jit(lambda s, xs: jax.lax.scan(lambda c, r: (fc.update(c, *r), None), s, xs)[0])
    runs = {b: fc.adapt(corrected, inducing=8, tau=3.0, band=b) for b in ("added", "shared")}
    assert runs["shared"].model.online.shared and not runs["added"].model.online.shared
    offline = fc.offline_model(corrected.model)
    X = np.asarray(fc.training_rows(corrected, flights)[0])
    lat = jax.jit(jax.vmap(lambda m, x: m.predictive_variance(m.mean_var_one(x)[1])[:6],
                           in_axes=(None, 0)))  # fmt: skip
    b = np.asarray(lat(offline, X))
    for when in ("start", "after"):
        s_run = runs["shared"] if when == "start" else scan(runs["shared"], cols)
        a_run = runs["added"] if when == "start" else scan(runs["added"], cols)
        on = s_run.model.online
        psi = np.asarray(jax.vmap(on.features)(jnp.asarray(X)))  # (N, 6, m)
        q0 = np.einsum("njm,njm->nj", psi, psi)
        post = np.einsum("njm,jmk,njk->nj", psi, np.asarray(on.cov), psi)
        np.testing.assert_allclose(lat(s_run.model, X), np.maximum(b - q0, 0) + post,
                                   rtol=1e-10, atol=1e-14)  # fmt: skip
        np.testing.assert_allclose(lat(a_run.model, X), b + post, rtol=1e-10, atol=1e-14)
        if when == "start":
            np.testing.assert_allclose(post, q0, rtol=1e-12)
            assert np.any(b > q0)  # where η's prior fits inside the band, the band is b's
        # at the export's states below: its predict_batch compiles once
        ps, pa = (r.predict_batch(*_export_states(flights, 12)) for r in (s_run, a_run))
        np.testing.assert_array_equal(np.asarray(ps.force), np.asarray(pa.force))
    to_c(s_run, tmp_path, name="model")
    so = tmp_path / "model.so"
    res = subprocess.run(["cc", "-O2", "-std=c99", "-Wall", "-Werror", "-shared", "-fPIC", "-o",
                          str(so), str(tmp_path / "model.c"), "-lm"],
                         capture_output=True, text=True)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    lib = ctypes.CDLL(str(so))
    m = on.Z.shape[0]

    class State(ctypes.Structure):
        _fields_ = [("mean", ctypes.c_double * (6 * m)), ("cov", ctypes.c_double * (6 * m * m)),
                    ("t", ctypes.c_double)]  # fmt: skip

    st = State()
    lib.model_online_init(ctypes.byref(st))  # the exported state: the updated one
    rpm, euler, v = _export_states(flights, 12)
    ref = s_run.predict_batch(rpm, euler, v)
    _, var, ok = _c_predict(lib.model_online_predict, st, rpm, euler, v)
    np.testing.assert_array_equal(ok, np.asarray(ref.in_domain))
    np.testing.assert_allclose(var[:, :6], ref.variance[:, :6], rtol=1e-7)
    # CasADi (double) and ONNX (the prior in float32, the correction in double): the band to
    # the prior's variance bound of each, relative to the band before η's prior is taken
    # out of it (the difference cancels; its error is the terms')
    from tests.helpers import variance_rtol

    u32 = 2.0**-24
    rpm, euler, v = (np.asarray(a, np.float32).astype(float) for a in (rpm, euler, v))
    ref = s_run.predict_batch(rpm, euler, v)
    offline = corrected.predict_batch(rpm, euler, v)
    scale = np.asarray(ref.variance) + np.asarray(offline.variance)
    pytest.importorskip("casadi")
    f = to_casadi(s_run)
    vtol = variance_rtol(fc.base(s_run), rpm, euler, v, None)
    for i in range(len(rpm)):
        got = np.asarray(f(rpm[i], euler[i], v[i])[3]).ravel()
        assert np.all(np.abs(got - ref.variance[i]) <= (vtol[i] + 1e-9) * scale[i]), i
    got = onnx_outputs(to_onnx(s_run, tmp_path / "model.onnx")["onnx"], rpm, euler, v)
    v32 = variance_rtol(fc.base(s_run), rpm, euler, v, u32)
    assert np.all(np.abs(got["variance"] - ref.variance) <= (v32[:, None] + 16 * u32) * scale)
    checkpoint.save(tmp_path / "ckpt", s_run)
    assert checkpoint.load(tmp_path / "ckpt").model.online.shared


def test_adapt_checks(synthetic_surrogate, corrected, flights):
    with pytest.raises(ValueError, match="prepared by gpg.flight.adapt"):
        fc.update(
            corrected,
            0.0,
            flights.rpm[0],
            flights.euler[0],
            flights.v_air[0],
            flights.force[0],
            flights.torque[0],
            flights.force_var[0],
            flights.torque_var[0],
        )
    with pytest.raises(ValueError, match="tau must be one or 6 positive"):
        fc.adapt(corrected, tau=0.0)
    with pytest.raises(ValueError, match="inputs must be"):
        fc.adapt(corrected, inputs=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="band must be 'added' or 'shared'"):
        fc.adapt(corrected, band="both")
    # a prior without a correction adapts too (δ = 0, the online term alone)
    plain = fc.adapt(synthetic_surrogate, inducing=6)
    assert plain.model.delta == () and plain.model.online.Z.shape == (6, 8)


def test_products_are_highest(corrected, flights):
    """The corrected and adapted model's predictions and the update run every product at
    Precision.HIGHEST (tests/test_precision.py's walk), in float32 where TF32 would apply."""
    from tests.test_precision import assert_highest

    adapted = fc.adapt(corrected, inducing=6).astype(jnp.float32)
    rpm, euler, v = (jnp.asarray(a[:20], jnp.float32) for a in (flights.rpm, flights.euler,
                                                                 flights.v_air))  # fmt: skip
    assert_highest(adapted.predict, rpm[0], euler[0], v[0], what="corrected predict")
    batch = lambda: adapted.predict_batch(rpm, euler, v, chunk=8)  # noqa: E731
    assert_highest(batch, what="corrected predict_batch")

    def f(a):
        p = adapted.predict(rpm[0], euler[0], a)
        return jnp.concatenate([p.force, p.variance[:3]])

    assert_highest(jax.jacfwd(f), v[0], what="corrected jacfwd(predict)")
    cols = [jnp.asarray(c[0], jnp.float32) for c in flights.columns()]
    assert_highest(fc.update, adapted, *cols, what="gpg.flight.update")


def test_simple_term_recovers_a_thrust_coefficient(synthetic_surrogate, flights):
    """A real vehicle whose rotors make 10 % less thrust and drag torque than ``M`` says, and
    otherwise the prior's loads: ``κ`` (the coefficient of ``M``'s own loads, in the GP's
    frame) comes out as −0.1 on every load output, ``ρ`` as 1, and ``m(x)`` is ``M``'s wrench
    rotated by the input's own angles (written out here)."""
    from gpg.quadrotor.frames import R_WB

    sur = synthetic_surrogate
    p = sur.predict_batch(flights.rpm, flights.euler, flights.v_air, mean_only=True)
    real = dataclasses.replace(
        flights,
        force=np.asarray(p.force) - 0.1 * flights.model_force,
        torque=np.asarray(p.torque) - 0.1 * flights.model_torque,
    )
    c = fc.correct(sur, real, **FIT)
    np.testing.assert_allclose(np.asarray(c.model.kappa), -0.1, atol=2e-3)
    np.testing.assert_allclose(np.asarray(c.model.scale[:6]), 1.0, atol=2e-2)
    X, _, _ = fc.training_rows(sur, real)
    x = np.asarray(sur.normalizer.x_inv(X[0]))
    F_B, tau_B = (np.asarray(a) for a in sur.simple.wrench_body(x[:4]))
    R = np.asarray(R_WB(x[4:7]))
    expect = np.concatenate([R @ F_B, R @ tau_B]) / np.asarray(sur.normalizer.y_std[:6])
    np.testing.assert_allclose(c.model.basis(jnp.asarray(X[0])), expect, rtol=1e-12)


def test_the_basis_columns_evaluated_once_a_query(corrected, flights, monkeypatch):
    """``M``'s column and the physical columns are evaluated once per query by the mean, the
    mean with its variance and a tracked model's (whose columns are the model's own), each
    a frame rotation and hundreds of operations in every program that predicts; counted while
    tracing, and the count can fail: the columns read twice by hand are counted twice."""
    from gpg.flight import basis as fb
    from gpg.flight import tracking as tk

    calls = {"simple": 0, "physics": 0}

    def counted(cls, key):
        inner = cls.__call__

        def call(self, x):
            calls[key] += 1
            return inner(self, x)

        monkeypatch.setattr(cls, "__call__", call)

    counted(fc.SimpleBasis, "simple")
    counted(fb.PhysicalBasis, "physics")
    tracked = tk.track(corrected, tk.default_drift(corrected)).model
    x = jnp.asarray(fc.training_rows(corrected, flights)[0][0])
    for fn in (corrected.model.mean_one, corrected.model.mean_var_one, tracked.mean_one,
               tracked.mean_var_one):  # fmt: skip
        calls.update(simple=0, physics=0)
        jax.make_jaxpr(fn)(x)
        assert calls == {"simple": 1, "physics": 1}, fn
    calls.update(simple=0, physics=0)
    m = corrected.model
    jax.make_jaxpr(lambda x: (m.basis(x), m.basis(x), m.explicit.mean(x)))(x)
    assert calls == {"simple": 2, "physics": 1}


def test_physical_basis_integrated_out(corrected, flights):
    """The physical basis with its coefficients integrated out (Rasmussen and Williams 2.7),
    against NumPy written here: ``β̄ = A⁻¹(Hᵀ K⁻¹ y + B⁻¹ b)``, the mean
    ``h_*ᵀ β̄ + k_*ᵀ K⁻¹ (y − H β̄)`` and the variance's added ``Rᵀ A⁻¹ R``,
    ``R = h_* − Hᵀ K⁻¹ k_*``, with ``K`` each discrepancy's kernel plus the labels' own noise
    and its ``ν²``; the band wider where the basis extrapolates (twice the fastest label)."""
    from gpg.flight.basis import PRIORS, TERMS

    m = corrected.model
    e = m.explicit
    assert e is not None and e.columns == ("prior", "simple", *TERMS)
    X, Y, V = fc.training_rows(corrected, flights)
    mu = np.asarray(m.prior.predict_mean(X))[:, :6]
    simple = np.asarray(jax.vmap(m.basis)(jnp.asarray(X)))
    phys = np.asarray(jax.vmap(e.physics)(jnp.asarray(X)))
    sd = np.array([PRIORS[c] for c in e.columns])
    b = np.zeros(sd.size)
    b[0] = 1.0
    near = X[:5] + 0.01
    far = near.copy()
    far[:, 7] = 2 * X[:, 7].max() - X[:, 7].min()  # the airspeed, normalised: far above
    Xq = np.concatenate([near, far])
    mean, var = m.predict_unclipped(Xq)
    pv = np.asarray(m.predictive_variance(var))
    p_mean, p_var = (np.asarray(a) for a in m.prior.predict_unclipped(Xq))
    hq_simple = np.asarray(jax.vmap(m.basis)(jnp.asarray(Xq)))
    hq_phys = np.asarray(jax.vmap(e.physics)(jnp.asarray(Xq)))
    total = np.zeros(Xq.shape[0])
    for j, d in enumerate(m.delta):
        h = d.hyper
        ls, s2, nu = np.asarray(h.lengthscale), float(h.variance), float(h.noise)
        K = _rbf(X, X, s2, ls) + np.diag(V[:, j] + nu)
        H = np.column_stack([mu[:, j], simple[:, j], phys[:, j]])
        Ki = np.linalg.inv(K)
        A = np.diag(1 / sd**2) + H.T @ Ki @ H
        beta = np.linalg.solve(A, H.T @ Ki @ Y[:, j] + b / sd**2)
        got = np.concatenate([[m.scale[j], m.kappa[j]], np.asarray(e.beta[j])])
        np.testing.assert_allclose(got, beta, rtol=1e-6, atol=1e-8)
        kq = _rbf(Xq, X, s2, ls)
        hq = np.column_stack([p_mean[:, j], hq_simple[:, j], hq_phys[:, j]])
        expect = hq @ beta + kq @ Ki @ (Y[:, j] - H @ beta)
        np.testing.assert_allclose(np.asarray(mean)[:, j], expect, rtol=1e-6, atol=1e-7)
        R = hq - kq @ Ki @ H
        v_beta = np.einsum("qp,pr,qr->q", R, np.linalg.inv(A), R)
        v_delta = s2 - np.einsum("qn,nm,qm->q", kq, Ki, kq) + nu
        v_prior = np.maximum(p_var, 0) * float(m.prior.output_scale[j]) * float(m.scale[j]) ** 2
        np.testing.assert_allclose(pv[:, j], v_prior + v_delta + v_beta, rtol=1e-6)
        total += v_beta / v_beta.mean()
    # wider where no label went: each far query against the same query at its own speed
    assert np.all(total[5:] > total[:5])


def test_physical_basis_with_the_prior_taken_as_it_is(synthetic_surrogate, flights):
    """``scale=False`` with the physical basis (an identified vehicle's prior): ``ρ = 1``, no
    prior column, the prior's mean moved into the targets; the coefficients and the mean of
    one component against the explicit-basis GP in NumPy."""
    from gpg.flight.basis import PRIORS, TERMS

    sur = fc.correct(synthetic_surrogate, flights, basis="physical", scale=False, **FIT)
    m, e = sur.model, sur.model.explicit
    np.testing.assert_array_equal(np.asarray(m.scale), 1.0)
    assert e.columns == ("simple", *TERMS) and not e.with_prior
    X, Y, V = fc.training_rows(sur, flights)
    j = 0
    d = m.delta[j]
    ls, s2, nu = np.asarray(d.hyper.lengthscale), float(d.hyper.variance), float(d.hyper.noise)
    s2, nu = s2 * float(d.output_scale[0]), nu * float(d.output_scale[0])
    Xj = jnp.asarray(X)
    H = np.column_stack([np.asarray(jax.vmap(m.basis)(Xj))[:, j],
                         np.asarray(jax.vmap(e.physics)(Xj))[:, j]])  # fmt: skip
    y = Y[:, j] - np.asarray(m.prior.predict_mean(X))[:, j]
    sd = np.array([PRIORS[c] for c in e.columns])
    Ki = np.linalg.inv(_rbf(X, X, s2, ls) + np.diag(V[:, j] + nu))
    beta = np.linalg.solve(np.diag(1 / sd**2) + H.T @ Ki @ H, H.T @ Ki @ y)  # prior mean 0
    np.testing.assert_allclose(np.concatenate([[m.kappa[j]], np.asarray(e.beta[j])]), beta,
                               rtol=1e-6, atol=1e-8)  # fmt: skip
    Xq = X[:4] + 0.01
    Hq = np.column_stack([np.asarray(jax.vmap(m.basis)(jnp.asarray(Xq)))[:, j],
                          np.asarray(jax.vmap(e.physics)(jnp.asarray(Xq)))[:, j]])  # fmt: skip
    expect = np.asarray(m.prior.predict_mean(Xq))[:, j] + Hq @ beta
    expect += _rbf(Xq, X, s2, ls) @ Ki @ (y - H @ beta)
    np.testing.assert_allclose(np.asarray(m.predict_unclipped(Xq)[0])[:, j], expect, rtol=1e-6,
                               atol=1e-7)  # fmt: skip


def test_physical_columns_in_closed_form(corrected):
    """The basis's drag, rotor-drag, inflow and edgewise columns at one input, written out in
    NumPy from the airflow frame's angles and speed (``v_B = R_HBᵀ (V, 0, 0)``)."""
    from scipy.spatial.transform import Rotation

    from gpg.flight.basis import AIR_DENSITY, RPM_REF

    e = corrected.model.explicit
    norm = corrected.normalizer
    x = np.array([3200.0, 3900.0, 3500.0, 4100.0, 0.4, -0.2, 0.15, 7.0])
    xn = np.asarray(norm.x(jnp.asarray(x)))
    R = Rotation.from_euler("ZYX", x[4:7]).as_matrix()  # R_HB = Rz(yaw) Ry(pitch) Rx(roll)
    v = R.T @ np.array([x[7], 0.0, 0.0])
    s = np.linalg.norm(v)
    p = np.asarray(corrected.simple.positions)
    w = x[:4] / RPM_REF
    cols = []
    for a in range(3):
        f = np.zeros(3)
        f[a] = -0.5 * AIR_DENSITY * s * v[a]
        cols.append(np.concatenate([R @ f, np.zeros(3)]))
    for fi in (
        -w[:, None] * np.array([v[0], v[1], 0.0]),
        w[:, None] * np.array([0.0, 0.0, v[2]]),
        np.tile([0.0, 0.0, -(v[0] ** 2 + v[1] ** 2)], (4, 1)),
    ):
        cols.append(np.concatenate([R @ fi.sum(0), R @ np.cross(p, fi).sum(0)]))
    expect = np.stack(cols, 1) / np.asarray(norm.y_std[:6])[:, None]
    np.testing.assert_allclose(np.asarray(e.physics(jnp.asarray(xn))), expect, rtol=1e-10,
                               atol=1e-12)  # fmt: skip


def test_correct_refuses_an_unknown_basis(synthetic_surrogate, flights):
    with pytest.raises(ValueError, match="basis must be 'physical' or 'regression'"):
        fc.correct(synthetic_surrogate, flights, basis="linear")


# the second flight's push (N, world), and the fixture prior's band made this much narrower
# (its output scale: a prior of more data), so that the held-out factor has something to
# widen with the prior's band beside it
PUSH = np.array([1.2, -0.9, 0.6])
CONFIDENT = 0.005
OUT = 6  # labels of the first flight taken out of the prior's domain


def _pushed_flights(synthetic_surrogate, flights):
    """The fixture's prior made confident (``CONFIDENT``), and its flight cut in two: ``a``,
    whose first ``OUT`` labels are flown three times faster than the prior's data went (out
    of its domain, where its band is its kernel's whole variance), and ``b``, pushed by
    ``PUSH``."""
    prior = synthetic_surrogate
    prior = eqx.tree_at(lambda s: s.model.output_scale, prior, prior.model.output_scale * CONFIDENT)
    half = len(flights) // 2
    a = dataclasses.replace(flights.take(slice(0, half)), name="a")
    fast = np.where(np.arange(half)[:, None] < OUT, 3.0, 1.0)
    a = dataclasses.replace(a, v_air=a.v_air * fast)
    b_ = flights.take(slice(half, None))
    b_ = dataclasses.replace(b_, name="b", force=b_.force + PUSH)
    return prior, a, b_


def _held_out_reference(cal, prior, lab, groups, j):
    """NumPy: each label of ``lab`` predicted by load output ``j``'s physical basis and
    discrepancy of ``cal`` (``ρ = 1``; its hyperparameters and terms' prior as chosen)
    fitted on the other group's labels, the coefficients integrated out; returns the squared
    error ``e²``, the latent variance ``v`` (with ``ν²``), the label's noise ``n``, the
    uncorrected ``prior``'s share ``p`` of the band (its own output scale) and the
    coefficients' posterior mean with each group held out (G, P)."""
    from gpg.flight.basis import PRIORS, TERMS

    m = cal.model
    f = cal.config["flight_correction"]["basis_prior"]["factors"][j]
    X, Y, V = fc.training_rows(cal, lab)
    Y, V = Y[:, j], V[:, j]
    h = m.delta[j].hyper
    ls, s2, nu = np.asarray(h.lengthscale), float(h.variance), float(h.noise)
    Y = Y - np.asarray(m.prior.predict_mean(X))[:, j]  # ρ = 1: the prior's mean moved over
    Xj = jnp.asarray(X)
    simple, phys = jax.vmap(m.basis)(Xj)[:, j], jax.vmap(m.explicit.physics)(Xj)[:, j]
    H = np.column_stack([np.asarray(simple), np.asarray(phys)])
    assert m.explicit.columns == ("simple", *TERMS)
    sd = np.array([PRIORS[c] * (f if c in TERMS else 1.0) for c in m.explicit.columns])
    np.testing.assert_array_equal(fc._chosen_prior(cal, False, True)[j], sd)  # fit_drift's
    e2v, betas = [], []
    for g in np.unique(groups):
        tr, te = groups != g, groups == g
        Ki = np.linalg.inv(_rbf(X[tr], X[tr], s2, ls) + np.diag(V[tr] + nu))
        A = np.diag(1 / sd**2) + H[tr].T @ Ki @ H[tr]
        beta = np.linalg.solve(A, H[tr].T @ Ki @ Y[tr])  # the prior's mean b = 0
        betas.append(beta)
        kq = _rbf(X[te], X[tr], s2, ls)
        mean = H[te] @ beta + kq @ Ki @ (Y[tr] - H[tr] @ beta)
        R = H[te] - kq @ Ki @ H[tr]
        var = s2 - np.einsum("qn,nm,qm->q", kq, Ki, kq) + nu
        var += np.einsum("qp,pr,qr->q", R, np.linalg.inv(A), R)
        e2v.append(np.column_stack([(Y[te] - mean) ** 2, var, V[te]]))
    e2, v, n = np.concatenate(e2v).T
    p = np.asarray(prior.model.predict(Xj)[1]) * float(prior.model.output_scale[j])
    return e2, v, n, p, np.array(betas)


def test_band_calibrated_on_held_out_flights(synthetic_surrogate, flights, monkeypatch):
    """Labels of two flights, the second pushed by a steady force the first did not have:
    each component's discrepancy and coefficient variance scaled by the ``c`` (at least 1)
    under which each flight, predicted from the other, has a mean squared standardised error
    of 1 over its labels in the prior's domain, under the band the model predicts: the
    labels' noise and the prior's share ``ρ² var_prior`` unscaled beside ``c`` times the
    latent variance; the physical terms' prior the candidate under which the worse-predicted
    held-out flight is predicted best by the discrepancy's own band (the factor solved
    without the prior's share). Both written out here in NumPy for the most widened
    component; calibrate=False keeps 1 and chooses the terms' prior as before. A component
    that both flights over-cover keeps ``c = 1`` and has the prior's share narrowed instead
    (:func:`_check_prior_share`)."""
    # two candidates keep the test's fits few; the rule is the same for any grid
    monkeypatch.setattr(fc, "BASIS_PRIOR_GRID", (0.01, 1.0))
    prior, a, b_ = _pushed_flights(synthetic_surrogate, flights)
    half = len(a)
    # ρ = 1 (the identified physics taken as it is): "auto" chooses the terms' prior
    cal = fc.correct(prior, [a, b_], basis="physical", scale=False, **FIT)
    choice = cal.config["flight_correction"]["basis_prior"]
    scores = np.asarray(choice["held_out_nlpd"])
    assert choice["grid"] == [0.01, 1.0] and scores.shape == (6, 2)
    np.testing.assert_array_equal(choice["factors"], np.take([0.01, 1.0], scores.argmin(1)))
    m = cal.model
    j = int(np.argmax([float(d.output_scale[0]) for d in m.delta]))
    f = choice["factors"][j]
    raw = fc.correct(prior, [a, b_], basis="physical", scale=False,
                     calibrate=False, basis_prior=f, **FIT)  # fmt: skip
    assert raw.config["flight_correction"]["basis_prior"]["factors"] == [f] * 6
    lab = Labels.concatenate([a, b_])
    groups = np.repeat([0, 1], [half, len(flights) - half])
    e2, v, n, p, betas = _held_out_reference(cal, prior, lab, groups, j)
    # the coefficients' spread between the flights held out: the delete-a-flight jackknife
    # (G − 1)/G Σ_g (β₋g − β̃)(β₋g − β̃)ᵀ; with two flights, (β₋₁ − β₋₂)(β₋₁ − β₋₂)ᵀ / 4
    d = betas[0] - betas[1]
    J = np.outer(d, d) / 4
    assert np.sqrt(np.max(np.diag(J))) > 1e-3 * np.max(np.abs(betas))  # a spread to add
    # the prior's domain at the labels (in the rows' order)
    dom = np.asarray(prior.predict_batch(lab.rpm, lab.euler, lab.v_air).in_domain)
    assert 0 < dom.sum() < dom.size  # both kinds of label, so that the domain is read
    assert np.median(p / v) > 0.1  # a share the solve must not ignore

    def factor(e2, v, n):  # mean(e² / (c v + n)) = 1, c >= 1, by bisection on log c
        lo, hi = 0.0, 40.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.mean(e2 / (np.exp(mid) * v + n)) > 1 else (lo, mid)
        return max(1.0, float(np.exp(lo)))

    c = factor(e2[dom], v[dom], n[dom] + p[dom])
    own = factor(e2, v, n)  # without the prior's share: what the candidates are scored under
    assert 1.0 < c < own  # each flight misses the other's push; the prior's share covers some
    # the labels out of the domain left out of the solve: with them, another factor
    assert abs(factor(e2, v, n + p) - c) > 0.02 * c
    np.testing.assert_allclose(float(m.delta[j].output_scale[0]), c, rtol=1e-6)
    assert choice["prior_share"][j] == 1.0  # a flight under-covered: the prior's share kept
    assert float(m.prior.output_scale[j]) == float(prior.model.output_scale[j])
    # the chosen candidate's score: the worse of the two held-out flights' mean negative log
    # Gaussian density under the discrepancy's own band
    s2o = own * v + n
    nlpd = 0.5 * np.log(2 * np.pi * s2o) + 0.5 * e2 / s2o
    worst = max(nlpd[:half].mean(), nlpd[half:].mean())
    np.testing.assert_allclose(scores[j].min(), worst, rtol=1e-6)
    # each flight's share inside the 95 % band held out as predicted (e² ≤ 1.96² (c v + p +
    # n)): recorded per output, compared away from the edge (a label within 1e-6 of it could
    # fall either way)
    s2c = c * v + n + p
    inside = e2 <= 1.959964**2 * s2c
    assert not np.any(np.abs(e2 / (1.959964**2 * s2c) - 1) < 1e-6)
    np.testing.assert_allclose(
        choice["held_out_coverage95"][j],
        [inside[:half].mean(), inside[half:].mean()],
        rtol=0,
        atol=1e-12,
    )
    assert len(choice["held_out_coverage95"]) == 6
    assert float(raw.model.delta[j].output_scale[0]) == 1.0

    # the coefficients' covariance: the posterior's times c, plus the spread (raw held no
    # flight out: its posterior's alone); compared as covariances, to the refit's rounding
    # against the largest entry (a Cholesky factor's small entries carry its differences)
    def cov(sur):
        C = np.asarray(sur.model.explicit.cov_chol[j])
        return C @ C.T

    def close(got, want):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.max(np.abs(want)))

    close(cov(cal), c * cov(raw) + J)
    np.testing.assert_allclose(choice["coefficient_spread"][j], np.sqrt(np.diag(J)),
                               rtol=1e-6, atol=1e-9 * np.sqrt(np.max(np.diag(J))))  # fmt: skip
    np.testing.assert_allclose(choice["held_out_factor"][j], c, rtol=1e-6)
    # calibrate=False leaves the band as the discrepancies give it; the terms' prior is chosen
    # as before (the candidates scored under their own factor), and the held-out shares are of
    # that band
    own = fc.correct(prior, [a, b_], basis="physical", scale=False,
                     calibrate=False, **FIT)  # fmt: skip
    mine = own.config["flight_correction"]["basis_prior"]
    # the same fits run again: equal to the rounding of a refit, not bit for bit
    assert mine["factors"] == choice["factors"]
    np.testing.assert_allclose(mine["held_out_nlpd"], choice["held_out_nlpd"], rtol=1e-9)
    np.testing.assert_allclose(mine["held_out_factor"], choice["held_out_factor"], rtol=1e-9)
    assert all(float(d.output_scale[0]) == 1.0 for d in own.model.delta)
    close(cov(own), cov(raw) + J)  # the spread without c
    # coefficient_spread=False: the posterior's alone, c times, and the same mean
    bare = fc.correct(prior, [a, b_], basis="physical", scale=False,
                      coefficient_spread=False, **FIT)  # fmt: skip
    assert bare.config["flight_correction"]["coefficient_spread"] is False
    assert cal.config["flight_correction"]["coefficient_spread"] is True
    close(cov(bare), c * cov(raw))
    # at the labels' states and at twice their airspeed (past every flight)
    for k in (1.0, 2.0):
        pc, pb = (s.predict_batch(lab.rpm[:16], lab.euler[:16], k * lab.v_air[:16])
                  for s in (cal, bare))  # fmt: skip
        np.testing.assert_allclose(np.asarray(pc.force), np.asarray(pb.force), rtol=1e-9,
                                   atol=1e-12)  # fmt: skip
        assert np.all(np.asarray(pc.variance) >= np.asarray(pb.variance) * (1 - 1e-9))
    inside1 = e2 <= 1.959964**2 * (v + n + p)
    assert not np.any(np.abs(e2 / (1.959964**2 * (v + n + p)) - 1) < 1e-6)
    want = [inside1[:half].mean(), inside1[half:].mean()]
    np.testing.assert_allclose(mine["held_out_coverage95"][j], want, rtol=0, atol=1e-12)
    _check_prior_share(cal, own, prior, lab, groups, dom)


def _check_prior_share(cal, own, prior, lab, groups, dom):
    """The component of ``cal`` with the least ``q``: every flight held out covered more widely
    than its band says, so ``c = 1`` and the prior's share is narrowed to the largest over the
    flights of the ``f`` at which that flight's mean ``e² / (v + f p + n)`` over its labels
    in the domain is 1 (NumPy, by bisection; :data:`fc.PRIOR_SHARE_FLOOR` where ``v + n``
    alone covers both, as here for the torques, which neither flight pushes; the interior
    root is :func:`test_prior_share_is_the_worst_flights_root`'s); the prior's output scale
    times ``q`` there, what :func:`fc.base` undoes exactly; ``own`` (calibrate=False) keeps
    the prior's."""
    choice = cal.config["flight_correction"]["basis_prior"]
    k = int(np.argmin(choice["prior_share"]))
    q = choice["prior_share"][k]
    assert q < 1.0 and choice["held_out_factor"][k] == 1.0
    e2, v, n, p, _ = _held_out_reference(cal, prior, lab, groups, k)
    assert np.median(p[dom] / v[dom]) > 0.1  # a share that could have covered the errors
    z2 = [np.mean((e2 / (v + q * p + n))[(groups == g) & dom]) for g in (0, 1)]
    if q > fc.PRIOR_SHARE_FLOOR:  # the worse flight's band as wide as its errors
        np.testing.assert_allclose(max(z2), 1.0, rtol=1e-6)
    else:  # the floor: each flight covered at it; without the floor, a root below it
        assert max(z2) < 1.0
    inside = e2 <= 1.959964**2 * (v + q * p + n)  # c = 1
    assert not np.any(np.abs(e2 / (1.959964**2 * (v + q * p + n)) - 1) < 1e-6)
    want = [inside[groups == g].mean() for g in (0, 1)]
    np.testing.assert_allclose(choice["held_out_coverage95"][k], want, rtol=0, atol=1e-12)
    # the prior's share of the predicted band: q times the uncalibrated model's, per output
    qs = np.ones(prior.model.n_outputs)
    qs[:6] = cal.config["flight_correction"]["prior_share"]
    os0 = np.asarray(prior.model.output_scale)
    np.testing.assert_allclose(np.asarray(cal.model.prior.output_scale), os0 * qs, rtol=1e-12)
    assert cal.config["flight_correction"]["prior_output_scale"] == os0.tolist()
    np.testing.assert_array_equal(np.asarray(fc.base(cal).model.output_scale), os0)
    xs = jnp.asarray(fc.training_rows(cal, lab)[0][:5])
    latent = jax.jit(lambda g: jax.vmap(g.mean_var_one)(xs)[1])  # compiled, not op by op
    parts = [latent(s.model) for s in (cal, own)]
    got, ref = (s.model.variance_parts(v)["prior"] for s, v in zip((cal, own), parts, strict=True))
    np.testing.assert_allclose(np.asarray(got), np.asarray(ref) * qs, rtol=1e-12)
    assert own.config["flight_correction"]["prior_share"] is None
    np.testing.assert_array_equal(np.asarray(own.model.prior.output_scale), os0)


def test_coefficient_spread_is_the_grouped_jackknife():
    """For an estimate that is the groups' mean (each group's own ``b_g``), the delete-a-group
    jackknife of :func:`fc._spread` is the groups' sample covariance over ``G``, the variance
    of their mean (closed form); one group gives none."""
    rng = np.random.default_rng(5)
    b = rng.normal(size=(4, 3)) * np.array([1.0, 0.1, 10.0])
    held = [(b.sum(0) - b[g]) / 3 for g in range(4)]  # each group held out in turn
    np.testing.assert_allclose(fc._spread(held), np.cov(b.T, ddof=1) / 4, rtol=1e-12,
                               atol=1e-14 * np.max(b**2))  # fmt: skip
    assert fc._spread(held[:1]) is None


def test_prior_share_is_the_worst_flights_root():
    """``fc._share``: for each flight the ``f`` at which its mean ``e² / (v + f p + n)`` is 1
    (NumPy bisection), the largest of them, not a pooled one; 1 where a flight is under-covered
    with the prior's whole share; the floor where ``v + n`` alone covers every flight."""
    rng = np.random.default_rng(3)
    m = 400
    v, n, p = rng.uniform(0.1, 0.3, 2 * m), rng.uniform(0.05, 0.1, 2 * m), rng.uniform(1, 3, 2 * m)
    flight = np.repeat([0, 1], m)
    scale = np.repeat([0.6, 1.2], m)  # the second flight's errors the larger share of p
    e2 = rng.chisquare(1, 2 * m) * (v + n + scale * 0.3 * p)

    def root(i):  # by bisection on log f over [floor, 1]
        lo, hi = np.log(fc.PRIOR_SHARE_FLOOR), 0.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.mean(e2[i] / (v[i] + np.exp(mid) * p[i] + n[i])) > 1 else (
                lo, mid)  # fmt: skip
        return float(np.exp(lo))

    fs = [root(flight == g) for g in (0, 1)]
    assert fc.PRIOR_SHARE_FLOOR < fs[0] < 0.8 * fs[1] < 0.8  # two interior roots, apart
    q = fc._share(e2, v, n, p, flight)
    np.testing.assert_allclose(q, fs[1], rtol=1e-9)
    z2 = [np.mean((e2 / (v + q * p + n))[flight == g]) for g in (0, 1)]
    np.testing.assert_allclose(z2[1], 1.0, rtol=1e-9)
    assert z2[0] < 1.0
    # a flight under-covered even with the whole share keeps it
    assert fc._share(np.where(flight == 0, e2 * 10, e2), v, n, p, flight) == 1.0
    # errors the discrepancy's band and the noise cover alone: the floor
    assert fc._share(0.1 * e2, v, n, p, flight) == fc.PRIOR_SHARE_FLOOR


def test_thinned_labels_calibrated_as_the_labels_kept(synthetic_surrogate, flights, monkeypatch):
    """``max_labels`` thins the labels before the held-out calibration reads them: each
    kept row's prior domain and band are its own label's, so the model is the one corrected
    on the kept labels themselves (the same rows, subsets and solves)."""
    monkeypatch.setattr(fc, "BASIS_PRIOR_GRID", (1.0,))
    prior, a, b_ = _pushed_flights(synthetic_surrogate, flights)
    n = len(a) + len(b_)
    keep = fc._thin(n, n - 9)
    kept = [a.take(keep[keep < len(a)]), b_.take(keep[keep >= len(a)] - len(a))]
    assert len(kept[0]) < len(a) and OUT - 1 in keep  # thinned, out-of-domain labels kept
    fit = {"basis": "physical", "scale": False, **FIT, "max_steps": 5}  # an equivalence: few steps
    thinned = fc.correct(prior, [a, b_], max_labels=len(keep), **fit)
    own = fc.correct(prior, kept, **fit)
    got, want = ([float(d.output_scale[0]) for d in m.model.delta] for m in (thinned, own))
    got, want = np.array(got), np.array(want)
    assert got.max() > 1.0  # a factor that the domain and the band move
    np.testing.assert_allclose(got, want, rtol=1e-9)
    shares = [m.config["flight_correction"]["prior_share"] for m in (thinned, own)]
    np.testing.assert_allclose(*shares, rtol=1e-9)
    # shares of labels: a refit's rounding may move one label across its band's edge
    np.testing.assert_allclose(
        thinned.config["flight_correction"]["basis_prior"]["held_out_coverage95"],
        own.config["flight_correction"]["basis_prior"]["held_out_coverage95"],
        rtol=0,
        atol=1.0 / min(len(k) for k in kept) + 1e-12,
    )


def test_every_label_through_inducing_inputs(synthetic_surrogate, corrected, flights, tmp_path):
    """Beyond ``exact_labels`` each discrepancy is an inducing-point GP on every label. With
    every label inducing it is the exact correction (the physical basis's ``G``, ``β̄`` and
    band included); with fewer (the regression basis here), a model that checkpoints like any
    other and says what it holds."""
    from gpg.gp.inducing import InducingGP

    every = fc.correct(synthetic_surrogate, flights, basis="physical",
                       exact_labels=N_LABELS // 2, inducing=N_LABELS, **FIT)  # fmt: skip
    assert all(isinstance(d, InducingGP) for d in every.model.delta)
    assert every.config["flight_correction"]["inducing"] == N_LABELS
    # off the labels, at their shape: corrected's predict_batch of that shape is compiled
    rpm, euler, v_air = flights.rpm * 1.02, flights.euler, flights.v_air + 0.5
    pe = corrected.predict_batch(rpm, euler, v_air)
    pi = every.predict_batch(rpm, euler, v_air)
    # The inducing Gram's jitter (1e-8 σ) is the only difference; the labels' Gram has a
    # condition number near 1e3 (noise 0.05² against loads of a few N): 1e-4 relative is ample.
    for a, b in ((pi.force, pe.force), (pi.torque, pe.torque)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * float(np.abs(b).max()))
    v = pe.variance[:, :6]
    np.testing.assert_allclose(pi.variance[:, :6], v, rtol=1e-4, atol=1e-6 * float(v.max()))
    # the fit's settings of the fixtures: their compiled programs serve this one too
    few = fc.correct(synthetic_surrogate, flights, exact_labels=N_LABELS // 2, inducing=12,
                     **FIT)  # fmt: skip
    assert few.model.describe()["flight_correction"]["inducing"] == 12
    assert few.model.describe()["flight_correction"]["n_labels"] == N_LABELS
    # the loops that read δ's variance at every label fold its two triangles into one
    X = jnp.asarray(fc.training_rows(few, flights)[0][:8])
    latent = jax.jit(lambda g: jax.vmap(g.mean_var_one)(X)[1])  # one program for each form
    for d, f in zip(few.model.delta, few.model.variance_views().delta, strict=True):
        assert f.post.shape[0] == 0
        v, vf = np.asarray(latent(d)), np.asarray(latent(f))
        # rounding of the largest terms the two forms pass through, ‖W‖₂² ‖k‖² ≤ ‖W‖₂² m σ²
        W, m = np.asarray(d.whiten), d.X.shape[0]
        bound = (
            64 * np.finfo(float).eps * np.linalg.norm(W, 2) ** 2 * m * float(d.hyper.variance) ** 2
        )
        np.testing.assert_allclose(vf, v, rtol=0, atol=bound)
        assert v.max() > 100 * bound  # the variance told apart from that rounding
    _stacked_as_one_by_one(few, corrected, X, flights)
    _offline_moments_stacked(every, flights)
    back = checkpoint.load(checkpoint.save(tmp_path / "few", few))
    assert jax.tree.structure(back.model) == jax.tree.structure(few.model)
    for a, b in zip(jax.tree.leaves(few.model), jax.tree.leaves(back.model), strict=True):
        np.testing.assert_array_equal(a, b)  # the same model: the same predictions
    # ρ, κ M and inducing-point δ in float C and in CasADi
    _exports_equal_predict(few, flights, tmp_path / "c", "float", n_casadi=4, onnx=False)
    with pytest.raises(ValueError, match="inducing must be >= 1"):
        fc.correct(synthetic_surrogate, flights, inducing=0)


def _row_tolerances(d, x, k):
    """How far a :class:`StackedInducing` row ``k`` of ``δ`` ``d`` at ``x`` and the mean and
    latent variance read from it may lie from ``d``'s own, by rounding alone: the two sum
    ``r² = ‖a‖² + ‖b‖² − 2 a·b`` in other orders, ``|Δr²| ≤ 4 D ε (‖a‖² + ‖b‖²)`` for each row,
    so ``|Δk| ≤ k |Δr²| / 2``; the mean's error is at most ``Σ |k w| |Δr²| / 2``, the
    variance's ``‖T Δk‖ (2 ‖T k‖ + ‖T Δk‖) ≤ 3 ‖T‖₂² ‖k‖ ‖Δk‖``."""
    eps = np.finfo(float).eps
    ls = np.asarray(d.hyper.lengthscale)
    a, B = np.asarray(x) / ls, np.asarray(d.X) / ls
    dr2 = 4 * B.shape[1] * eps * (a @ a + np.sum(B * B, 1))
    w = np.asarray(d.weights)[:, 0]
    dk = k * dr2 / 2 + 4 * eps * k
    mean_tol = np.sum(np.abs(k * w) * dr2) + 4 * k.size * eps * np.sum(np.abs(k * w))
    T = np.asarray(d.whiten)
    var_tol = 3 * np.linalg.norm(T, 2) ** 2 * np.linalg.norm(k) * np.linalg.norm(dk)
    var_tol += 4 * k.size * eps * np.linalg.norm(T @ k) ** 2
    return dk, mean_tol, var_tol


def _offline_moments_stacked(every, flights):
    """A bank scores each label under the offline band (:meth:`Corrected.offline_moments`):
    through the stack each kernel row is read once, for ``δ``'s mean, its variance and the
    physical coefficients', and gives what ``mean_var_one`` and ``predictive_variance`` give
    one ``δ`` at a time; a bank's ``online_step`` through the stack is the one that reads them
    one by one."""
    from gpg.flight.bank import adapt_bank
    from gpg.gp.inducing import StackedInducing

    folded = fc.offline_model(every.model).variance_views()
    one_pass = folded.stacked()
    (stack,) = one_pass.delta
    assert isinstance(stack, StackedInducing) and folded.explicit is not None
    np.testing.assert_array_equal(stack.noise, [float(d.noise) for d in folded.delta])
    X = jnp.asarray(fc.training_rows(every, flights)[0][:4])

    @jax.jit
    @jax.vmap
    def read(x):
        mean, band = one_pass.offline_moments(x)
        ref_mean, var = folded.mean_var_one(x)
        k, means, latents = stack.evaluate(x)
        return (mean, band, ref_mean, folded.predictive_variance(var)[:6], k, means, latents,
                stack.rows(x), stack.means(x), stack.latents(x))  # fmt: skip

    got = [np.asarray(a) for a in read(X)]
    mean, band, ref_mean, ref_band, k = got[:5]
    e, eps = folded.explicit, np.finfo(float).eps
    C, G = np.asarray(e.cov_chol), np.asarray(e.G)
    for i, x in enumerate(np.asarray(X)):
        for j, d in enumerate(folded.delta):
            dk, mean_tol, var_tol = _row_tolerances(d, x, k[i, j])
            # evaluate against rows, means and latents read apart: the same formulas, which
            # the compiler may fuse and sum in other orders (within the rows' rounding bounds)
            assert np.all(np.abs(k[i, j] - got[7][i, j]) <= dk), (i, j)
            np.testing.assert_allclose(got[5][i, j], got[8][i, j], rtol=0, atol=mean_tol)
            np.testing.assert_allclose(got[6][i, j], got[9][i, j], rtol=0, atol=var_tol)
            sc = float(d.output_scale[0])
            np.testing.assert_allclose(mean[i, j], ref_mean[i, j], rtol=0, atol=sc * mean_tol
                                       + 8 * eps * abs(ref_mean[i, j]))  # fmt: skip
            # the coefficients' share ‖Cᵀ(h − Gᵀk)‖²: Δk moves it by at most
            # ‖C‖ ‖G‖ ‖Δk‖ (2 ‖u‖ + ‖C‖ ‖G‖ ‖Δk‖), u = Cᵀ(h − Gᵀk)
            cg = np.linalg.norm(C[j], 2) * np.linalg.norm(G[j], 2) * np.linalg.norm(dk)
            u = np.sqrt(max(ref_band[i, j], 0.0))
            tol = sc * var_tol + cg * (2 * u + cg) + 16 * eps * ref_band[i, j]
            np.testing.assert_allclose(band[i, j], ref_band[i, j], rtol=0, atol=tol)
    with pytest.raises(ValueError, match="carry no variance"):
        fc.offline_model(every.model).mean_view().stacked().offline_moments(X[0])
    # the bank's step through the stack and one δ at a time (update's reading)
    bank = adapt_bank(every, [(1.0, 0.1), (30.0, None)], ahead=2, inducing=8, t0=0.0)
    cols = flights.columns()
    a = b = fc.online_state(bank)
    stacked_step, one_by_one = fc.online_step(bank), fc.online_step(bank, stack=False)
    for i in range(5):
        args = [c[i] for c in cols]
        a, b = stacked_step(a, *args), one_by_one(b, *args)
    # the bands above differ by rounding; five steps of small filters amplify it far less than
    # 1e3, and the log weights are sums of a few log densities of order one
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-13 * max(float(np.abs(y).max()), 1))


def _stacked_as_one_by_one(few, corrected, X, flights):
    """online_step's view reads the six inducing-point δ through one StackedInducing: each
    δ's mean and latent variance as the GP's own (and the δ variance the wind state's step
    reads), and the tracked step as the one reading them one by one."""
    from gpg.flight.tracking import default_drift, track
    from gpg.gp.inducing import StackedInducing

    view = few.model.mean_view(True)
    stacked = view.stacked()
    (stack,) = stacked.delta
    assert isinstance(stack, StackedInducing)
    assert corrected.model.stacked() is corrected.model  # exact δ: nothing stacked

    @eqx.filter_jit
    @jax.vmap
    def read(x):  # one program: both forms at each query
        one = [d.mean_var_one(x) for d in view.delta]
        return {"mean": stack.means(x), "var": stack.latents(x),
                "mean_1": jnp.stack([m[0] for m, _ in one]),
                "var_1": jnp.stack([v for _, v in one]),
                "latent": stacked._delta_latent_at(x), "latent_1": view._delta_latent_at(x),
                "rows": jnp.stack([d._row(x) for d in view.delta])}  # fmt: skip

    xs = X[:4]
    got = {k: np.asarray(v) for k, v in read(xs).items()}
    for i, x in enumerate(np.asarray(xs)):
        for j, d in enumerate(view.delta):
            _, mean_tol, var_tol = _row_tolerances(d, x, got["rows"][i, j])
            close = lambda u, v, tol: np.testing.assert_allclose(u, v, rtol=0, atol=tol)  # noqa: E731
            close(got["mean"][i, j], got["mean_1"][i, j], mean_tol)
            close(got["var"][i, j], got["var_1"][i, j], var_tol)
            # what the wind state's step reads: δ's variance, scaled (the offline mean: below)
            sc = float(d.output_scale[0])
            close(got["latent"][i, j], got["latent_1"][i, j], sc * var_tol)
    # the tracked step reads the offline mean through the stack; one by one it is update's
    # (tests/flight/test_tracking.py)
    sur = track(few, default_drift(few), t0=0.0)
    cols = flights.columns()
    stacked_step, one_by_one = fc.online_step(sur), fc.online_step(sur, stack=False)
    a = b = fc.online_state(sur)
    for i in range(6):
        args = [c[i] for c in cols]
        a, b = stacked_step(a, *args), one_by_one(b, *args)
    # rounding in the means (above) moves the steps apart by as little; six Kalman steps of a
    # well-conditioned P-state filter amplify it by far less than 1e3
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-13 * float(np.abs(y).max()))


def test_hyperparameters_refined_on_every_label(synthetic_surrogate, flights):
    """``hyperparameters="all"``: each discrepancy's subset fit refined on every label by the
    collapsed bound through the model's own inducing inputs; the bound on every label is then
    at least the subset's (for every output: the refinement starts there and keeps the
    better), the model records it, and an unknown choice is refused by name."""
    from gpg.gp.inducing import collapsed_bound

    opts = {"exact_labels": N_LABELS // 2, "inducing": 12, "subset_size": 20, "max_steps": 20}
    sub = fc.correct(synthetic_surrogate, flights, **opts)
    every = fc.correct(synthetic_surrogate, flights, hyperparameters="all", **opts)
    assert every.config["flight_correction"]["hyperparameters"] == "all"
    m = sub.model
    X, Y, V = fc.training_rows(sub, flights)
    mu = np.asarray(m.prior.predict_mean(X))[:, :6]
    ms = np.asarray(jax.vmap(m.basis)(jnp.asarray(X)))
    np.testing.assert_array_equal(every.model.scale, m.scale)  # ρ, κ do not see δ
    R = Y - np.asarray(m.scale)[:6] * mu - np.asarray(m.kappa) * ms
    gain = []
    for j in range(6):
        Z = np.asarray(m.delta[j].X)
        np.testing.assert_array_equal(every.model.delta[j].X, Z)  # the same inducing inputs
        b_sub, b_all = (collapsed_bound(X, R[:, j], Z, hyper=mod.delta[j].hyper, row_noise=V[:, j])
                        for mod in (m, every.model))  # fmt: skip
        gain.append(b_all - b_sub)
    # never worse (the refinement keeps the better of its start and its end, to rounding),
    # and better somewhere: the subset of 20 labels did not fix the hyperparameters of 60
    assert min(gain) >= -1e-6 * N_LABELS and max(gain) > 0.1
    with pytest.raises(ValueError, match="hyperparameters must be"):
        fc.correct(synthetic_surrogate, flights, hyperparameters="every")
    with pytest.raises(ValueError, match="basis_prior must be"):
        fc.correct(synthetic_surrogate, flights, basis_prior=0.0)


def test_online_update_in_c_equals_jax(corrected, flights, tmp_path):
    """The adapted model's C (``gpg.export.to_c``): its state after a 10-minute stream at
    10 Hz (the labels replayed, time moving on) equals ``lax.scan`` of :func:`fc.update` to
    1e-9 (double: both run the same float64 Kalman steps, whose rounding the forgetting keeps
    from growing), and its ``online_predict`` then equals ``predict`` of the updated model;
    the example loop ``examples/c_adapt/adapt.c`` reads the labels from CSV and prints, for
    each, the prediction made before the update; a label with NaN is refused, the state kept."""
    import ctypes
    import subprocess
    from pathlib import Path

    from gpg.export import to_c

    m_ind = 48
    # a forgetting time per weight (per output, as fit_forgetting(per_output=True) gives, is
    # the case of equal rows): the C must read each weight's own
    adapted = fc.adapt(corrected, inducing=m_ind, tau=5.0)
    per = np.geomspace(2.0, 20.0, 6 * m_ind).reshape(6, m_ind)
    adapted = fc.with_online(
        adapted, dataclasses.replace(adapted.model.online, tau=jnp.asarray(per))
    )
    n = 6000
    idx = np.arange(n) % len(flights)
    cols = [np.asarray(c, float)[idx] for c in flights.columns()]
    cols[0] = np.arange(n) * 0.1
    final, _ = jax.jit(lambda s, xs: jax.lax.scan(lambda c, r: (fc.update(c, *r), None), s, xs))(
        adapted, tuple(jnp.asarray(c) for c in cols)
    )
    to_c(adapted, tmp_path, name="model")
    so = tmp_path / "model.so"
    res = subprocess.run(
        [
            "cc",
            "-O2",
            "-std=c99",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-shared",
            "-fPIC",
            "-o",
            str(so),
            str(tmp_path / "model.c"),
            "-lm",
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    lib = ctypes.CDLL(str(so))

    class State(ctypes.Structure):
        _fields_ = [
            ("mean", ctypes.c_double * (6 * m_ind)),
            ("cov", ctypes.c_double * (6 * m_ind * m_ind)),
            ("t", ctypes.c_double),
        ]

    D = ctypes.POINTER(ctypes.c_double)

    def _label_args(r):  # one CSV row (t, rpm, euler, v_air, force, torque, variances)
        return [
            np.ascontiguousarray(r[i:j]).ctypes.data_as(D)
            for i, j in ((1, 5), (5, 8), (8, 11), (11, 14), (14, 17), (17, 20), (20, 23))
        ]

    st = State()
    lib.model_online_init(ctypes.byref(st))
    rows = np.column_stack([c.reshape(n, -1) for c in cols])
    for r in rows:
        a = _label_args(r)
        assert lib.model_online_update(ctypes.byref(st), ctypes.c_double(r[0]), *a) == 1
    o = final.model.online
    np.testing.assert_allclose(
        np.ctypeslib.as_array(st.mean).reshape(6, m_ind),
        o.mean,
        rtol=0,
        atol=1e-9 * max(1.0, float(np.abs(o.mean).max())),
    )
    np.testing.assert_allclose(
        np.ctypeslib.as_array(st.cov).reshape(6, m_ind, m_ind), o.cov, rtol=0, atol=1e-9
    )
    assert st.t == float(o.t)
    bad = rows[0].copy()
    bad[12] = np.nan
    a = _label_args(bad)
    before = np.ctypeslib.as_array(st.mean).copy()
    assert lib.model_online_update(ctypes.byref(st), ctypes.c_double(1e4), *a) == 0
    assert np.array_equal(np.ctypeslib.as_array(st.mean), before) and st.t == float(o.t)
    rpm, euler, v = _export_states(flights, 8)
    ref = final.predict_batch(rpm, euler, v)
    assert_c_predicts(lib.model_online_predict, st, ref, rpm, euler, v, 1e-7)
    # the example loop on the first minute, each prediction made before its update
    csv = tmp_path / "labels.csv"
    np.savetxt(csv, rows[:600], delimiter=",", header="t,rpm,euler,v_air,force,torque,vars")
    example = Path(__file__).parents[2] / "examples" / "c_adapt" / "adapt.c"
    exe = tmp_path / "adapt"
    res = subprocess.run(
        [
            "cc",
            "-O2",
            "-std=c99",
            "-Wall",
            "-Werror",
            "-I",
            str(tmp_path),
            "-o",
            str(exe),
            str(example),
            str(tmp_path / "model.c"),
            "-lm",
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    out = subprocess.run([str(exe), str(csv)], check=True, capture_output=True, text=True).stdout
    got = np.loadtxt(out.splitlines()[1:], delimiter=",")
    assert got.shape == (600, 15) and np.all(got[:, -1] == 1)
    for k in (0, 1, 599):  # the example's prediction k: the state after k updates
        lib.model_online_init(ctypes.byref(st))
        for r in rows[:k]:
            a = _label_args(r)
            lib.model_online_update(ctypes.byref(st), ctypes.c_double(r[0]), *a)
        f, t, lv, var = np.zeros(3), np.zeros(3), np.zeros(8), np.zeros(12)
        lib.model_online_predict(
            ctypes.byref(st),
            *[
                np.ascontiguousarray(x).ctypes.data_as(D)
                for x in (rows[k, 1:5], rows[k, 5:8], rows[k, 8:11], f, t, lv, var)
            ],
        )
        np.testing.assert_allclose(got[k, 1:7], np.concatenate([f, t]), rtol=1e-15, atol=1e-15)


def test_half_turn_corrected_reads_airflow_from_behind_at_its_image(
    synthetic_surrogate, corrected, flights, tmp_path
):
    """A corrected model whose surrogate reads airflow from behind at the half-turn image
    (:func:`gpg.quadrotor.frames.half_turn`): a label flown from behind gives the training
    rows of its image (to the rounding of the angles and of ``M`` at the two), the model
    predicts there as at the image, and its C, CasADi and ONNX exports predict as it does at
    such states (the C's online update reads its labels through the same ``gp_input``)."""
    from gpg.quadrotor.frames import half_turn

    turn = jax.vmap(half_turn)
    rpm, euler = (np.asarray(a) for a in turn(flights.rpm, flights.euler))
    back = dataclasses.replace(flights, rpm=rpm, euler=euler)  # the same flight, from behind
    half = dataclasses.replace(synthetic_surrogate, half_turn=True)
    X, Y, V = fc.training_rows(synthetic_surrogate, flights)
    Xb, Yb, Vb = fc.training_rows(half, back)
    np.testing.assert_allclose(Xb, X, rtol=0, atol=1e-12)  # the angles' rounding (|x| <~ 1)
    np.testing.assert_allclose(Yb, Y, rtol=0, atol=1e-12 * np.abs(Y).max())
    np.testing.assert_allclose(Vb, V, rtol=1e-12)
    model = dataclasses.replace(corrected, half_turn=True)
    p = model.predict_batch(rpm, euler, flights.v_air)
    q = corrected.predict_batch(flights.rpm, flights.euler, flights.v_air)
    for key in ("force", "torque", "variance"):
        want = np.asarray(getattr(q, key))
        np.testing.assert_allclose(getattr(p, key), want, rtol=0, atol=1e-12 * np.abs(want).max())
    np.testing.assert_array_equal(p.in_domain, q.in_domain)
    _exports_equal_predict(model, back, tmp_path, "double", n=12, n_casadi=2)
