"""Frames: Euler round trips, proper rotations, the airflow frame H and its special points."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor import frames


def random_euler(rng, n):
    return np.column_stack(
        [rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-np.pi, np.pi, n)]
    )


def test_rotation_properties(rng):
    for e in random_euler(rng, 20):
        R = np.asarray(frames.R_WB(e))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)


def test_conventions():
    # Positive pitch raises the nose (body x toward world −z); positive yaw turns it right (+y).
    np.testing.assert_allclose(
        frames.R_WB([0, 0.3, 0]) @ np.array([1.0, 0, 0]), [np.cos(0.3), 0, -np.sin(0.3)], atol=1e-15
    )
    np.testing.assert_allclose(
        frames.R_WB([0.3, 0, 0]) @ np.array([1.0, 0, 0]), [np.cos(0.3), np.sin(0.3), 0], atol=1e-15
    )
    # Positive roll lowers the right side (body y toward world +z).
    np.testing.assert_allclose(
        frames.R_WB([0, 0, 0.3]) @ np.array([0, 1.0, 0]), [0, np.cos(0.3), np.sin(0.3)], atol=1e-15
    )


def test_euler_round_trip(rng):
    for e in random_euler(rng, 50):
        back = np.asarray(frames.euler_from_R(frames.R_WB(e)))
        np.testing.assert_allclose(back, e, atol=1e-12)


@pytest.mark.parametrize(
    "pitch", [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-7, -np.pi / 2 + 1e-9, 1.5707]
)
def test_round_trip_near_pitch_limits(rng, pitch):
    for yaw, roll in rng.uniform(-3, 3, (10, 2)):
        R = frames.R_WB([yaw, pitch, roll])
        e = frames.euler_from_R(R)
        np.testing.assert_allclose(frames.R_WB(e), R, atol=1e-9)  # same rotation, any split
        assert abs(float(e[1]) - pitch) < 1e-9


def test_airflow_frame_takes_airflow_to_x(rng):
    for v in rng.normal(size=(30, 3)) * 7:
        R = np.asarray(frames.R_WH(v))
        vhat = v / np.linalg.norm(v)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)  # a rotation, not a mirror
        np.testing.assert_allclose(R @ [1.0, 0, 0], vhat, atol=1e-14)  # R_WH e_x = v̂
        np.testing.assert_allclose(R.T @ vhat, [1.0, 0, 0], atol=1e-14)  # i.e. R_HW v̂ = e_x
        assert abs(R[2, 1]) < 1e-14  # y_H stays horizontal


def test_airflow_frame_does_not_mirror():
    """Pitfall 2: the paper's lone Householder matrix ``I − 2uuᵀ`` (``u ∝ v̂ − e_x``) also takes
    ``e_x`` to ``v̂`` but is a reflection (det −1) that swaps left and right rotors; ``R_WH`` must
    be a proper rotation for the same airflow."""
    v = np.array([3.0, 4.0, 0.0]) / 5
    R = np.asarray(frames.R_WH(v))
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R @ [1.0, 0, 0], v, atol=1e-14)


def test_airflow_frame_commutes_with_world_yaw(rng):
    for v in rng.normal(size=(10, 3)) * 5:
        a = rng.uniform(-np.pi, np.pi)
        Rz = np.asarray(frames.rot_z(a))
        np.testing.assert_allclose(frames.R_WH(Rz @ v), Rz @ frames.R_WH(v), atol=1e-12)


@pytest.mark.parametrize(
    "v",
    [
        [0.0, 0, 0],
        [5.0, 0, 0],
        [1e-12, 0, 0],
        [0, 0, -4.0],
        [0, 0, 3.0],
        [-2.0, 0, 0],
        [0, 1e-10, 0],
    ],
)
def test_airflow_frame_special_points_finite(v):
    v = jnp.asarray(v)
    R = frames.R_WH(v)
    assert np.all(np.isfinite(R))
    np.testing.assert_allclose(np.asarray(R) @ np.asarray(R).T, np.eye(3), atol=1e-14)
    J = jax.jacfwd(frames.R_WH)(v)
    assert np.all(np.isfinite(J))
    g = jax.grad(lambda w: jnp.sum(frames.to_airflow_frame(jnp.array([0.1, 0.2, 0.3]), w)[0]))(v)
    assert np.all(np.isfinite(g))
    if float(jnp.linalg.norm(v)) == 0.0:
        np.testing.assert_array_equal(R, np.eye(3))


def test_dataset_airflow_keeps_euler(rng):
    """With airflow along +x (the dataset frame), H = W and the Euler angles are unchanged."""
    for e in random_euler(rng, 10) * [0.5, 0.6, 0.5]:
        eh, speed, R = frames.to_airflow_frame(e, [7.0, 0, 0])
        np.testing.assert_allclose(eh, e, atol=1e-12)
        assert float(speed) == 7.0


def test_safe_norm_gradient_at_zero():
    assert np.all(np.asarray(jax.grad(frames.safe_norm)(jnp.zeros(3))) == 0)


def test_hover_blend_is_wind_axes_above_hover_speed(rng):
    """Above ``hover_speed`` in horizontal airspeed the blended frame is exactly wind axes
    (``R_WH e_x = v̂``), bit for bit."""
    for e in random_euler(rng, 10):
        d = rng.normal(size=3)
        d[:2] *= rng.uniform(0.5, 15.0) / np.linalg.norm(d[:2])
        v = d
        a = frames.to_airflow_frame(e, v, 0.5)
        b = frames.to_airflow_frame(e, v, 0.0)
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_allclose(np.asarray(a[2])[:, 0], v / np.linalg.norm(v), atol=1e-14)


def test_hover_blend_follows_body_heading_at_rest(rng):
    """At zero airspeed H turns to the body heading: ψ_H = 0 and (θ, φ) unchanged, whatever
    the yaw; without the blend a yaw beyond ±90° would leave the dataset's box."""
    for e in random_euler(rng, 10) * [1.0, 0.6, 0.6]:
        eh, speed, R = frames.to_airflow_frame(e, np.zeros(3), 0.5)
        np.testing.assert_allclose(eh, [0.0, e[1], e[2]], atol=1e-12)
        assert float(speed) == 0.0
        eh0, _, _ = frames.to_airflow_frame(e, np.zeros(3), 0.0)
        np.testing.assert_allclose(eh0, e, atol=1e-12)  # pure wind axes: H = W at rest


