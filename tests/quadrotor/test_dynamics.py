"""Rigid body, motors and the aerodynamic interface of gpg.quadrotor.dynamics."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor.dynamics import (
    AeroModel,
    Quadrotor,
    SimpleAero,
    State,
    Wind,
    Wrench,
    quat_from_euler,
    quat_to_R,
)
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.simple_model import SimpleModel
from gpg.surrogate import SurrogateAero


class NoAero(AeroModel):
    def wrench(self, rpm, R_WB, v_air, omega):
        return Wrench(jnp.zeros(3), jnp.zeros(3), jnp.zeros(0), jnp.asarray(True))


def run(quad, s, cmd, dt, n, wind=None):
    wind = wind or Wind.calm()

    @jax.jit
    def go(s):
        def body(s, k):
            s, _ = quad.step(s, cmd, k * dt, dt, wind)
            return s, s

        return jax.lax.scan(body, s, jnp.arange(n, dtype=float))

    return go(s)


@pytest.fixture(scope="module")
def simple(vehicle):
    return SimpleModel.from_vehicle(vehicle, 5.3e-7, 8.4e-9)


def test_quaternion_matches_euler(rng):
    for e in np.column_stack(
        [rng.uniform(-3, 3, 10), rng.uniform(-1.5, 1.5, 10), rng.uniform(-3, 3, 10)]
    ):
        np.testing.assert_allclose(quat_to_R(quat_from_euler(jnp.asarray(e))), R_WB(e), atol=1e-14)


def test_free_fall_is_exact(vehicle):
    quad = Quadrotor.from_vehicle(vehicle, NoAero())
    s0 = State.hover([1.0, 2.0, -50.0], 0.0)
    s, _ = run(quad, s0, jnp.zeros(4), 0.01, 200)
    g = float(vehicle.gravity)
    np.testing.assert_allclose(s.v, [0, 0, g * 2.0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s.p, [1.0, 2.0, -50.0 + 0.5 * g * 4.0], rtol=1e-12)


def test_torque_free_body_conserves_momentum_and_energy(vehicle):
    quad = Quadrotor.from_vehicle(vehicle, NoAero())
    s0 = State.hover([0, 0, 0], 0.0, euler=[0.2, 0.3, -0.4])
    np.testing.assert_allclose(s0.R, R_WB(jnp.array([0.2, 0.3, -0.4])), atol=1e-14)
    s0 = eqx.tree_at(lambda s: s.w, s0, jnp.array([3.0, -1.0, 2.0]))
    J = np.asarray(vehicle.inertia)
    _, traj = run(quad, s0, jnp.zeros(4), 1e-3, 3000)
    R = np.asarray(jax.vmap(quat_to_R)(traj.q))
    L = np.einsum("tij,tj->ti", R, np.asarray(traj.w) * J)  # world angular momentum
    E = 0.5 * np.sum(J * np.asarray(traj.w) ** 2, axis=1)
    np.testing.assert_allclose(L, np.broadcast_to(L[0], L.shape), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(E, E[0], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(traj.q), axis=1), 1.0, atol=1e-14)


def test_hover_at_trim_stays_put(vehicle, simple):
    quad = Quadrotor.from_vehicle(vehicle, SimpleAero(simple))
    trim = float(simple.hover_rpm(float(vehicle.weight)))
    s0 = State.hover([0.0, 0.0, -10.0], trim)
    s, _ = run(quad, s0, jnp.full(4, trim), 0.01, 1000)
    np.testing.assert_allclose(s.p, [0, 0, -10.0], atol=1e-9)
    np.testing.assert_allclose(s.w, 0.0, atol=1e-12)


def test_motor_lag_is_first_order(vehicle):
    quad = Quadrotor.from_vehicle(vehicle, NoAero())
    tau = float(vehicle.motor_time_constant)
    n = int(round(tau / 1e-3))
    s, _ = run(quad, State.hover([0, 0, 0], 1000.0), jnp.full(4, 3000.0), 1e-3, n)
    np.testing.assert_allclose(s.rpm, 3000.0 - 2000.0 * np.exp(-1.0), rtol=1e-9)
    s, _ = run(quad, State.hover([0, 0, 0], 1000.0), jnp.full(4, 9e9), 1e-3, 5000)
    np.testing.assert_allclose(s.rpm, float(vehicle.rpm_max), rtol=1e-6)  # clipped command


def test_wind_enters_as_airspeed(vehicle):
    seen = []

    class Spy(AeroModel):
        def wrench(self, rpm, R_WB, v_air, omega):
            jax.debug.callback(lambda v: seen.append(np.asarray(v)), v_air)
            return Wrench(jnp.zeros(3), jnp.zeros(3), jnp.zeros(0), jnp.asarray(True))

    quad = Quadrotor.from_vehicle(vehicle, Spy())
    s0 = eqx.tree_at(lambda s: s.v, State.hover([0, 0, 0], 0.0), jnp.array([4.0, 0.0, 0.0]))
    wind = Wind(
        jnp.array([1.0, 2.0, 0.0]), jnp.array([0.0, 0.5, 0.0]), jnp.asarray(4.0), jnp.asarray(0.0)
    )
    quad.step(s0, jnp.zeros(4), jnp.asarray(1.0), 0.01, wind)
    np.testing.assert_allclose(seen[0], [3.0, -2.5, 0.0], atol=1e-12)  # v − w(1 s)


def test_surrogate_and_simple_share_the_interface(vehicle, simple):
    """A surrogate of data that M explains exactly flies like M."""
    from gpg.data.bounds import Bounds
    from gpg.data.dataset import Dataset
    from gpg.data.sampling import latin_hypercube
    from gpg.surrogate import Surrogate

    x = latin_hypercube(40, Bounds(), 3)
    y, J = simple.batch(x[:, :7])
    ds = Dataset(
        x=x,
        y_aero=np.asarray(y),
        jac_aero=np.asarray(J),
        meta={"simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9}},
    )
    sur = Surrogate.fit(ds, "gpg", {"hyper": {"fit": False}}, vehicle=vehicle)
    state = eqx.tree_at(
        lambda s: s.q,
        State.hover([0, 0, -5.0], 3500.0),
        quat_from_euler(jnp.array([0.1, -0.2, 0.1])),
    )
    wrench = eqx.filter_jit(lambda m, *args: m.wrench(*args))  # op by op: a hundred programs
    a = wrench(SimpleAero(simple), state.rpm, state.R, jnp.array([5.0, 0, 0]), state.w)
    b = wrench(SurrogateAero(sur), state.rpm, state.R, jnp.array([5.0, 0, 0]), state.w)
    for w in (a, b):  # the same Wrench, field by field (no noise outputs in this dataset)
        assert isinstance(w, Wrench)
        assert w.force.shape == w.torque.shape == (3,)
        assert w.levels.shape == (0,)
        assert w.in_domain.shape == () and w.in_domain.dtype == bool
    np.testing.assert_allclose(b.force, a.force, atol=1e-6)
    np.testing.assert_allclose(b.torque, a.torque, atol=1e-6)
    assert bool(b.in_domain)
