"""Surrogate: frames, training labels, equivariance under world yaw, batching, scan, bad input."""

import dataclasses
import functools
import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor.frames import rot_z
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset, variance_rtol

EXACT = {"hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-10, "grad_noise_scale": 1e-6}}
BINNED = {
    "hyper": {"fit": False, "lengthscale": 0.8},
    "partition": {"bins": 3, "points_per_bin": None},
    "near": {"budget": 0.5, "points": None},
}


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(50, seed=3)[0]


@pytest.fixture(scope="module")
def exact(data):
    return Surrogate.fit(data, "gpg", EXACT)


@pytest.fixture(scope="module")
def binned(data):
    return Surrogate.fit(data, "gpgs_hybrid", BINNED)


def state(x):
    """A dataset case as a world-frame query: airflow along +x."""
    return x[:4], x[4:7], np.array([x[7], 0.0, 0.0])


def test_training_point_returns_its_label(exact, data):
    for i in (0, 7, 21):
        p = exact.predict(*state(data.x[i]))
        assert bool(p.in_domain)
        np.testing.assert_allclose(p.force, data.y_aero[i, :3], rtol=1e-4, atol=1e-4 * 20)
        np.testing.assert_allclose(p.torque, data.y_aero[i, 3:], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(p.levels, data.y_noise[i], rtol=1e-5)
        assert p.variance.shape == (9,) and np.all(  # ~0 here, the signal variance far away
            np.asarray(p.variance) < 1e-6 * exact.predict(*state(3 * data.x.max(0))).variance
        )


@pytest.mark.parametrize("which", ["exact", "binned"])
def test_world_yaw_rotates_force_and_torque(which, exact, binned, data, rng):
    sur = exact if which == "exact" else binned
    for x in data.x[:4]:
        rpm, euler, v = state(x)
        v = v + np.array([0.0, 1.5, -2.0])  # also off-axis, climbing airflow
        a = rng.uniform(-np.pi, np.pi)
        R = np.asarray(rot_z(a))
        p = sur.predict(rpm, euler, v)
        q = sur.predict(rpm, euler + np.array([a, 0, 0]), R @ v)
        np.testing.assert_allclose(q.force, R @ np.asarray(p.force), atol=1e-9)
        np.testing.assert_allclose(q.torque, R @ np.asarray(p.torque), atol=1e-9)
        np.testing.assert_allclose(q.levels, p.levels, atol=1e-9)
        assert bool(q.in_domain) == bool(p.in_domain)


def test_mean_fast_path_and_batches(binned, data):
    rpm, euler, v = (
        data.x[:20, :4],
        data.x[:20, 4:7],
        np.column_stack([data.x[:20, 7], np.zeros((20, 2))]),
    )
    full = binned.predict_batch(rpm, euler, v, chunk=8)
    vm = jax.vmap(binned.predict)(jnp.asarray(rpm), jnp.asarray(euler), jnp.asarray(v))
    fast = binned.predict_batch(rpm, euler, v, mean_only=True, chunk=6)
    np.testing.assert_allclose(full.force, vm.force, rtol=1e-12, atol=1e-12)
    # Both variances sum the float32 factor's products, in different orders (the batch by bin
    # tiles, gpg.gp.binned.by_bin): each is within variance_rtol of the exact quadratic form.
    vtol = 2 * variance_rtol(binned, rpm, euler, v)[:, None] * np.asarray(vm.variance)
    np.testing.assert_array_less(np.abs(np.asarray(full.variance) - vm.variance), vtol)
    np.testing.assert_allclose(fast.force, full.force, rtol=1e-12, atol=1e-12)
    assert fast.variance is None and full.force.shape == (20, 3)
    one = binned.predict_mean(*state(data.x[3]))
    np.testing.assert_allclose(one.force, full.force[3], rtol=1e-12)


def test_usable_inside_scan(binned, data):
    rpm, euler = jnp.asarray(data.x[0, :4]), jnp.asarray(data.x[0, 4:7])

    def step(v, _):
        p = binned.predict_mean(rpm, euler, v)
        return v + 0.01 * p.force, p.force[2]

    _, fz = jax.lax.scan(step, jnp.array([5.0, 0.0, 0.0]), None, length=5)
    assert fz.shape == (5,) and np.all(np.isfinite(fz))


def test_traces_once(exact, data, caplog):
    exact.predict(*state(data.x[1]))
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        for i in (2, 3, 4):
            exact.predict(*state(data.x[i]))
    assert not [r for r in caplog.records if "Compiling jit(_predict)" in r.getMessage()]


def test_out_of_domain_and_bad_values(binned, data):
    rpm, euler, v = state(data.x[5])
    assert bool(binned.predict(rpm, euler, v).in_domain)
    assert not bool(
        binned.predict(rpm * np.array([1, -1, 1, 1]), euler, v).in_domain
    )  # negative rpm
    assert not bool(binned.predict(rpm, euler, -v).in_domain)  # flying backwards: yaw_H ≈ 180°
    assert not bool(binned.predict(rpm * 10, euler, v).in_domain)  # beyond the rpm range
    hover = binned.predict(rpm, euler, np.zeros(3))  # zero airspeed: finite
    assert np.all(np.isfinite(hover.force))


def test_nan_policy(binned, data):
    """From Python every entry point raises, naming the input; under the caller's own jit the
    prediction is flagged out of domain instead (nothing can be raised there)."""
    rpm, euler, v = state(data.x[5])
    nan_euler = euler * np.array([1.0, np.nan, 1.0])
    for call in (
        binned.predict,
        binned.predict_mean,
        binned.realtime(),
        binned.realtime(with_var=False),
    ):
        with pytest.raises(ValueError, match=r"euler holds NaN or inf"):
            call(rpm, nan_euler, v)
    with pytest.raises(ValueError, match=r"v_air holds NaN or inf in row\(s\) \[1\]"):
        binned.predict_batch(
            np.stack([rpm, rpm]), np.stack([euler, euler]), np.stack([v, v + np.inf])
        )
    under_jit = jax.jit(lambda r, e, a: binned.predict(r, e, a))
    assert not bool(under_jit(rpm, nan_euler, v).in_domain)
    assert bool(under_jit(rpm, euler, v).in_domain)


def test_hover_in_domain_whatever_the_yaw(binned, data):
    """Hovering facing any direction is inside the training box (yaw ±90°): at rest H follows
    the body heading. Pure wind axes (hover_speed=0) take H = W and flag a yaw of 150°."""
    rpm, euler, _ = state(data.x[5])
    euler = np.array([np.radians(150.0), euler[1], euler[2]])
    drift = np.array([0.01, -0.02, 0.005])
    # the synthetic data start at 0.27 m/s; a generated dataset's box starts at 0
    sur = eqx.tree_at(lambda s: s.box_lo, binned, binned.box_lo.at[7].set(0.0))
    assert bool(sur.predict(rpm, euler, drift).in_domain)
    wind_axes = dataclasses.replace(sur, hover_speed=0.0)
    assert not bool(wind_axes.predict(rpm, euler, drift).in_domain)
    with pytest.raises(ValueError, match="hover_speed"):
        Surrogate.fit(data, "gps_1x", BINNED, hover_speed=-1.0)


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.zeros(3), np.zeros(3), np.zeros(3)), r"rpm must have shape \(4,\)"),
        (
            (np.zeros(4), np.zeros((2, 3)), np.zeros(3)),
            r"euler must have shape \(3,\) for one state",
        ),
        ((np.zeros(4), np.zeros(3), np.zeros(2)), r"v_air must have shape \(3,\)"),
    ],
)
def test_wrong_shapes(binned, args, match):
    with pytest.raises(ValueError, match=match):
        binned.predict(*args)