def test_hover_blend_continuous_and_smooth():
    """The blend weight and its gradient vanish at ‖v‖ = hover_speed (no jump in the frame or
    its Jacobian), and the Jacobian is finite at rest."""
    e = jnp.array([2.5, 0.2, -0.1])
    u = jnp.array([0.6, 0.8, 0.0])

    def euler_h(s):
        return frames.to_airflow_frame(e, s * u, 0.5)[0]

    below, above = euler_h(0.5 - 1e-7), euler_h(0.5 + 1e-7)
    np.testing.assert_allclose(below, above, atol=1e-6)
    d_below = jax.jacfwd(euler_h)(0.5 - 1e-7)
    d_above = jax.jacfwd(euler_h)(0.5 + 1e-7)
    np.testing.assert_allclose(d_below, d_above, atol=1e-5)
    J = jax.jacfwd(lambda v: frames.to_airflow_frame(e, v, 0.5)[0])(jnp.zeros(3))
    assert np.all(np.isfinite(J))


def test_hover_blend_commutes_with_world_yaw(rng):
    for _ in range(10):
        e = random_euler(rng, 1)[0] * [1.0, 0.5, 0.5]
        v = rng.normal(size=3) * 0.2  # inside the blend
        a = rng.uniform(-np.pi, np.pi)
        Rz = np.asarray(frames.rot_z(a))
        eh, _, R = frames.to_airflow_frame(e, v, 0.5)
        eh2, _, R2 = frames.to_airflow_frame(e + [a, 0, 0], Rz @ v, 0.5)
        np.testing.assert_allclose(np.asarray(R2), Rz @ np.asarray(R), atol=1e-12)
        np.testing.assert_allclose(eh2, eh, atol=1e-12)


