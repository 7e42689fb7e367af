"""Geometric controller, mixer and reference trajectories."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import AeroModel, Quadrotor, SimpleAero, State, Wind, Wrench
from gpg.quadrotor.rollout import batched_rollouts, simulate
from gpg.quadrotor.simple_model import SimpleModel


@pytest.fixture(scope="module")
def setup(vehicle):
    simple = SimpleModel.from_vehicle(vehicle, 5.3e-7, 8.4e-9)
    quad = Quadrotor.from_vehicle(vehicle, SimpleAero(simple))
    ctrl = GeometricController.create(vehicle, simple)
    trim = float(simple.hover_rpm(float(vehicle.weight)))
    return simple, quad, ctrl, trim


def test_reaches_waypoint_with_simplified_model(setup):
    _, quad, ctrl, trim = setup
    plan = WaypointPlan.create([[0, 0, -10], [6, -8, -13]], start_time=0.5, leg_time=5.0)
    s, tr = jax.jit(lambda s0: simulate(quad, ctrl, plan, Wind.calm(), s0, 0.01, 1000))(
        State.hover([0, 0, -10.0], trim)
    )
    np.testing.assert_allclose(s.p, [6, -8, -13], atol=0.05)
    err = np.linalg.norm(np.asarray(tr.p) - np.asarray(tr.ref_p), axis=1)
    assert err.max() < 0.5
    assert np.isclose(float(tr.euler[-1, 0]), np.arctan2(-8, 6), atol=0.02)  # nose along the leg


class DragAero(AeroModel):
    """``M`` plus an isotropic airframe drag ``−k |v_air| v_air`` (world frame, at the centre
    of mass): an aerodynamic model on which the wind acts, unlike ``M`` alone."""

    simple: SimpleAero
    k: float  # ½ ρ C_D A, kg/m

    def wrench(self, rpm, R_WB, v_air, omega):
        w = self.simple.wrench(rpm, R_WB, v_air, omega)
        drag = -self.k * jnp.sqrt(jnp.sum(v_air**2)) * v_air
        return Wrench(w.force + drag, w.torque, w.levels, w.in_domain)


def test_steady_wind_offset_matches_position_gain(setup, vehicle):
    """With airframe drag, a steady wind pushes the hovering vehicle downwind until the
    position gain balances the drag (the controller has no integral action): the vehicle
    settles, without oscillating or drifting, at ``drag / K_p`` from its waypoint."""
    simple, _, ctrl, trim = setup
    k = 0.5 * float(vehicle.air_density) * float(vehicle.drag_area[0])
    quad = Quadrotor.from_vehicle(vehicle, DragAero(SimpleAero(simple), k))
    wind = np.array([8.0, -4.0, 0.0])
    hold = np.array([0.0, 0.0, -10.0])
    plan = WaypointPlan.create([hold, hold])
    s, tr = jax.jit(lambda s0: simulate(quad, ctrl, plan, Wind.constant(wind), s0, 0.01, 1000))(
        State.hover(hold, trim)
    )
    drag = k * np.linalg.norm(wind) * wind  # the air moves with the wind past a vehicle at rest
    offset = drag / np.asarray(ctrl.kp)
    assert np.linalg.norm(offset) > 0.05  # the wind matters here
    np.testing.assert_allclose(s.p, hold + offset, atol=1e-6)
    np.testing.assert_allclose(s.v, 0.0, atol=1e-6)
    dev = np.linalg.norm(np.asarray(tr.p) - hold, axis=1)
    assert dev.max() < 1.5 * np.linalg.norm(offset)  # no large overshoot on the way


def test_mixer_limits_and_yaw_priority(setup, vehicle):
    simple, _, ctrl, trim = setup
    T = float(vehicle.weight)
    rpm = np.asarray(ctrl.mix(jnp.asarray(T), jnp.array([0.0, 0.0, 50.0])))  # absurd yaw demand
    assert np.all(rpm >= float(vehicle.rpm_min)) and np.all(rpm <= float(vehicle.rpm_max))
    u = np.asarray(simple.allocation) @ rpm**2
    np.testing.assert_allclose(u[0], T, rtol=1e-9)  # thrust kept
    np.testing.assert_allclose(u[1:3], 0.0, atol=1e-9)  # roll/pitch kept
    assert u[3] > 0  # yaw as much as the motors allow
    np.testing.assert_allclose(ctrl.mix(jnp.asarray(T), jnp.zeros(3)), trim, rtol=1e-12)


def test_waypoint_plan_reference():
    plan = WaypointPlan.create([[0, 0, 0], [10, 0, 0], [10, 10, 0]], start_time=1.0, leg_time=2.0)
    r0, r_end, r_mid = plan(jnp.asarray(0.5)), plan(jnp.asarray(10.0)), plan(jnp.asarray(2.0))
    np.testing.assert_allclose(r0.p, 0.0)
    np.testing.assert_allclose(r_end.p, [10, 10, 0])
    np.testing.assert_allclose(r_mid.p, [5, 0, 0])
    np.testing.assert_allclose(r_mid.v, [10 * 30 / 16 / 2, 0, 0])  # peak speed 15/8 d/T
    np.testing.assert_allclose(r_end.v, 0.0)
    assert np.isclose(float(plan(jnp.asarray(5.0)).yaw), np.pi / 2)
    flip = WaypointPlan.create([[0, 0, 0], [1, 0, 0], [0, 0, 0]], yaw0=0.0)
    assert np.isclose(abs(float(flip(jnp.asarray(100.0)).yaw)), np.pi)
    with pytest.raises(ValueError, match="waypoints must be"):
        WaypointPlan.create([[0, 0, 0]])
    with pytest.raises(ValueError, match="yaw must be"):
        WaypointPlan.create([[0, 0, 0], [1, 0, 0]], yaw="north")


def test_batched_rollouts_equal_single(setup):
    _, quad, ctrl, trim = setup
    s0 = State.hover([0, 0, -10.0], trim)
    key = jax.random.key(3)
    _, tr = jax.jit(lambda k: batched_rollouts(quad, ctrl, k, s0, n_envs=4, n_steps=150, dt=0.01))(
        key
    )
    assert tr.p.shape == (4, 150, 3) and np.all(np.isfinite(np.asarray(tr.p)))
    from gpg.quadrotor.rollout import random_scenario

    plan, wind = random_scenario(jax.random.split(key, 4)[2], s0.p)
    _, one = simulate(quad, ctrl, plan, wind, s0, 0.01, 150)
    np.testing.assert_allclose(tr.p[2], one.p, rtol=1e-10, atol=1e-10)


def test_unknown_gain(vehicle):
    with pytest.raises(ValueError, match=r"unknown controller gains \['kp'\]"):
        GeometricController.create(
            vehicle, SimpleModel.from_vehicle(vehicle, 5e-7, 8e-9), {"kp": 1}
        )