def test_batch_shape_errors(binned):
    with pytest.raises(ValueError, match=r"rpm must have shape \(N, 4\)"):
        binned.predict_batch(np.zeros(4), np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="batch sizes differ"):
        binned.predict_batch(np.zeros((2, 4)), np.zeros((3, 3)), np.zeros((2, 3)))


@functools.cache
def _batch_surrogate(noise: bool):
    full, _ = synthetic_dataset(30, seed=4, raw=False)
    ds = full if noise else full.without("noise", "gradients")
    cfg = {"hyper": {"fit": False}, "partition": {"bins": 2}}
    return ds, Surrogate.fit(ds, "gps_1x", cfg, residual=False)


@pytest.mark.parametrize("noise", [True, False])
@pytest.mark.parametrize("mean_only", [True, False])
@pytest.mark.parametrize("chunk", [7, 1024])
def test_predict_batch_for_every_output_set(noise, mean_only, chunk):
    """The issue's repro (30 rows, no noise columns, 2 bins, no residual) and every other
    combination: batches in several chunks and in one, equal to single predictions."""
    ds, sur = _batch_surrogate(noise)
    rpm, euler, v = ds.x[:, :4], ds.x[:, 4:7], np.column_stack([ds.x[:, 7], 0 * ds.x[:, :2]])
    out = sur.predict_batch(rpm, euler, v, mean_only=mean_only, chunk=chunk)
    assert out.force.shape == (30, 3) and out.levels.shape == (30, 3 if noise else 0)
    assert (out.variance is None) == mean_only
    one = (sur.predict_mean if mean_only else sur.predict)(rpm[11], euler[11], v[11])
    np.testing.assert_allclose(out.force[11], one.force, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.levels[11], one.levels, rtol=1e-12, atol=1e-12)
    assert np.all(np.asarray(out.in_domain))