def test_vertical_airflow_is_continuous_and_differentiable():
    """Climbs and descents: the frame's heading follows the body's as the horizontal airspeed
    vanishes, so 1 mm/s of sideways air changes the frame by about 1e-3 (not by 90°), and the
    autodiff Jacobian matches central differences at and around vertical airflow."""
    yaw = 0.3

    def frame(v):
        return frames.airflow_frame(v, yaw, 0.5)

    for vz in (3.0, -3.0, 0.7):
        ref = np.asarray(frame(jnp.array([0.0, 0.0, vz])))
        # x_H along the airflow, y_H the body's right (level body) at exactly vertical airflow.
        np.testing.assert_allclose(ref[:, 0], [0, 0, np.sign(vz)], atol=1e-15)
        np.testing.assert_allclose(ref[:, 1], [-np.sin(yaw), np.cos(yaw), 0], atol=1e-15)
        for t in np.linspace(0, 2 * np.pi, 9):
            R = np.asarray(frame(jnp.array([1e-3 * np.cos(t), 1e-3 * np.sin(t), vz])))
            assert np.max(np.abs(R - ref)) < 5e-3
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
            assert np.linalg.det(R) > 0
        for v0 in ([0.0, 0.0, vz], [0.2, -0.1, vz], [0.0, 0.4999, vz]):
            v0 = jnp.asarray(v0)
            J = jax.jacfwd(lambda v: frame(v).ravel())(v0)
            h = 1e-6
            fd = np.stack(
                [(frame(v0 + h * d) - frame(v0 - h * d)).ravel() / (2 * h) for d in np.eye(3)], 1
            )
            np.testing.assert_allclose(J, fd, atol=1e-8 * np.abs(fd).max())
    # At the blend's edge (horizontal airspeed = hover_speed) value and slope match wind axes.
    for w in (0.5 - 1e-7, 0.5 + 1e-7):
        v = jnp.array([w * 0.6, w * 0.8, 2.0])
        np.testing.assert_allclose(frame(v), frames.R_WH(v), atol=1e-6)


def _autodiff_rate(euler_W, v, h):
    """The rate's definition taken literally: forward-mode derivatives of the whole frame."""

    def coords(v):
        euler_h, _, R = frames.to_airflow_frame(euler_W, v, h)
        return euler_h, R

    d_euler, d_frame = jax.jacfwd(coords)(v)
    return jnp.maximum(jnp.sqrt(jnp.sum(d_euler**2)), jnp.sqrt(jnp.sum(d_frame**2) / 2.0))


@pytest.mark.parametrize("h", [0.0, 0.5, 2.0])
def test_airflow_frame_rate_is_the_frames_derivative(rng, h):
    """The closed-form rate is ``max(‖∂euler_H/∂v‖, ‖∂R_WH/∂v‖/√2)`` by autodiff of
    :func:`to_airflow_frame`, over attitudes, hover, the blend, fast flight and nearly
    vertical airflow (where it reaches thousands of rad per m/s)."""
    n = 3000
    E = random_euler(rng, n)
    V = rng.normal(size=(n, 3)) * rng.choice([0.01, 0.1, 0.3, 1.0, 5.0], (n, 1))
    V[:300, :2] *= 1e-4  # nearly vertical airflow
    new = np.asarray(jax.jit(jax.vmap(lambda e, v: frames.airflow_frame_rate(e, v, h)))(E, V))
    ref = np.asarray(jax.jit(jax.vmap(lambda e, v: _autodiff_rate(e, v, h)))(E, V))
    assert np.all(np.isfinite(new)) and np.all(new > 0)
    # Two float64 evaluations of the same derivative in different orders: a few hundred
    # roundings (ε ≈ 2e-16), amplified by the cancellations near the singular sets, at most
    # about rate x speed here (≤ 1e4): 1e-9 relative.
    np.testing.assert_allclose(new, ref, rtol=1e-9)
    # Central differences of the frame at regular states: an independent check of both.
    for e, v in zip(E[300:305], V[300:305], strict=True):
        step = 1e-6 * max(np.linalg.norm(v), 1.0)
        cols_e, cols_R = [], []
        for k in range(3):
            dv = step * np.eye(3)[k]
            ep, _, Rp = frames.to_airflow_frame(e, v + dv, h)
            em, _, Rm = frames.to_airflow_frame(e, v - dv, h)
            cols_e.append((np.asarray(ep) - np.asarray(em)) / (2 * step))
            cols_R.append((np.asarray(Rp) - np.asarray(Rm)).ravel() / (2 * step))
        fd = max(np.linalg.norm(cols_e), np.linalg.norm(cols_R) / np.sqrt(2.0))
        rate = float(frames.airflow_frame_rate(e, v, h))
        np.testing.assert_allclose(rate, fd, rtol=1e-5)  # O(step²) truncation, O(ε/step) noise


