"""The body-frame formulation (gpg.names.FRAMES, ``Surrogate.frame == "body"``): inputs
``(rpm, R_WBᵀ v_air)``, no singular coordinates. On a synthetic body-frame dataset (an
analytic function, exact gradients): the world prediction is the body prediction rotated, the
domain is the ball of air velocities (hover, vertical and reverse air inside), 1 mm/s of air
moves the force by at most what its Lipschitz bound allows (no jump anywhere), derivatives
equal finite differences, checkpoints keep the frame, and what does not take the body frame
says so."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import Surrogate, checkpoint
from gpg.quadrotor.frames import R_WB
from tests.helpers import synthetic_body_dataset


@pytest.fixture(scope="module")
def body():
    """The default model on synthetic body-frame data (fixed hyperparameters: the fits' own
    tests are elsewhere; one fit for the fast budget)."""
    ds, _ = synthetic_body_dataset(60, seed=3)
    hyper = {"fit": False, "lengthscale": 0.8, "noise": 1e-6}
    cfg = {"hyper": hyper, "partition": {"points_per_bin": 20}, "near": {"points": 30}}
    return ds, Surrogate.fit(ds, "gpgs_hybrid", cfg)


RPM = np.full(4, 3600.0)


def test_world_prediction_is_the_body_prediction_rotated(body):
    """``F_W = R_WB F_B`` (to rounding), the variance rotated likewise; the body entry point
    (``predict_body``) gives the body-frame values themselves."""
    _, sur = body
    euler = np.array([2.5, -0.4, 0.3])  # heading 143°: the air comes from behind-left
    R = np.asarray(R_WB(jnp.asarray(euler)))
    v_b = np.array([-6.0, 2.0, 1.5])
    world = sur.predict(RPM, euler, R @ v_b)
    b = sur.predict_body(RPM, R, v_b)
    np.testing.assert_allclose(np.asarray(world.force), R @ np.asarray(b.force), atol=1e-10)
    np.testing.assert_allclose(np.asarray(world.torque), R @ np.asarray(b.torque), atol=1e-10)
    np.testing.assert_allclose(
        np.asarray(world.variance)[:3], (R**2) @ np.asarray(b.variance)[:3], rtol=1e-10
    )
    np.testing.assert_allclose(np.asarray(world.levels), np.asarray(b.levels), atol=1e-10)
    assert bool(world.in_domain) and bool(b.in_domain)


@pytest.mark.parametrize(
    "v, inside",
    [
        ((0.0, 0.0, 0.0), True),  # hover
        ((0.0, 0.0, 3.0), True),  # vertical descent
        ((0.0, 0.0, -3.0), True),  # vertical climb
        ((1.0, 0.0, -3.0), True),
        ((-5.0, 0.0, 0.0), True),  # air from behind
        ((0.0, -19.9, 0.0), True),
        ((12.0, 12.0, 12.0), False),  # 20.8 m/s: outside the ball, inside its box
        ((0.0, 0.0, 20.5), False),
    ],
)
def test_domain_is_the_ball_of_air_velocities(body, v, inside):
    _, sur = body
    assert bool(sur.predict_mean(RPM, np.array([0.7, 0.1, -0.2]), np.array(v)).in_domain) is inside
    assert not bool(
        sur.predict_mean(np.array([3600, 3600, -1.0, 3600]), np.zeros(3), np.zeros(3)).in_domain
    )


def test_no_jump_anywhere_near_hover_or_vertical_air(body):
    """1 mm/s of air, along each axis, at hover, vertical and near-vertical air and random
    headings: the force changes by at most ``1e-3 m/s · max|∂F/∂v|`` (the mean is smooth: no
    frame to swing). The bound's derivative comes from jax.jacfwd at the same states, and the
    Jacobian itself equals central finite differences (step 1e-5 m/s, float64: truncation
    ~1e-10 relative)."""
    _, hyb = body
    rng = np.random.default_rng(0)
    v = np.concatenate(
        [
            np.zeros((1, 3)),
            [[0, 0, 3.0], [0, 0, -3.0], [0, 0, 10.0]],
            np.c_[0.01 * rng.normal(size=(6, 2)), rng.uniform(-5, 5, (6, 1))],
            0.3 * rng.normal(size=(6, 3)),
        ]
    )
    euler = np.c_[rng.uniform(-np.pi, np.pi, len(v)), 0.2 * rng.normal(size=(len(v), 2))]
    force = jax.jit(jax.vmap(lambda e, w: hyb.predict_mean(RPM, e, w).force))
    dF = jax.jit(jax.vmap(jax.jacfwd(lambda e, w: hyb.predict_mean(RPM, e, w).force, argnums=1)))
    J = np.asarray(dF(euler, v))
    f0 = np.asarray(force(euler, v))
    for a in range(3):
        step = np.zeros(3)
        step[a] = 1e-3
        change = np.abs(np.asarray(force(euler, v + step)) - f0).max(1)
        assert np.all(change <= 1e-3 * np.abs(J).max((1, 2)) * 1.01 + 1e-12), change
        h = np.zeros(3)
        h[a] = 1e-5
        fd = (np.asarray(force(euler, v + h)) - np.asarray(force(euler, v - h))) / 2e-5
        np.testing.assert_allclose(fd, J[:, :, a], rtol=1e-5, atol=1e-6 * np.abs(J).max())


def test_checkpoint_keeps_the_frame(body, tmp_path):
    _, sur = body
    checkpoint.save(tmp_path / "b", sur)
    back = checkpoint.load(tmp_path / "b")
    assert back.frame == "body"
    state = (RPM, np.array([0.4, 0.0, 0.1]), np.array([0.0, 0.0, -4.0]))
    np.testing.assert_array_equal(
        np.asarray(back.predict(*state).force), np.asarray(sur.predict(*state).force)
    )


@pytest.mark.slow  # M_noise's compilation (10 s); its body-frame physics has a fast test
def test_m_noise_in_the_body_frame(body):
    """``noise_model=True`` fits body-frame data: the levels' targets are ``L − M_noise(x_B)``
    and ``predict`` adds ``M_noise`` at the query's ``x_B = (rpm, R_WBᵀ v_air)`` back to the
    GP's levels (recomputed here from the model's parts, float64: 1e-10)."""
    ds, _ = body
    sur = Surrogate.fit(ds, "gpg", {"hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-6}},
                        noise_model=True)  # fmt: skip
    assert sur.noise_model is not None
    euler, v = np.array([2.5, -0.4, 0.3]), np.array([-3.0, 1.0, 2.0])
    x_b = jnp.concatenate([jnp.asarray(RPM), R_WB(jnp.asarray(euler)).T @ jnp.asarray(v)])
    gp = sur.normalizer.y_inv(sur.model.mean_one(sur.normalizer.x(x_b)))
    p = sur.predict(RPM, euler, v)
    np.testing.assert_allclose(p.levels, gp[6:] + sur.noise_model(x_b), rtol=1e-10)
    assert bool(p.in_domain)


def test_what_does_not_take_the_body_frame_says_so(body):
    ds, _ = body
    with pytest.raises(ValueError, match="partition.dim=7 is not an input of the 7-input data"):
        Surrogate.fit(ds, "gpgs", {"hyper": {"fit": False}})


def test_condition_and_propose_on_body_frame_cases(body):
    """New cases (air from every direction, some without the w gradient) conditioned equal a
    rebuild on all cases with the same hyperparameters and bins, to 1e-8 of the normalised
    mean and variance; the next cases are proposed inside the ball; cases outside the ball or
    in the other frame are refused by name."""
    from dataclasses import replace

    from gpg import design
    from gpg.data import Bounds, latin_hypercube
    from tests.helpers import _synthetic, smooth_body, synthetic_body_dataset, synthetic_dataset

    ds, sur = body
    _, W = synthetic_body_dataset(60, seed=3)  # the fixture's function
    x = latin_hypercube(12, Bounds(), 11, "body")
    new = _synthetic(x, *smooth_body(x, W), ds.meta)
    jac, jn = new.jac_aero.copy(), new.jac_noise.copy()
    jac[::2, :, 6], jn[::2, :, 6] = np.nan, np.nan
    new = replace(new, jac_aero=jac, jac_noise=jn)
    grown = sur.condition(new)
    ref = design.rebuild(sur, design.merge_datasets(ds, new))
    Q = np.asarray(sur.normalizer.x(latin_hypercube(30, Bounds(), 12, "body")))
    (m1, v1), (m2, v2) = grown.model.predict(Q), ref.predict(Q)
    np.testing.assert_allclose(m1, m2, atol=1e-8)
    np.testing.assert_allclose(v1, v2, atol=1e-8)

    far = x.copy()
    far[0, 4:] = [12.0, 12.0, 12.0]  # 20.8 m/s: inside the ball's box, outside the ball
    wider = {**ds.meta, "bounds": {"rpm": [0.0, 7000.0], "airspeed": [0.0, 25.0]}}
    with pytest.raises(ValueError, match=r"new case\(s\) \[0\] lie outside .*ball"):
        sur.condition(_synthetic(far, *smooth_body(far, W), wider))
    # The next cases: drawn from the ball, never outside it; candidates outside refused.
    p = design.propose(sur, ds, batch=3, candidates=200, reference=64)
    assert p.x.shape == (3, 7) and p.gradients.shape == (3, 7)
    assert np.all(np.linalg.norm(p.x[:, 4:], axis=1) <= 20.0)
    with pytest.raises(ValueError, match=r"candidate\(s\) \[0\] lie outside .*ball"):
        design.propose(sur, ds, batch=1, candidates=far, reference=64)
    airflow = synthetic_dataset(5, seed=2, raw=False)[0]
    with pytest.raises(ValueError, match="airflow frame but the surrogate was fitted in the body"):
        sur.condition(airflow)


@pytest.mark.slow  # a linearisation compile; gpg.mpc has its own fast tests
def test_mpc_linearises_a_body_frame_surrogate_at_hover_in_still_air(body):
    """``gpg.mpc.Dynamics`` on the body-frame surrogate at hover in still air (``v_air = 0``,
    where the airflow frame is singular): its Jacobians equal central differences."""
    from gpg.mpc import Dynamics, pack
    from gpg.quadrotor.dynamics import State, Wind
    from gpg.quadrotor.vehicle import load_vehicle

    _, sur = body
    dyn = Dynamics.create(
        load_vehicle("sui_endurance"), sur, 0.01, wind=Wind.constant([0.0, 0.0, 0.0])
    )
    x = pack(State(p=jnp.zeros(3), v=jnp.zeros(3), q=jnp.array([1.0, 0, 0, 0]), w=jnp.zeros(3),
                   rpm=jnp.full(4, 3600.0)))  # fmt: skip
    u = jnp.full(4, 3600.0)
    lin = jax.jit(dyn.linearize)(x, u, 0.0)
    f = jax.jit(dyn)
    h = jnp.concatenate([jnp.full(13, 1e-5), jnp.full(4, 1e-2)])
    A_fd = jnp.stack(
        [(f(x + h * e, u, 0.0) - f(x - h * e, u, 0.0)) / (2 * (h * e).sum()) for e in jnp.eye(17)],
        axis=1,
    )
    np.testing.assert_allclose(lin.A, A_fd, rtol=1e-5, atol=1e-7)
