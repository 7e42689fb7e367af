"""Paper-style datasets in the body frame (gpg/data/convert.py): against the generator's own
body frame at the converted inputs, values and gradients (the angle gradients as derivatives
along directions of the air velocity) to rounding; against the chain rule of an analytic
body-frame function and its finite differences; and a surrogate trains on the result."""

import dataclasses

import numpy as np
import pytest

from gpg import Surrogate
from gpg.data.bounds import Bounds
from gpg.data.convert import to_body
from gpg.data.sampling import generate
from gpg.quadrotor.generator import jacobian_body
from tests.helpers import synthetic_body_dataset, synthetic_dataset


@pytest.mark.slow  # a generator compile; to_body keeps the fast test below
def test_converted_values_are_the_generators_body_frame(gen, y_body_of):
    """Values to 1e-10 of the load's scale at the converted inputs."""
    air = generate(gen, 3, bounds=Bounds(), seed=5, chunk=32, gradients="none", keep_raw=False,
                   meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}})  # fmt: skip
    body = to_body(air)
    assert body.frame == "body" and body.x.shape == (3, 7) and not body.has_noise
    for i in range(3):
        y = np.asarray(y_body_of(body.x[i]))
        np.testing.assert_allclose(body.y_aero[i], y[:6], atol=1e-10 * np.abs(y[:6]).max())
    assert body.meta["bounds"] == {"rpm": [0.0, 7000.0], "airspeed": [0.0, 20.0]}


@pytest.mark.slow  # the generator's exact Jacobian in both frames (long compiles)
def test_converted_gradients_are_the_generators_body_frame(gen):
    """Rotor-speed gradients (exact in both frames) to 1e-8 relative: ``∂y_B/∂r = Rᵀ ∂y/∂r``
    at fixed body-frame air; the angle gradients are the body-frame Jacobian along the two
    tangent directions; the airspeed's not run."""
    import jax

    air = generate(gen, 3, bounds=Bounds(), seed=5, chunk=32, gradients="exact", keep_raw=False,
                   meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}})  # fmt: skip
    body = to_body(air)
    jac = jax.jit(lambda x: jacobian_body(gen, x))
    for i in range(3):
        J = np.asarray(jac(body.x[i]))[:6, :7]
        np.testing.assert_allclose(
            body.jac_aero[i, :, :4], J[:, :4], rtol=1e-8, atol=1e-10 * np.abs(J).max()
        )
        # The angle gradients as derivatives along the directions of (u, v, w): J d.
        along = J @ body.grad_dirs[i, 4:6].T
        np.testing.assert_allclose(
            body.jac_aero[i, :, 4:6], along, rtol=1e-7, atol=1e-9 * np.abs(J).max()
        )
    assert np.isnan(body.jac_aero[:, :, 6]).all() and body.gradient_mask[:, :6].all()


def test_a_surrogate_trains_on_converted_data_and_body_data_are_refused():
    air, _ = synthetic_dataset(30, seed=2, raw=False)
    body = to_body(air)
    sur = Surrogate.fit(body, "gpg", {"hyper": {"fit": False, "lengthscale": 0.8}})
    assert sur.frame == "body"
    p = sur.predict(np.full(4, 3600.0), np.zeros(3), np.array([5.0, 0.0, 0.0]))
    assert np.all(np.isfinite(np.asarray(p.force)))
    # Without recorded bounds the domain is the ball of the data's largest airspeed (the box
    # of the cases' own velocities holds no hover: its ball about hover would be empty).
    assert bool(p.in_domain) and float(sur.ball_radius) == pytest.approx(body.airspeed.max())
    from gpg import design  # its candidates: each rotor in its own range, inside the ball

    assert not design._outside(sur, design.box_samples(sur, 300, 0), 0.0).any()
    with pytest.raises(ValueError, match="converts airflow-frame data"):
        to_body(synthetic_body_dataset(4)[0])