def test_foreign_data_needs_a_vehicle():
    """No silent default vehicle: a dataset that names none needs vehicle=."""
    ds, _ = synthetic_dataset(30, seed=4, raw=False)
    meta = {k: v for k, v in ds.meta.items() if k != "vehicle"}
    bare = dataclasses.replace(ds, meta=meta)
    with pytest.raises(ValueError, match="the dataset names no vehicle: pass vehicle="):
        Surrogate.fit(bare, "gps_1x", {"hyper": {"fit": False}, "partition": {"bins": 2}})
    sur = Surrogate.fit(
        bare, "gps_1x", {"hyper": {"fit": False}, "partition": {"bins": 2}}, vehicle="sui_endurance"
    )
    assert sur.simple is not None
    # bounds= sets the in-domain box.
    sur = Surrogate.fit(
        ds,
        "gps_1x",
        {"hyper": {"fit": False}, "partition": {"bins": 2}},
        bounds={"airspeed": [0.0, 5.0]},
    )
    assert float(sur.box_hi[7]) == 5.0


def test_without_noise_or_residual(data):
    sur = Surrogate.fit(data.without("noise"), "gpg", EXACT, residual=False)
    p = sur.predict(*state(data.x[0]))
    assert p.levels.shape == (0,) and p.variance.shape == (6,) and sur.simple is None
    np.testing.assert_allclose(p.force, data.y_aero[0, :3], rtol=1e-4, atol=2e-3)


@pytest.mark.slow
def test_noise_model_is_added_back(data):
    """With M_noise the GP learns L − M_noise; the surrogate adds M_noise back (a training
    point still returns its label; checkpoints store it as any other module field)."""
    from gpg.quadrotor.simple_noise import SimpleNoise

    sur = Surrogate.fit(data, "gpg", EXACT, noise_model=True)
    assert isinstance(sur.noise_model, SimpleNoise)
    for i in (0, 7):
        np.testing.assert_allclose(
            sur.predict(*state(data.x[i])).levels, data.y_noise[i], rtol=1e-5
        )
    with pytest.raises(ValueError, match="noise_model=True needs residual=True"):
        Surrogate.fit(data, "gps_1x", BINNED, residual=False, noise_model=True)


