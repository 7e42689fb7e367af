"""Rotations: body attitude, Euler angles and the airflow-aligned frame H.

Conventions (docs/design.md, "Conventions"): world/dataset frame x forward, y right, z down;
body frame FRD; ``R_WB = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; Euler vectors are ordered
``(yaw, pitch, roll)`` as in the input vector ``x = (r1..r4, yaw, pitch, roll, airspeed)``.

The airflow frame ``H`` (paper, Section "Real-time Simulation") has its x axis along the
airspeed vector ``v_air = v_vehicle − v_wind``, so that in ``H`` every query looks like a dataset
case (airflow along +x). The paper builds ``R_WH`` as a single Householder matrix
``I − 2uuᵀ``, which is a *reflection* (det −1): used as a change of frame it mirrors the vehicle
and swaps left and right rotors. Here ``R_WH`` is a proper rotation ("wind axes"):
``R_WH = Rz(χ) Ry(γ)`` with heading ``χ = atan2(v_y, v_x)`` and climb angle
``γ = atan2(−v_z, ‖v_xy‖)``. It satisfies ``R_WH e_x = v̂`` (equivalently ``R_WHᵀ v̂ = e_x``;
for the symmetric Householder matrix the two statements coincide, for a rotation only these
do). Unlike the minimal (Rodrigues) rotation from ``e_x`` to ``v̂`` it commutes with rotations
about the world z axis, ``R_WH(Rz v) = Rz R_WH(v)``, so yawing a whole query yaws its prediction
for every airspeed, climbing or not; it keeps ``y_H`` horizontal like the dataset frame. It is
defined everywhere: ``v = 0`` gives the identity, vertical airflow a heading of zero, and the
gradients stay finite there (guarded ``atan2`` and ``sqrt``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "R_WB",
    "R_WH",
    "TINY_SPEED",
    "airflow_direction",
    "airflow_frame",
    "airflow_frame_rate",
    "euler_from_R",
    "half_turn",
    "matmul",
    "matvec",
    "safe_atan2",
    "to_airflow_frame",
]

# Below this horizontal speed (m/s) the heading is taken as zero. Far below any physical
# airspeed; only there to keep atan2 and its gradient defined at the origin.
TINY_SPEED = 1e-9  # also the exports' (C, CasADi, ONNX): the same frame everywhere

# Rotor order r1..r4 (rear-right, rear-left, front-left, front-right): a half turn about the
# body z axis takes each hub to its diagonal opposite, r1 <-> r3 and r2 <-> r4.
HALF_TURN_ROTORS = (2, 3, 0, 1)


def rot_x(a: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Rotation about x by ``a`` (rad)."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.array([[o, z, z], [z, c, -s], [z, s, c]])


def rot_y(a: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Rotation about y by ``a`` (rad); positive pitch raises the nose (x toward −z)."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.array([[c, z, s], [z, o, z], [-s, z, c]])


def rot_z(a: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Rotation about z by ``a`` (rad); positive yaw turns the nose right (x toward +y)."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.array([[c, -s, z], [s, c, z], [z, z, o]])


def matvec(R: Float[Array, "m n"], v: Float[Array, " n"]) -> Float[Array, " m"]:
    """``R @ v`` as a broadcast multiply-add.

    XLA fuses it with its neighbours, where a small ``dot`` (3x3 rotations, the 4x4 rotor
    allocation) would be a separate kernel launch; the launches add up in a real-time
    prediction (see docs/measurements.md).

    Args:
        R: an (m, n) matrix.
        v: an (n,) vector.

    Returns:
        The (m,) product ``R v``.
    """
    return jnp.sum(R * v[None, :], axis=1)


def matmul(A: Float[Array, "3 3"], B: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """``A @ B`` for 3x3 matrices, fusible (see :func:`matvec`).

    Args:
        A: the left (3, 3) matrix.
        B: the right (3, 3) matrix.

    Returns:
        The (3, 3) product ``A B``.
    """
    return jnp.sum(A[:, :, None] * B[None, :, :], axis=1)


def R_WB(euler: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    """Body-to-world rotation ``Rz(yaw) Ry(pitch) Rx(roll)``.

    Written out entry by entry (the product expanded), which compiles to one fused kernel.

    Args:
        euler: (3,) angles ``(yaw, pitch, roll)`` (rad), the order of the input vector ``x``.

    Returns:
        The (3, 3) rotation ``R_WB`` (body FRD to world, z down).
    """
    euler = jnp.asarray(euler)
    cy, sy = jnp.cos(euler[0]), jnp.sin(euler[0])
    cp, sp = jnp.cos(euler[1]), jnp.sin(euler[1])
    cr, sr = jnp.cos(euler[2]), jnp.sin(euler[2])
    return jnp.stack(
        [
            jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr]),
            jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr]),
            jnp.stack([-sp, cp * sr, cp * cr]),
        ]
    )


def safe_atan2(
    y: Float[ArrayLike, ""], x: Float[ArrayLike, ""], tiny: float = 0.0
) -> Float[Array, ""]:
    """``atan2(y, x)``, but 0 with a zero gradient where ``|x|, |y| <= tiny`` instead of NaN.

    Both branches of the ``where`` are kept finite (the origin is replaced by ``(1, 0)`` before
    ``arctan2``), so the gradient of the unused branch cannot poison the result with NaN.

    Args:
        y: the ordinate.
        x: the abscissa.
        tiny: the half-width of the square around the origin that gives 0.

    Returns:
        The angle (rad) in ``(−π, π]``, 0 near the origin.
    """
    at_origin = (jnp.abs(x) <= tiny) & (jnp.abs(y) <= tiny)
    xs = jnp.where(at_origin, 1.0, x)
    ys = jnp.where(at_origin, 0.0, y)
    return jnp.where(at_origin, 0.0, jnp.arctan2(ys, xs))


def safe_norm(v: Float[ArrayLike, "*n"]) -> Float[Array, ""]:
    """Euclidean norm with a zero (not NaN) gradient at ``v = 0``."""
    v = jnp.asarray(v)
    sq = jnp.sum(v * v)
    zero = sq <= 0.0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))


def half_turn(
    rpm: Float[ArrayLike, "4"], euler: Float[ArrayLike, "3"]
) -> tuple[Float[Array, "4"], Float[Array, "3"]]:
    """The same vehicle state described with the body frame turned half a turn about its z
    axis and the rotors relabelled: ``R_WB Rz(π)`` and ``r1 ↔ r3``, ``r2 ↔ r4``.

    For a vehicle whose diagonal hubs are each other's image under the half turn and spin the
    same way, both descriptions are one physical state: the world-frame loads are equal. With
    ``R_WB = Rz(ψ) Ry(θ) Rx(φ)``, ``R_WB Rz(π) = Rz(ψ + π) Ry(−θ) Rx(−φ)``, so the angles are
    ``(ψ + π, −θ, −φ)`` (yaw not wrapped: every use of it is periodic).

    Args:
        rpm: (4,) rotor speeds r1..r4.
        euler: (3,) attitude ``(yaw, pitch, roll)`` (rad).

    Returns:
        The rotor speeds relabelled and the angles of the turned body frame.
    """
    rpm, euler = jnp.asarray(rpm), jnp.asarray(euler)
    return rpm[jnp.array(HALF_TURN_ROTORS)], jnp.stack([euler[0] + jnp.pi, -euler[1], -euler[2]])


def euler_from_R(R: Float[ArrayLike, "3 3"]) -> Float[Array, "3"]:
    """The Euler angles of a rotation, the inverse of :func:`R_WB`; pitch in [−π/2, π/2].

    Pitch comes from ``atan2(−R31, ‖(R11, R21)‖)``, which stays accurate near ±90° where
    ``asin`` loses half its digits. At gimbal lock (``cos pitch = 0``) yaw and roll are not
    separable; roll is then set to zero and yaw read from the second column.

    Args:
        R: a (3, 3) rotation matrix (body to world).

    Returns:
        The (3,) angles ``(yaw, pitch, roll)`` (rad) with ``R_WB(euler) = R``.
    """
    R = jnp.asarray(R)
    cp = jnp.hypot(R[0, 0], R[1, 0])
    pitch = safe_atan2(-R[2, 0], cp)
    locked = cp < 1e-12
    yaw_free = safe_atan2(R[1, 0], R[0, 0])
    roll_free = safe_atan2(R[2, 1], R[2, 2])
    yaw_locked = safe_atan2(-R[0, 1], R[1, 1])
    yaw = jnp.where(locked, yaw_locked, yaw_free)
    roll = jnp.where(locked, 0.0, roll_free)
    return jnp.stack([yaw, pitch, roll])


def R_WH(v_air: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    """Airflow frame: a proper rotation with ``R_WH @ e_x = v̂_air`` (wind axes).

    ``R_WH = Rz(χ) Ry(γ)`` with heading ``χ`` and climb angle ``γ`` of ``v_air`` (module
    docstring): not the paper's Householder reflection. The heading is zero where both
    horizontal components are within :data:`TINY_SPEED` of zero (vertical airflow), the climb
    where the vertical and the horizontal speed both are, so ``v = 0`` gives the identity.

    Args:
        v_air: (3,) airspeed ``v_vehicle − v_wind`` in the world frame (m/s).

    Returns:
        The (3, 3) rotation ``R_WH`` (airflow frame to world).
    """
    v = jnp.asarray(v_air)
    heading = safe_atan2(v[1], v[0], TINY_SPEED)
    climb = safe_atan2(-v[2], safe_norm(v[:2]), TINY_SPEED)
    return R_WB(jnp.stack([heading, climb, jnp.zeros_like(climb)]))  # Rz(χ) Ry(γ)


def airflow_direction(
    v_air_W: Float[ArrayLike, "3"], yaw: Float[ArrayLike, ""], hover_speed: float
) -> Float[Array, "3"]:
    """The vector whose direction ``H`` takes as its x axis.

    ``v_air`` itself above ``hover_speed``, blended toward the body's horizontal heading below
    it. At zero airspeed the aerodynamic wrench does not depend on the direction of ``H`` at all,
    so any choice is exact there; but wind axes alone then pick a heading of zero (or whatever
    direction a few mm/s of drift point), which puts a hovering vehicle with a yaw beyond ±90°,
    or a tilted one, outside the training box for no physical reason. Adding
    ``c = h (1 − ‖v‖²/h²)²₊`` along the heading makes ``ψ_H → 0`` and ``γ → 0`` in hover;
    ``c`` and its gradient vanish at ``‖v‖ = h``, so above that the frame is exactly wind
    axes, and the result commutes with rotations about the world z axis like :func:`R_WH`.

    Args:
        v_air_W: (3,) airspeed in the world frame (m/s).
        yaw: the body's heading (rad).
        hover_speed: the blend's speed ``h`` (m/s, static); 0 or less returns ``v_air_W``.

    Returns:
        The (3,) direction vector (m/s, not normalised).
    """
    v = jnp.asarray(v_air_W)
    if hover_speed <= 0.0:
        return v
    h = float(hover_speed)
    c = h * jnp.maximum(1.0 - jnp.sum(v * v) / h**2, 0.0) ** 2
    return v + c * jnp.stack([jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw)])


def airflow_frame(
    v_air_W: Float[ArrayLike, "3"], yaw: Float[ArrayLike, ""], hover_speed: float
) -> Float[Array, "3 3"]:
    """``R_WH`` of the airflow frame, continuous wherever it can be (see below).

    ``x_H`` is the direction of :func:`airflow_direction` (``v̂_air`` above ``hover_speed``). Wind
    axes then fix ``y_H`` horizontal and perpendicular to the airflow's horizontal part, which
    is undefined when the airflow is vertical (climbs, descents): its heading jumps with the
    sideways millimetres per second. Here ``y_H`` is the wind axes' ``z_W × d`` plus
    ``c (−sin ψ, cos ψ, 0)``, the body's own right, with ``c = h (1 − ‖d_xy‖²/h²)²₊``, projected
    perpendicular to ``x_H`` and normalised. ``c`` and its gradient vanish at ``‖d_xy‖ = h``,
    so above that horizontal speed the frame is exactly wind axes; as the horizontal airspeed
    vanishes the frame's heading turns to the body's, continuously and differentiably.

    Singular set (no continuous frame of a direction exists everywhere, by the hairy-ball
    theorem): ``y_H`` vanishes for airflow from the rear half of the body (``|χ − ψ| > 90°``)
    at the one horizontal speed where the two terms cancel (about ``0.55 h`` directly from
    behind, at any climb angle; horizontal airflow only, elsewhere in the rear half). With the
    paper's yaw range (±90°) most of those states are out of the training domain, but not
    all: in a steep climb or descent from behind the roll relative to ``H`` can bring them
    back inside, so a surrogate also asks :func:`airflow_frame_rate` before it calls a
    query in domain.

    Args:
        v_air_W: (3,) airspeed in the world frame (m/s).
        yaw: the body's heading (rad).
        hover_speed: the blend's speed ``h`` (m/s, static); 0 or less gives pure wind axes,
            :func:`R_WH`.

    Returns:
        The (3, 3) rotation ``R_WH`` (airflow frame to world).
    """
    v = jnp.asarray(v_air_W)
    if hover_speed <= 0.0:
        return R_WH(v)
    h = float(hover_speed)
    d = airflow_direction(v, yaw, hover_speed)
    dxy2 = d[0] * d[0] + d[1] * d[1]
    wind_axes = R_WH(d)
    x = d / jnp.where(jnp.sum(d * d) > 0, safe_norm(d), 1.0)
    c = h * jnp.maximum(1.0 - dxy2 / h**2, 0.0) ** 2
    zero = jnp.zeros_like(d[0])
    y_ref = jnp.stack([-d[1], d[0], zero]) + c * jnp.stack([-jnp.sin(yaw), jnp.cos(yaw), zero])
    y = y_ref - jnp.sum(y_ref * x) * x
    y = y / jnp.where(jnp.sum(y * y) > 0, safe_norm(y), 1.0)
    blended = jnp.stack([x, y, jnp.cross(x, y)], axis=1)
    # Where the blend weight is zero the frame is wind axes: the same bits as R_WH.
    return jnp.where(dxy2 >= h**2, wind_axes, blended)


def to_airflow_frame(
    euler_W: Float[ArrayLike, "3"], v_air_W: Float[ArrayLike, "3"], hover_speed: float = 0.0
) -> tuple[Float[Array, "3"], Float[Array, ""], Float[Array, "3 3"]]:
    """Attitude in the airflow frame and airspeed: ``(euler_H, ‖v‖, R_WH)``.

    ``R_HB = R_WHᵀ R_WB`` (paper, Section "Real-time Simulation"); ``euler_H`` are its
    ``(yaw, pitch, roll)``, the angles a dataset case with the same relative airflow would have.
    ``hover_speed > 0`` (m/s, static) turns ``H`` toward the body heading at low airspeed and
    at low horizontal airspeed (vertical airflow), see :func:`airflow_direction` and
    :func:`airflow_frame`; 0 gives pure wind axes.

    Args:
        euler_W: (3,) attitude ``(yaw, pitch, roll)`` in the world frame (rad).
        v_air_W: (3,) airspeed in the world frame (m/s).
        hover_speed: the hover blend's speed (m/s, static); 0: pure wind axes.

    Returns:
        ``euler_H`` (3,), the attitude relative to ``H``; the airspeed ``‖v_air‖`` (m/s, with
        a zero gradient at rest); and ``R_WH`` (3, 3).
    """
    euler_W = jnp.asarray(euler_W)
    rwh = airflow_frame(v_air_W, euler_W[0], hover_speed)
    r_hb = matmul(rwh.T, R_WB(euler_W))
    return euler_from_R(r_hb), safe_norm(v_air_W), rwh


def airflow_frame_rate(
    euler_W: Float[ArrayLike, "3"], v_air_W: Float[ArrayLike, "3"], hover_speed: float = 0.0
) -> Float[Array, ""]:
    """How fast the query's airflow-frame coordinates turn with the air velocity, in rad per
    m/s: the larger of ``‖∂euler_H/∂v_air‖_F`` and ``‖∂R_WH/∂v_air‖_F / √2`` (the derivatives
    of :func:`to_airflow_frame`, in closed form; no gradient flows back through it).

    Away from the frame's singular sets it is about ``1/‖v_air‖`` (``1/hover_speed`` in the
    hover blend); it grows without bound near them (vertical airflow with pure wind axes, the
    rear-airflow ring of :func:`airflow_frame`, the Euler angles' gimbal lock). There a
    millimetre per second of air turns ``H``, and with it the prediction, by a finite amount:
    a surrogate is out of domain where this exceeds :data:`gpg.surrogate.MAX_FRAME_RATE`.
    Where the frame or the angles are not differentiable at all (no horizontal airspeed with
    pure wind axes, a vanishing axis of the blend, ``cos pitch_H = 0``) it is ``inf``.

    Written out rather than taken by ``jax.jacfwd`` because every prediction evaluates it: the
    forward-mode program of the whole frame was over half of a surrogate's compiled
    prediction. ``H``'s turn per unit of ``v_j`` is an angular velocity ``w_j`` (in ``H``,
    ``∂R_WH/∂v_j = R_WH [w_j]×``, so ``‖∂R_WH/∂v_j‖_F = √2 ‖w_j‖``), read off the axes'
    derivatives; ``R_HB = R_WHᵀ R_WB`` turns at ``−w_j``, and the Euler angles' rates follow
    from it by the ZYX kinematics.

    Args:
        euler_W: (3,) attitude ``(yaw, pitch, roll)`` in the world frame (rad).
        v_air_W: (3,) airspeed in the world frame (m/s).
        hover_speed: the hover blend's speed (m/s, static), as in :func:`to_airflow_frame`.

    Returns:
        The rate (rad per m/s, a scalar, ``inf`` where the frame is not differentiable).
    """
    v = jnp.asarray(v_air_W)
    v = jax.lax.stop_gradient(v.astype(jnp.result_type(v, float)))
    euler_W = jax.lax.stop_gradient(jnp.asarray(euler_W).astype(v.dtype))
    d, J_d, y_ref, J_y = _blend_derivatives(v, euler_W[0], hover_speed)
    dd = jnp.sum(d * d)
    bad = dd <= 0.0
    norm_d = jnp.sqrt(jnp.where(bad, 1.0, dd))
    x = d / norm_d
    J_x = (J_d - x[:, None] * _vm(x, J_d)[None, :]) / norm_d
    y_perp = y_ref - jnp.sum(y_ref * x) * x
    yy = jnp.sum(y_perp * y_perp)
    bad = bad | (yy <= 0.0)
    norm_y = jnp.sqrt(jnp.where(bad, 1.0, yy))
    y = y_perp / norm_y
    z = jnp.cross(x, y)
    # w_j in H: (z·∂y, −z·∂x, y·∂x); z·∂y = (z·∂y_ref − (y_ref·x) z·∂x) / ‖y_perp‖ as z ⊥ x, y
    zx = _vm(z, J_x)
    w = jnp.stack([(_vm(z, J_y) - jnp.sum(y_ref * x) * zx) / norm_y, -zx, _vm(y, J_x)])
    frame_rate = jnp.sqrt(jnp.sum(w * w))
    # R_HB's first column (yaw and pitch of H's angles) without the angles themselves, from
    # R_WB's first column (R_WB's own products, only the three that column needs)
    cp = jnp.cos(euler_W[1])
    b = jnp.stack([jnp.cos(euler_W[0]) * cp, jnp.sin(euler_W[0]) * cp, -jnp.sin(euler_W[1])])
    r0 = jnp.stack([jnp.sum(x * b), jnp.sum(y * b), jnp.sum(z * b)])
    cp2 = r0[0] * r0[0] + r0[1] * r0[1]  # cos² pitch_H
    locked = cp2 <= 0.0
    cp2 = jnp.where(locked, 1.0, cp2)
    om = -w  # R_HB's angular velocity per unit v_j, in H
    roll = (om[0] * r0[0] + om[1] * r0[1]) / cp2
    pitch = (om[1] * r0[0] - om[0] * r0[1]) / jnp.sqrt(cp2)
    yaw = om[2] - roll * r0[2]  # + roll · sin pitch_H, sin pitch_H = −R_HB[2, 0]
    euler_rate = jnp.sqrt(jnp.sum(roll * roll + pitch * pitch + yaw * yaw))
    rate = jnp.where(bad | locked, jnp.inf, jnp.maximum(euler_rate, frame_rate))
    if hover_speed <= 0.0:
        rate = jnp.where(v[0] ** 2 + v[1] ** 2 <= TINY_SPEED**2, jnp.inf, rate)
    return rate


def _vm(u: Array, J: Array) -> Array:
    """``uᵀ J`` as a broadcast multiply-add (fusible, see :func:`matvec`)."""
    return jnp.sum(u[:, None] * J, axis=0)


def _turn(a: Array) -> Array:
    """``z_W × a`` for a vector, or for each column of a (3, 3) matrix: ``(−a_y, a_x, 0)``."""
    return jnp.stack([-a[1], a[0], jnp.zeros_like(a[0])])


def _blend_derivatives(v: Array, yaw: Array, hover_speed: float):
    """:func:`airflow_frame`'s direction ``d`` and unnormalised ``y_ref`` with their
    Jacobians in ``v`` (both blends' weights ``h (1 − s²/h²)²₊`` differentiated by hand)."""
    eye = jnp.eye(3, dtype=v.dtype)
    if hover_speed <= 0.0:
        return v, eye, _turn(v), _turn(eye)
    h = float(hover_speed)
    zero = jnp.zeros_like(yaw)
    nose = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), zero])
    right = jnp.stack([-jnp.sin(yaw), jnp.cos(yaw), zero])
    s = jnp.maximum(1.0 - jnp.sum(v * v) / h**2, 0.0)
    d = v + h * s * s * nose
    J_d = eye + nose[:, None] * (-4.0 * s / h * v)[None, :]
    s2 = jnp.maximum(1.0 - (d[0] * d[0] + d[1] * d[1]) / h**2, 0.0)
    y_ref = _turn(d) + h * s2 * s2 * right
    dc2 = -4.0 * s2 / h * (d[0] * J_d[0] + d[1] * J_d[1])
    return d, J_d, y_ref, _turn(J_d) + right[:, None] * dc2[None, :]