def _analytic_airflow(n=12, seed=3):
    """An airflow-frame dataset made from a known body-frame function ``f_B(r, v)``:
    ``y = blkdiag(R, R) f_B(r, Rᵀ V e_x)`` with its exact Jacobian in ``(r, θ)`` by JAX."""
    import jax
    import jax.numpy as jnp

    from gpg.data.dataset import Dataset
    from gpg.quadrotor.frames import R_WB

    rng = np.random.default_rng(seed)
    W = jnp.asarray(rng.normal(scale=0.3, size=(7, 6)))

    def f_body(x7):
        z = jnp.concatenate([x7[:4] / 4000.0, x7[4:] / 10.0])
        return jnp.sin(z @ W) + 0.2 * (z @ W) ** 2

    def f_air(r, th, V):
        R = R_WB(th)
        yb = f_body(jnp.concatenate([r, R.T @ jnp.array([V, 0.0, 0.0])]))
        return jnp.concatenate([R @ yb[:3], R @ yb[3:]])

    r = rng.uniform(3000, 4500, (n, 4))
    th = np.stack([rng.uniform(-np.pi / 2, np.pi / 2, n), rng.uniform(-1, 1, n),
                   rng.uniform(-1, 1, n)], 1)  # fmt: skip
    V = rng.uniform(0, 15, n)
    V[0] = 0.0  # hover: the angles move nothing
    y = np.asarray(jax.vmap(f_air)(r, th, V))
    jr, jt = jax.vmap(jax.jacfwd(f_air, argnums=(0, 1)))(r, th, V)
    jac = np.concatenate([np.asarray(jr), np.asarray(jt)], axis=2)
    jac[1, :, 5] = np.nan  # one case without its pitch perturbation
    x = np.concatenate([r, th, V[:, None]], 1)
    return Dataset(x=x, y_aero=y, jac_aero=jac), jax.jit(f_body)


def test_angle_gradients_become_directional_derivatives():
    """Each converted row equals the body-frame function's derivative along its direction:
    against ``jax.jvp`` (the chain rule, to rounding) and central finite differences."""
    import jax

    air, f_body = _analytic_airflow()
    body = to_body(air)
    dirs = body.grad_dirs
    for i in range(body.n):
        x = body.x[i]
        np.testing.assert_allclose(body.y_aero[i], f_body(x), rtol=1e-12, atol=1e-12)
        for g in range(7):
            if np.isnan(body.jac_aero[i, 0, g]):
                continue
            d = dirs[i, g]
            _, jvp = jax.jvp(f_body, (x,), (d,))
            # Exact derivatives in both frames: rounding of O(1) products only.
            np.testing.assert_allclose(body.jac_aero[i, :, g], jvp, rtol=1e-9, atol=1e-10)
            # A step of 1e-3 of the input's scale (4000 rpm, 10 m/s in f_B): central
            # differences truncate at ~(1e-3)² relative, round at ~1e-16 / 1e-3.
            h = 1e-3 * (4000.0 if g < 4 else 10.0)
            fd = (np.asarray(f_body(x + h * d)) - np.asarray(f_body(x - h * d))) / (2 * h)
            np.testing.assert_allclose(body.jac_aero[i, :, g], fd, rtol=1e-5, atol=1e-7)
    uvw = dirs[:, 4:, 4:]
    # Directions: orthonormal, the first two tangent to |v| = V, the third radial (not run).
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", uvw, uvw),
                               np.broadcast_to(np.eye(3), uvw.shape), atol=1e-12)  # fmt: skip
    moving = np.linalg.norm(body.x[:, 4:], axis=1) > 0
    radial = body.x[moving, 4:] / np.linalg.norm(body.x[moving, 4:], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.einsum("nj,nj->n", uvw[moving, 2], radial)), 1.0,
                               atol=1e-12)  # fmt: skip
    assert np.isnan(body.jac_aero[:, :, 6]).all()
    assert np.isnan(body.jac_aero[0, :, 4:]).all()  # hover: no velocity derivative at all
    # Without its pitch perturbation, case 1 still has two (yaw and roll span the plane).
    assert not np.isnan(body.jac_aero[1, :, 4:6]).any()
    plain = to_body(air, angle_gradients=False)
    assert plain.grad_dirs is None and np.isnan(plain.jac_aero[:, :, 4:]).all()
    np.testing.assert_array_equal(plain.jac_aero[:, :, :4], body.jac_aero[:, :, :4])


def test_converted_directions_train_gpg_and_the_hybrid():
    """gpg and gpgs_hybrid train on the directional rows: the hybrid's mean is GP-G's, its
    near-set variance bounds GP-G's; other kinds refuse the data, naming why."""
    air, _ = synthetic_dataset(40, seed=4, raw=False)
    body = to_body(air)
    assert body.grad_dirs is not None
    hyper = {"hyper": {"fit": False, "lengthscale": 0.9}}
    sur = Surrogate.fit(body, "gpg", hyper)
    assert sur.model.bases is not None
    sup = Surrogate.fit(body, "gpgs_hybrid", {**hyper, "partition": {"scheme": "kdtree"},
                                              "variance_dtype": "float64"})  # fmt: skip
    q = np.asarray(sur.normalizer.x(0.5 * (body.x[:5] + body.x[5:10])))  # between cases
    (ma, va), (mb, vb) = sur.model.predict(q), sup.model.predict(q)
    np.testing.assert_allclose(ma, mb, rtol=1e-8, atol=1e-8)
    assert np.all(np.asarray(vb) >= np.asarray(va) - 1e-10)
    with pytest.raises(ValueError, match="along other directions"):
        Surrogate.fit(body, "gpgs", {**hyper, "partition": {"scheme": "kdtree"}})