def test_airflow_frame_rate_at_the_singular_sets():
    """``inf`` where the frame is not differentiable, unbounded toward the other singular
    sets: no horizontal airspeed with pure wind axes, the Euler angles' gimbal lock in ``H``,
    the blend's rear-airflow ring (where ``y_H`` vanishes)."""
    from scipy.optimize import brentq

    rate = jax.jit(frames.airflow_frame_rate, static_argnums=2)
    e = jnp.array([0.0, 0.1, 0.2])
    for v in ([0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [0.0, 1e-10, 2.0]):
        assert float(rate(e, jnp.asarray(v), 0.0)) == np.inf
    # at rest with the blend, H = Rz(yaw) and d = h e_x: x_H turns by 1/h per m/s along y and
    # z, y_H does not turn about x_H, so √2/h (the Euler angles' rates give the same norm here)
    assert float(rate(e, jnp.zeros(3), 0.5)) == pytest.approx(np.sqrt(2.0) / 0.5, rel=1e-14)
    # pitch_H = 90° (H = W for airflow along +x): the roll and yaw rates divide by cos pitch_H
    assert float(rate(jnp.array([0.3, np.pi / 2, 0.0]), jnp.array([5.0, 0.0, 0.0]), 0.0)) > 1e12
    # airflow from straight behind at the speed where y_ref's two terms cancel (yaw 0, h 0.5):
    # y_ref = (−v_y, k, 0) turns by 1/|k| per m/s of v_y around its zero
    h = 0.5

    def k(s):  # y_ref along the body's right: (c − s) + c₂, c = h(1 − s²/h²)², d = (c − s) e_x
        c = h * (1 - s**2 / h**2) ** 2
        return (c - s) + h * max(1 - (c - s) ** 2 / h**2, 0.0) ** 2

    s = brentq(k, 0.3, 0.49, xtol=1e-15)
    v = jnp.array([-s, 1e-6, 0.0])
    near = float(rate(jnp.zeros(3), v, h))
    assert near > 1e5
    # y_perp ≈ 1e-6 m/s: float64 rounding of ≈ 1e-16 m/s in it, 1e-10 of the rate; 1e-6 asked
    np.testing.assert_allclose(near, float(_autodiff_rate(jnp.zeros(3), v, h)), rtol=1e-6)
    assert float(rate(jnp.zeros(3), jnp.array([-(s + 1e-3), 1e-6, 0.0]), h)) < 1e3


def test_half_turn_is_the_body_turned_about_z_with_the_rotors_relabelled(rng):
    """``R_WB(image) = R_WB Rz(π)`` (closed form), the rotors r1 <-> r3 and r2 <-> r4, twice
    the identity; above the hover blend the airflow frame is the same and the attitude in it
    is ``(ψ_H + π, −θ_H, −φ_H)``: what the surrogate's half turn reads."""
    Rz = np.diag([-1.0, -1.0, 1.0])
    for e in random_euler(rng, 20):
        rpm = rng.uniform(1000, 5000, 4)
        r2, e2 = frames.half_turn(rpm, e)
        np.testing.assert_array_equal(r2, rpm[[2, 3, 0, 1]])
        np.testing.assert_allclose(frames.R_WB(e2), np.asarray(frames.R_WB(e)) @ Rz, atol=1e-14)
        r3, e3 = frames.half_turn(r2, e2)
        np.testing.assert_array_equal(r3, rpm)
        np.testing.assert_allclose(frames.R_WB(e3), frames.R_WB(e), atol=1e-14)
        v = rng.normal(size=3) * 8.0
        v[:2] += 3.0 * np.sign(v[:2])  # horizontal airspeed well above the hover blend's 2 m/s
        eh, _, R = frames.to_airflow_frame(e, v, 2.0)
        eh2, _, R2 = frames.to_airflow_frame(e2, v, 2.0)
        np.testing.assert_allclose(R2, R, atol=1e-14)
        np.testing.assert_allclose(frames.R_WB(eh2), np.asarray(frames.R_WB(eh)) @ Rz, atol=1e-13)
        if abs(eh[1]) < 1.5:  # away from gimbal lock the angles themselves
            turned = np.array([eh[0] + np.pi, -eh[1], -eh[2]])
            wrap = (np.asarray(eh2) - turned + np.pi) % (2 * np.pi) - np.pi
            np.testing.assert_allclose(wrap, 0.0, atol=1e-12)
