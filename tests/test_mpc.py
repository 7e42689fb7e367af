"""MPC: flat dynamics equal the simulator's step, linearisations and the variance's Jacobian
match finite differences, covariance propagation, and MPPI on a system with a known answer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.mpc import MPPI, Dynamics, pack, propagate, unpack
from gpg.quadrotor.dynamics import Quadrotor, SimpleAero, State, Wind
from gpg.quadrotor.simple_model import SimpleModel


@pytest.fixture(scope="module")
def M(vehicle):
    return SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09)


def _state():
    return State(
        p=jnp.array([1.0, -2.0, -10.0]),
        v=jnp.array([3.0, 1.0, -0.5]),
        q=jnp.array([0.99, 0.05, -0.08, 0.1])
        / jnp.linalg.norm(jnp.array([0.99, 0.05, -0.08, 0.1])),
        w=jnp.array([0.1, -0.2, 0.05]),
        rpm=jnp.array([3500.0, 3600.0, 3550.0, 3620.0]),
    )


def _fd_jac(f, x, h):
    return jnp.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in jnp.eye(x.size)], axis=-1)


def test_flat_dynamics_is_the_simulators_step(vehicle, M):
    wind = Wind.constant([1.0, -0.5, 0.0])
    dyn = Dynamics.create(vehicle, M, 0.01, wind=wind)
    s = _state()
    u = jnp.array([3550.0, 3580.0, 3500.0, 3600.0])
    want, _ = Quadrotor.from_vehicle(vehicle, SimpleAero(M)).step(s, u, 0.3, 0.01, wind)
    np.testing.assert_allclose(dyn(pack(s), u, 0.3), pack(want), rtol=1e-12, atol=1e-12)
    x = pack(s)
    np.testing.assert_allclose(pack(unpack(x)), x, atol=1e-15)
    with pytest.raises(ValueError, match="shape \\(17,\\)"):
        dyn(x[:16], u, 0.0)
    with pytest.raises(ValueError, match="shape \\(4,\\)"):
        dyn(x, u[:3], 0.0)


def test_linearisation_and_variance_jacobians(vehicle, synthetic_surrogate):
    dyn = Dynamics.create(vehicle, synthetic_surrogate, 0.01, wind=Wind.constant([1.0, 0.0, 0.0]))
    x, u = pack(_state()), jnp.array([3550.0, 3580.0, 3500.0, 3600.0])
    lin = jax.jit(dyn.linearize)(x, u, 0.2)
    f, var = jax.jit(dyn), jax.jit(dyn.variance)
    np.testing.assert_allclose(lin.x_next, f(x, u, 0.2), rtol=1e-12)
    h = jnp.concatenate([jnp.full(13, 1e-5), jnp.full(4, 1e-2)])  # rpm in hundreds
    A_fd = jnp.stack(
        [(f(x + h * e, u, 0.2) - f(x - h * e, u, 0.2)) / (2 * (h * e).sum()) for e in jnp.eye(17)],
        axis=1,
    )
    B_fd = _fd_jac(lambda uu: f(x, uu, 0.2), u, 1e-2)
    np.testing.assert_allclose(lin.A, A_fd, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(lin.B, B_fd, rtol=1e-5, atol=1e-9)
    V_fd = jnp.stack(
        [
            (var(x + h * e, u, 0.2) - var(x - h * e, u, 0.2)) / (2 * (h * e).sum())
            for e in jnp.eye(17)
        ],
        axis=1,
    )
    assert np.all(np.asarray(lin.variance) > 0)
    np.testing.assert_allclose(
        lin.dvariance_dx, V_fd, rtol=1e-5, atol=1e-9 * float(jnp.max(lin.variance))
    )
    assert np.all(lin.state_variance[3:6] > 0) and np.all(lin.state_variance[10:13] > 0)
    assert np.all(lin.state_variance[:3] == 0)


def test_propagate_is_the_recursion():
    """Σ₁ = A₀ Σ₀ A₀ᵀ + diag(q₀), Σ₂ = A₁ Σ₁ A₁ᵀ + diag(q₁), with a NumPy reference."""
    from gpg.mpc import Linearization

    rng = np.random.default_rng(0)
    A = rng.normal(size=(2, 17, 17)) * 0.3
    q = rng.uniform(0, 1, (2, 17))
    z = np.zeros((2, 17))
    lin = Linearization(
        z,
        jnp.asarray(A),
        z[:, :4, None] * 0,
        z[:, :6],
        z[:, :6, None] * 0,
        z[:, :4, None] * 0,
        jnp.asarray(q),
    )
    S0 = np.eye(17) * 0.1
    S = np.asarray(propagate(lin, jnp.asarray(S0)))
    S1 = A[0] @ S0 @ A[0].T + np.diag(q[0])
    np.testing.assert_allclose(S[0], S1, rtol=1e-12)
    np.testing.assert_allclose(S[1], A[1] @ S1 @ A[1].T + np.diag(q[1]), rtol=1e-12)


def test_mppi_steers_a_double_integrator():
    """x = (position, velocity), u = acceleration: MPPI drives it to the origin."""
    dt = 0.1

    def f(x, u, t):
        return jnp.array([x[0] + dt * x[1] + 0.5 * dt**2 * u[0], x[1] + dt * u[0]])

    def cost(xs, us, ts):
        return jnp.sum(xs[:, 0] ** 2) + 0.1 * jnp.sum(xs[:, 1] ** 2) + 0.01 * jnp.sum(us**2)

    mppi = MPPI(
        f,
        cost,
        jnp.array([1.0]),
        jnp.array([-2.0]),
        jnp.array([2.0]),
        temperature=0.5,
        dt=dt,
        horizon=20,
        samples=256,
        knots=5,
    )
    solve = jax.jit(mppi.solve)
    x, us = jnp.array([2.0, 0.0]), jnp.zeros((20, 1))
    for k in range(60):
        us, info = solve(jax.random.key(k), x, us, k * dt)
        x = f(x, us[0], 0.0)
        us = MPPI.shift(us)
    assert abs(float(x[0])) < 0.1 and abs(float(x[1])) < 0.2
    with pytest.raises(ValueError, match="knots"):
        MPPI(
            f,
            cost,
            jnp.ones(1),
            -jnp.ones(1),
            jnp.ones(1),
            temperature=1.0,
            dt=dt,
            horizon=4,
            samples=8,
            knots=9,
        )