def test_body_frame_entry_point(binned, data):
    from gpg.quadrotor.frames import R_WB

    rpm, euler, v = state(data.x[5])
    euler = euler + np.array([0.7, 0.05, -0.1])  # not the dataset frame: a rotated body
    R = np.asarray(R_WB(euler))
    w = binned.predict(rpm, euler, v)
    b = binned.predict_body(rpm, R, R.T @ v)
    np.testing.assert_allclose(b.force, R.T @ np.asarray(w.force), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(b.torque, R.T @ np.asarray(w.torque), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(b.levels, w.levels, rtol=1e-12)
    # The variances are the same ellipsoid's diagonal in two frames: equal traces.
    np.testing.assert_allclose(b.variance[:3].sum(), w.variance[:3].sum(), rtol=1e-10)
    np.testing.assert_allclose(b.variance[6:], w.variance[6:], rtol=1e-12)
    assert bool(b.in_domain) == bool(w.in_domain)
    with pytest.raises(ValueError, match="rotation matrix"):
        binned.predict_body(rpm, 2 * R, v)
    with pytest.raises(ValueError, match="3x3"):
        binned.predict_body(rpm, R[:2], v)


@pytest.mark.parametrize("which", ["exact", "binned"])
def test_jacobians_of_predict(which, exact, binned, data):
    """jax.jacrev/jacfwd of the world-frame prediction (mean and variance) match central
    differences and each other. The hybrid stores its variance factors in float32, which
    makes its variance too rough for a finite difference: its float64 copy is differentiated."""
    sur = exact if which == "exact" else binned.astype(jnp.float64)

    def f(z):
        p = sur.predict(z[:4], z[4:7], z[7:])
        return jnp.concatenate([p.force, p.torque, p.levels, p.variance])

    rpm, euler, v = state(data.x[9])
    z = jnp.asarray(np.concatenate([rpm, euler + np.array([0.2, 0.0, 0.0]), v + 0.7]))
    Jr = jax.jit(jax.jacrev(f))(z)
    Jf = jax.jit(jax.jacfwd(f))(z)
    h = np.maximum(np.abs(np.asarray(z)), 1.0) * 6e-6
    Jd = np.stack(
        [(f(z + hh * e) - f(z - hh * e)) / (2 * hh) for e, hh in zip(np.eye(10), h, strict=True)], 1
    )
    np.testing.assert_allclose(Jf, Jr, rtol=1e-9, atol=1e-12 * np.abs(Jd).max())
    for sl in (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 18)):
        assert np.max(np.abs(Jr[sl] - Jd[sl])) < 1e-6 * np.max(np.abs(Jd[sl]))


def test_non_finite_prediction_is_never_in_domain(binned, data):
    """Under the caller's jit nothing can be raised: a prediction that is not finite (a
    damaged model here) comes back flagged, never as a silent NaN in domain."""
    import equinox as eqx

    bad = eqx.tree_at(
        lambda s: s.model.mean.coef, binned, binned.model.mean.coef.at[:, 0].set(jnp.nan)
    )
    rpm, euler, v = state(data.x[2])
    p = jax.jit(lambda s, r, e, w: s.predict(r, e, w))(bad, rpm, euler, v)
    assert not np.all(np.isfinite(np.asarray(p.force))) and not bool(p.in_domain)
    assert bool(binned.predict(rpm, euler, v).in_domain)


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.full(4, 3600.0) + 0j, np.zeros(3), np.ones(3)), "rpm must be real numbers"),
        ((np.full(4, 3600.0), np.zeros(3, bool), np.ones(3)), "euler must be real numbers"),
        ((np.full(4, 3600.0), np.zeros(3), ["a", "b", "c"]), "v_air must be real numbers"),
    ],
)
def test_complex_bool_and_text_queries_are_refused(binned, args, match):
    with pytest.raises(ValueError, match=match):
        binned.predict(*args)


