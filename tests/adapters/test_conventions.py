"""The conventions boundary: conversions round-trip, agree with each other, and a z-up
simulator sees gpg's wrench in its own frames."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.adapters import conventions as cv
from gpg.quadrotor.dynamics import quat_from_euler, quat_to_R
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.simple_model import SimpleModel


def test_round_trips_and_consistency(rng):
    euler = rng.uniform(-1.0, 1.0, (5, 3))
    for e in euler:
        q = quat_from_euler(jnp.asarray(e))
        qz = cv.quat_to_zup(q)
        np.testing.assert_allclose(cv.quat_from_zup(qz), q, atol=1e-15)
        np.testing.assert_allclose(cv.quat_xyzw_to_wxyz(cv.quat_wxyz_to_xyzw(q)), q)
        # The z-up quaternion is the z-up attitude matrix F R F (scipy's xyzw convention).
        from scipy.spatial.transform import Rotation

        np.testing.assert_allclose(
            Rotation.from_quat(np.asarray(qz)).as_matrix(), cv.flip_rotation(R_WB(e)), atol=1e-12
        )
        np.testing.assert_allclose(cv.rotation_from_zup_quat(qz), quat_to_R(q), atol=1e-12)
    v = rng.normal(size=3)
    np.testing.assert_allclose(cv.flip(cv.flip(v)), v)
    np.testing.assert_allclose(cv.rad_s_to_rpm(cv.rpm_to_rad_s(3600.0)), 3600.0)
    np.testing.assert_allclose(cv.rpm_to_rad_s(60.0), 2 * np.pi)


@pytest.mark.parametrize("which", ["M", "surrogate"])
def test_zup_wrench_is_gpgs_wrench_in_zup_frames(which, vehicle, synthetic_surrogate, rng):
    simple = SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09)
    aero = simple if which == "M" else synthetic_surrogate
    from gpg.quadrotor.dynamics import SimpleAero

    zup = cv.ZUp(SimpleAero(aero) if which == "M" else aero, rad_s=True)
    euler = np.array([0.4, 0.1, -0.2])
    q = quat_from_euler(jnp.asarray(euler))
    rpm = np.array([3500.0, 3600.0, 3550.0, 3620.0])
    v_w, wind_w = np.array([4.0, 1.0, -0.5]), np.array([-2.0, 0.5, 0.0])  # gpg world
    wrench = eqx.filter_jit(zup.wrench)  # one program: op by op it compiled a hundred
    out = wrench(cv.rpm_to_rad_s(rpm), cv.quat_to_zup(q), cv.flip(v_w), cv.flip(wind_w))
    if which == "M":
        want_f, want_t = (np.asarray(x) for x in simple(np.concatenate([rpm, euler])).reshape(2, 3))
        var = None
    else:
        p = synthetic_surrogate.predict(rpm, euler, v_w - wind_w)
        want_f, want_t, var = np.asarray(p.force), np.asarray(p.torque), p.variance
        assert bool(out.in_domain) == bool(p.in_domain)
    np.testing.assert_allclose(out.force_world, cv.flip(want_f), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.torque_world, cv.flip(want_t), rtol=1e-10, atol=1e-10)
    Rz = cv.flip_rotation(R_WB(euler))
    np.testing.assert_allclose(out.force_body, Rz.T @ out.force_world, rtol=1e-10, atol=1e-10)
    if var is not None:  # a rotation keeps the trace of a variance
        np.testing.assert_allclose(np.sum(out.variance_body[:3]), np.sum(var[:3]), rtol=1e-9)
    # In hover M's thrust points up in the z-up world.
    level = wrench(cv.rpm_to_rad_s(np.full(4, 3500.0)), np.array([0, 0, 0, 1.0]), np.zeros(3))
    if which == "M":
        assert float(level.force_world[2]) > 0 and abs(float(level.force_world[0])) < 1e-9
