"""Physical sanity of the BEMT generator (acceptance list of the physics issue)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor import bemt
from gpg.quadrotor.frames import R_WB


def test_hover_thrust_follows_rpm_squared(aero, simple):
    P_F = float(simple.P_F)  # least squares over 2000-6000 rpm
    for rpm in np.arange(2000.0, 6001.0, 500.0):
        T = np.asarray(aero([rpm] * 4, [0, 0, 0], 0.0).rotors.thrust)
        np.testing.assert_allclose(T, P_F * rpm**2, rtol=0.05)


def test_hover_rpm_for_weight(aero, vehicle):
    W = float(vehicle.weight)
    lift = lambda r: -float(aero([r] * 4, [0, 0, 0], 0.0).force_W[2])  # noqa: E731
    assert lift(3300.0) < W < lift(3900.0)


def test_zero_rpm_zero_loads_at_rest(aero):
    """No rotation, no airspeed: no loads (to 1e-20 N; velocities are floored at 1e-6 m/s)."""
    res = aero([0.0] * 4, [0.1, 0.2, -0.3], 0.0)
    for leaf in (
        res.rotors.thrust,
        res.rotors.torque,
        res.rotors.force,
        res.rotors.moment,
        res.force_W,
        res.torque_W,
    ):
        np.testing.assert_allclose(np.asarray(leaf), 0.0, rtol=0, atol=1e-20)


@pytest.mark.slow  # compiles the generator's exact Jacobian (20 s); see test_bemt
def test_zero_rpm_in_wind_is_finite(y_of, jac_of):
    """Stopped rotors in a 15 m/s wind: finite loads and finite gradients (no 0/0)."""
    x = [0.0] * 4 + [0.3, -0.2, 0.1, 15.0]
    assert np.all(np.isfinite(np.asarray(y_of(x))))
    assert np.all(np.isfinite(np.asarray(jac_of(x))))


@pytest.mark.parametrize("V", [5.0, 10.0, 20.0])
def test_h_force_opposes_motion(aero, V):
    res = aero([3600.0] * 4, [0, 0, 0], V)
    assert np.all(np.asarray(res.rotors.h_force) > 0)  # dragged downstream, with the airflow
    assert np.all(np.asarray(res.rotors.force)[:, 0] < 0)  # i.e. against the +x motion


@pytest.mark.parametrize("V, pitch", [(10.0, 0.0), (20.0, 0.0), (15.0, -0.15)])
def test_rear_rotors_ingest_front_wake(aero, V, pitch):
    T = np.asarray(aero([3600.0] * 4, [0, pitch, 0], V).rotors.thrust)
    assert max(T[0], T[1]) < min(T[2], T[3])  # r1, r2 rear; r3, r4 front


def test_mirror_symmetry(y_of, rng):
    """y -> −y with r1<->r2, r3<->r4: Fy, Mx, Mz flip; Fx, Fz, My and the noise below stay."""
    for _ in range(6):
        x = np.concatenate(
            [
                rng.uniform(500, 6500, 4),
                rng.uniform([-1.2, -0.9, -1.2], [1.2, 0.9, 1.2]),
                [rng.uniform(0, 20)],
            ]
        )
        xm = x[[1, 0, 3, 2, 4, 5, 6, 7]] * [1, 1, 1, 1, -1, 1, -1, 1]
        y, ym = np.asarray(y_of(x)), np.asarray(y_of(xm))
        sign = np.array([1, -1, 1, -1, 1, -1])
        np.testing.assert_allclose(ym[:6], sign * y[:6], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ym[8], y[8], rtol=1e-9)


@pytest.mark.slow  # compiles the generator's exact Jacobian (30 s)
def test_exact_jacobian_matches_central_differences(y_of, jac_of, rng):
    for _ in range(4):
        x = np.concatenate(
            [
                rng.uniform(1000, 6000, 4),
                rng.uniform([-1.2, -0.9, -1.2], [1.2, 0.9, 1.2]),
                [rng.uniform(2, 18)],
            ]
        )
        J = np.asarray(jac_of(x))
        for j, h in enumerate([0.05] * 4 + [1e-6] * 3):
            e = np.zeros(8)
            e[j] = h
            fd = (np.asarray(y_of(x + e)) - np.asarray(y_of(x - e))) / (2 * h)
            np.testing.assert_allclose(J[:, j], fd, rtol=2e-5, atol=1e-7 * np.abs(J).max())


@pytest.mark.slow
def test_inflow_converges_everywhere(gen, rng):
    """Blade-element and momentum thrust agree at the solved inflow across the sampling box."""
    n = 300
    X = np.column_stack(
        [
            rng.uniform(0, 7000, (n, 4)),
            rng.uniform(-np.pi / 2, np.pi / 2, n),
            rng.uniform(-np.pi / 3, np.pi / 3, n),
            rng.uniform(-np.pi / 2, np.pi / 2, n),
            rng.uniform(0, 20, n),
        ]
    )
    v, cfg = gen.vehicle, gen.bemt
    grid = bemt._grid(v, cfg.n_radial, cfg.n_azimuth)

    def resid(x):
        v_rel = -(R_WB(x[4:7]).T @ jnp.stack([x[7], 0.0, 0.0]))

        def one(o, d):
            v0 = bemt.solve_inflow(v, cfg, o, d, v_rel[:2], v_rel[2])
            T = bemt._bet_thrust(v, cfg, grid, o, d, v_rel[:2], v_rel[2], v0)
            return (T - bemt._momentum_thrust(v, cfg, v_rel[:2], v_rel[2], v0)) / (
                jnp.abs(T) + 0.01
            )

        return jax.vmap(one)(x[:4] * bemt.RPM_TO_RAD_S, v.spin)

    r = np.asarray(jax.jit(jax.vmap(resid))(jnp.asarray(X)))
    assert np.all(np.isfinite(r))
    assert np.abs(r).max() < 1e-8


def test_polar_limits(vehicle):
    foil = vehicle.airfoil
    a = jnp.deg2rad(jnp.array([0.0, 5.0, 90.0, 180.0, -90.0]))
    cl, cd = bemt.polar(foil, jnp.sin(a), jnp.cos(a), jnp.zeros(5))
    np.testing.assert_allclose(cl[1], float(foil.lift_slope) * np.deg2rad(5 + 3.0), rtol=0.02)
    assert abs(float(cl[2])) < 1e-6 and float(cd[2]) > 1.9  # flat plate broadside
    assert abs(float(cl[3])) < 1e-6  # reversed flow, flat plate