def test_prediction_is_continuous_and_differentiable_at_vertical_airflow(synthetic_surrogate):
    """A descent with the nose 40° down (pitch 50° in the airflow frame, inside the data's
    ±60°): the prediction moves by a few mN for 1 mm/s of sideways air (with pure wind axes the
    frame turned by up to a quarter turn), and autodiff matches central differences at the
    vertical airflow itself. (A level vehicle in axial flow sits at pitch_H ≈ ±90°, the
    Euler angles' own singularity, out of the data's box: docs/design.md.)"""
    sur = synthetic_surrogate
    rpm, euler = np.full(4, 3600.0), np.array([0.3, -0.7, 0.1])

    def f(v):
        p = sur.predict(rpm, euler, v)
        return jnp.concatenate([p.force, p.torque, p.variance])

    v0 = jnp.array([0.0, 0.0, 3.0])
    assert bool(sur.predict(rpm, euler, v0).in_domain)
    ref = np.asarray(f(v0))
    for t in np.linspace(0, 2 * np.pi, 7):
        moved = np.asarray(f(v0 + 1e-3 * jnp.array([np.cos(t), np.sin(t), 0.0])))
        assert np.max(np.abs(moved[:6] - ref[:6])) < 5e-3 * max(1.0, np.abs(ref[:6]).max())
    J = jax.jit(jax.jacrev(f))(v0)
    h = 1e-5
    fd = np.stack([(f(v0 + h * e) - f(v0 - h * e)) / (2 * h) for e in jnp.eye(3)], 1)
    np.testing.assert_allclose(J, fd, atol=1e-6 * np.abs(fd).max())


def test_old_level_and_noise_model_names_warn(synthetic_surrogate):
    """``Prediction.noise`` (the levels) and ``Surrogate.noise`` (M_noise) before gpg 0.2."""
    sur = synthetic_surrogate
    p = sur.predict(np.full(4, 3000.0), np.zeros(3), np.array([3.0, 0.0, 0.0]))
    with pytest.warns(DeprecationWarning, match="Prediction.noise is deprecated"):
        np.testing.assert_array_equal(p.noise, p.levels)
    with pytest.warns(DeprecationWarning, match="Surrogate.noise is deprecated"):
        assert sur.noise is sur.noise_model
    with pytest.warns(DeprecationWarning, match="Surrogate.n_noise is deprecated"):
        assert sur.n_noise == sur.n_levels