def test_converted_data_and_its_models_keep_their_directions(tmp_path):
    """The directions survive the dataset file, a subset, the checkpoint and the exports (the
    mean folded over coordinate rows, the hybrid's variance factors too: the layout's float64
    evaluation is the model's)."""
    from gpg import checkpoint, export
    from gpg.data.dataset import Dataset
    from gpg.export import layout

    air, _ = synthetic_dataset(24, seed=6, raw=False)
    body = to_body(air)
    body.save(tmp_path / "b")
    back = Dataset.load(tmp_path / "b")
    np.testing.assert_array_equal(back.grad_dirs, body.grad_dirs)
    np.testing.assert_array_equal(body.subset(np.array([3, 1])).grad_dirs, body.grad_dirs[[3, 1]])
    assert body.without("gradients").grad_dirs is None
    sur = Surrogate.fit(body, "gpgs_hybrid", {"hyper": {"fit": False, "lengthscale": 0.9},
                                              "partition": {"scheme": "kdtree"},
                                              "variance_dtype": "float64"})  # fmt: skip
    checkpoint.save(tmp_path / "ck", sur)
    again = checkpoint.load(tmp_path / "ck")
    q = np.asarray(sur.normalizer.x(body.x[:4] * 0.97))
    for u, v in zip(sur.model.predict(q), again.model.predict(q), strict=True):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    # The exports read coordinate kernel rows: the factor is folded with the directions.
    s = layout.spec(sur)
    mean, var = (np.asarray(a) for a in sur.model.predict_unclipped(q))
    for xn, m, v in zip(q, mean, var, strict=True):
        ref_mean, ref_var = layout.reference(s, xn)
        np.testing.assert_allclose(ref_mean, m, rtol=0, atol=1e-12)
        assert abs(ref_var - v) <= 1e-12 * float(s.sigma)  # float64 factors both
    with pytest.raises(ValueError, match="cases without some gradients"):
        export.to_c(Surrogate.fit(body, "gpg", {"hyper": {"fit": False, "lengthscale": 0.9}}),
                    tmp_path / "c")  # fmt: skip


def test_a_converted_surrogate_conditions_on_more_cases():
    """``Surrogate.condition`` on converted cases (directional rows) and on body-frame cases
    with coordinate gradients: the rebuild on all the cases with the same hyperparameters,
    normaliser and bins (:func:`gpg.design.rebuild`), for gpg and the hybrid."""
    from gpg import design
    from gpg.design import merge_datasets

    air, _ = synthetic_dataset(36, seed=7, raw=False)
    body = to_body(air)
    # The six most central cases are the new ones: inside the others' box and ball.
    centre = np.abs((body.x - body.x.mean(0)) / body.x.std(0)).max(1)
    new, old = np.argsort(centre)[:6], np.argsort(centre)[6:]
    extra, _ = synthetic_body_dataset(80, seed=8)
    extra = extra.without("noise", "raw samples")
    extra = dataclasses.replace(extra, meta={**extra.meta, "bounds": body.meta["bounds"]})
    cfg = {"hyper": {"fit": False, "lengthscale": 0.9}, "variance_dtype": "float64",
           "partition": {"scheme": "kdtree"}}  # fmt: skip
    for model in ("gpg", "gpgs_hybrid"):
        conf = {k: v for k, v in cfg.items() if model == "gpgs_hybrid" or k == "hyper"}
        sur = Surrogate.fit(body.subset(old), model, conf)
        inside = np.flatnonzero(~design._outside(sur, extra.x, 0.0).any(1))[:4]
        assert inside.size == 4  # body-frame cases with coordinate gradients, in the domain
        more = extra.subset(inside)
        grown = sur.condition(body.subset(new)).condition(more)
        ref = design.rebuild(
            sur, merge_datasets(merge_datasets(body.subset(old), body.subset(new)), more)
        )
        q = np.asarray(sur.normalizer.x(0.5 * (body.x[old[:6]] + body.x[new])))
        for u, v in zip(grown.model.predict(q), ref.predict(q), strict=True):
            np.testing.assert_allclose(u, v, rtol=1e-7, atol=1e-9)