@pytest.mark.parametrize("hover_speed", [0.0, 0.5])
def test_no_in_domain_query_jumps_with_a_millimetre_per_second_of_air(hover_speed, monkeypatch):
    """Near vertical airflow (climbs, descents, hover in wind) the airflow frame and the data's
    coordinates of a query swing with the sideways air: at its singular sets a finite step for
    any small change. In domain, 1 mm/s of air in any direction moves the GP's inputs (angles
    in ``H``) and the frame by at most ``MAX_FRAME_RATE`` times it (central differences
    here, independent of the autodiff that sets the flag); the same sampler finds the
    states inside the data's box that only the frame-rate test flags, which break that bound
    (by degrees with pure wind axes): the box alone would let them through."""
    from gpg import surrogate
    from gpg.quadrotor.frames import to_airflow_frame
    from gpg.surrogate import MAX_FRAME_RATE, predict_state

    data, _ = synthetic_dataset(40, seed=3, raw=False)
    sur = Surrogate.fit(data, "gpg", EXACT, hover_speed=hover_speed)
    rng = np.random.default_rng(7)
    n = 4000
    rpm = rng.uniform(1000, 6000, (n, 4))
    euler = np.column_stack(
        [rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.4, 1.4, n), rng.uniform(-1.5, 1.5, n)]
    )
    side = 10 ** rng.uniform(-5, 0.3, n) * np.exp(1j * rng.uniform(0, 2 * np.pi, n))
    v = np.column_stack([side.real, side.imag, rng.choice([-1, 1], n) * rng.uniform(0, 8, n)])

    @jax.jit
    @jax.vmap
    def coords(e, v):
        euler_h, _, rwh = to_airflow_frame(e, v, hover_speed)
        return jnp.concatenate([euler_h, rwh.ravel() / np.sqrt(2)])

    flag = jax.jit(jax.vmap(lambda r, e, v: predict_state(sur, r, e, v, False).in_domain))
    ok = np.asarray(flag(rpm, euler, v))
    monkeypatch.setattr(surrogate, "MAX_FRAME_RATE", np.inf)
    box_only = jax.jit(jax.vmap(lambda r, e, v: predict_state(sur, r, e, v, False).in_domain))
    in_box = np.asarray(box_only(rpm, euler, v))
    step = 1e-3
    moved = np.zeros(n)
    for t in np.linspace(0, 2 * np.pi, 6, endpoint=False):
        for up in (0.0, 1.0):
            d = step * np.array([np.cos(t) * (1 - up), np.sin(t) * (1 - up), up])
            # yaw wraps at ±180°: compare angles on the circle
            diff = np.asarray(coords(euler, v + d / 2)) - np.asarray(coords(euler, v - d / 2))
            diff[:, :3] = (diff[:, :3] + np.pi) % (2 * np.pi) - np.pi
            change = np.maximum(
                np.linalg.norm(diff[:, :3], axis=1), np.linalg.norm(diff[:, 3:], axis=1)
            )
            moved = np.maximum(moved, change)
    assert ok.sum() > 200 and (in_box & ~ok).sum() >= 5 and not (ok & ~in_box).any()
    assert moved[ok].max() <= 1.1 * MAX_FRAME_RATE * step, moved[ok].max()
    # without the frame-rate flag the bound fails inside the box: by degrees at the vertical
    # airflow of pure wind axes
    assert moved[in_box & ~ok].max() > 1.1 * MAX_FRAME_RATE * step
    assert hover_speed > 0 or moved[in_box & ~ok].max() > np.radians(10.0)


def test_fit_arguments_of_the_wrong_kind_are_named(data):
    """Each refused before any fit, with the argument named (they used to surface as
    ``unhashable type``, a dict-update ``ValueError`` and a NumPy broadcasting error)."""
    with pytest.raises(ValueError, match="bounds must be a mapping of"):
        Surrogate.fit(data, "gpg", EXACT, bounds=[[0, 7000]])
    with pytest.raises(ValueError, match=r"config \(the model options\) must be a mapping"):
        Surrogate.fit(data, "gpg", [("hyper", {"fit": False})])
    bad = {"hyper": {"fit": False, "lengthscale": [1.0, 2.0, 3.0]}}
    with pytest.raises(ValueError, match="hyper.lengthscale has 3 values; the model has 8 inputs"):
        Surrogate.fit(data, "gpg", bad)


def test_jit_of_a_bound_predict_says_what_to_call(synthetic_surrogate):
    """``jax.jit(sur.predict)`` cannot hash the surrogate's arrays (and baking them into the
    program would be worse): the error says what to call, and that call equals ``predict``."""
    sur = synthetic_surrogate
    state = (jnp.full(4, 4000.0), jnp.array([0.1, 0.05, -0.02]), jnp.array([3.0, 1.0, 0.0]))
    with pytest.raises(TypeError, match=r"jax.jit\(Surrogate.predict\)\(model, ...\).*filter_jit"):
        jax.jit(sur.predict)(*state)
    want = sur.predict(*state)
    # The same function compiled in another program: XLA may fuse and reassociate its float64
    # sums differently, a few thousand roundings at most on these well-conditioned 50 points.
    for got in (jax.jit(Surrogate.predict)(sur, *state), eqx.filter_jit(sur.predict)(*state)):
        np.testing.assert_allclose(got.force, want.force, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got.variance, want.variance, rtol=1e-12, atol=1e-15)


def test_half_turn_reads_airflow_from_behind_at_its_image(data, rng, tmp_path):
    """``half_turn``: a state whose airflow comes from behind is predicted as its image
    (rotors relabelled, body turned about z: the same physical state, whose airflow comes from
    the front and is read as it is), to the rounding of ``M`` at the two (1e-12 of each
    vector's scale); from the front exactly as the plain surrogate. Its derivatives are the
    image's through the chain rule (``∂image/∂euler = diag(1, −1, −1)``); a checkpoint keeps
    the setting; ``fit`` refuses data whose microphones are off the axis, the body frame and a
    vehicle that is not its own image, naming why."""
    from gpg import checkpoint
    from gpg.quadrotor.frames import half_turn, to_airflow_frame
    from gpg.quadrotor.vehicle import Vehicle, vehicle_config
    from tests.helpers import synthetic_body_dataset

    quiet = data.without("noise")
    sur = Surrogate.fit(quiet, "gpgs_hybrid", BINNED, half_turn=True)
    plain = dataclasses.replace(sur, half_turn=False)
    assert sur.half_turn and not plain.half_turn
    n = 40
    rpm = rng.uniform(2500, 4500, (n, 4))
    euler = rng.uniform([-np.pi, -0.4, -0.4], [np.pi, 0.4, 0.4], (n, 3))
    v = np.column_stack([rng.uniform(-8, 8, (n, 2)), rng.uniform(-1, 1, n)])
    v[:, 0] += 2.0 * np.sign(v[:, 0])  # above the hover blend
    image = tuple(np.asarray(a) for a in jax.vmap(half_turn)(rpm, euler))
    eh = np.asarray(jax.vmap(lambda e, w: to_airflow_frame(e, w, plain.hover_speed)[0])(euler, v))
    back = np.cos(eh[:, 0]) < 0
    assert 5 < back.sum() < n - 5
    both = sur.predict_batch(np.concatenate([rpm, image[0]]), np.concatenate([euler, image[1]]),
                             np.concatenate([v, v]))  # fmt: skip
    q = plain.predict_batch(rpm, euler, v)
    for key in ("force", "torque", "variance", "in_domain"):
        pair = np.asarray(getattr(both, key))
        got, img, front = pair[:n], pair[n:], np.asarray(getattr(q, key))
        np.testing.assert_array_equal(got[~back], front[~back])
        scale = np.maximum(np.abs(img[back]).max(), 1.0)
        np.testing.assert_allclose(got[back], img[back], rtol=0, atol=1e-12 * scale)
    inside = np.asarray(both.in_domain)[:n]
    assert inside[back].sum() > np.asarray(q.in_domain)[back].sum()  # the plain one: outside
    i = int(np.flatnonzero(back & inside)[0])
    # one program for the state and its image: the image, from the front, is read as it is
    J = jax.vmap(jax.jacrev(lambda r_, e, w: sur.predict(r_, e, w).force, argnums=(1, 2)))(
        np.stack([rpm[i], image[0][i]]), np.stack([euler[i], image[1][i]]), np.stack([v[i]] * 2)
    )
    Je, Jv = (np.asarray(a) for a in J)
    np.testing.assert_allclose(Jv[0], Jv[1], rtol=1e-9, atol=1e-12 * np.abs(Jv[1]).max())
    turn = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(Je[0], Je[1] @ turn, rtol=1e-9, atol=1e-12 * np.abs(Je[1]).max())
    checkpoint.save(tmp_path / "ht", sur)
    assert checkpoint.load(tmp_path / "ht").half_turn
    with pytest.raises(ValueError, match=r"microphone 0 .* noise: false"):
        Surrogate.fit(data, "gpgs_hybrid", BINNED, half_turn=True)
    with pytest.raises(ValueError, match="airflow-frame data"):
        Surrogate.fit(synthetic_body_dataset(20, seed=1)[0], "gpg", EXACT, half_turn=True)
    cfg = vehicle_config("sui_endurance")
    cfg["layout"]["spin"] = [1, -1, -1, 1]
    with pytest.raises(ValueError, match="r1 and r3 spin opposite ways"):
        Surrogate.fit(quiet, "gpg", EXACT, vehicle=Vehicle.from_config(cfg), half_turn=True)
