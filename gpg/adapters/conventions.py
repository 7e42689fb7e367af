"""The one boundary between gpg's conventions and those of the simulators users fly.

gpg: world NED-like (x forward, y right, z down), body FRD, quaternions scalar first
``(w, x, y, z)``, rotor speeds in rpm, airspeed ``v_air = v_vehicle − v_wind``.

RotorPy, Crazyflow and gym-pybullet-drones: world z up, body FLU (x forward, y left, z up),
quaternions scalar last ``[x, y, z, w]``, rotor speeds in rad/s (RotorPy) or rpm (Crazyflow,
gym-pybullet-drones).

The two world frames (and the two body frames) differ by the rotation ``F = diag(1, −1, −1)``,
a half turn about x (a proper rotation, so no handedness changes): a vector is ``F v`` in the
other convention, an attitude ``F R F``, and a quaternion ``q_F ⊗ q ⊗ q_F⁻¹`` with
``q_F = (0, 1, 0, 0)``, i.e. ``(w, x, y, z) ↦ (w, x, −y, −z)``. Every function is its own
inverse up to the quaternion order, is pure JAX (jit, vmap, grad) and accepts NumPy.

Rotor order and spin: gpg numbers r1 rear-right, r2 rear-left, r3 front-left, r4 front-right
(FRD positions); a rotor with gpg spin ``+1`` turns about ``+z_FRD`` (clockwise seen from above)
and its drag torque points up, which RotorPy writes as ``rotor_directions = +1``. Positions
convert like any body vector.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from gpg.quadrotor.dynamics import quat_to_R
from gpg.quadrotor.frames import euler_from_R, matvec
from gpg.surrogate import Surrogate, predict_state

__all__ = [
    "ZUp",
    "ZUpWrench",
    "flip",
    "flip_rotation",
    "quat_from_zup",
    "quat_to_zup",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "rad_s_to_rpm",
    "rotation_from_zup_quat",
    "rpm_to_rad_s",
]

FLIP = jnp.array([1.0, -1.0, -1.0])  # diag(F): z down <-> z up, FRD <-> FLU
RAD_S_PER_RPM = 2.0 * math.pi / 60.0


def flip(v: Float[ArrayLike, "*B 3"]) -> Float[Array, "*B 3"]:
    """A vector (world or body) from z down to z up or back: ``F v``.

    Args:
        v: (..., 3) vectors in either convention (world NED or z up, body FRD or FLU).

    Returns:
        The vectors in the other convention: ``(x, −y, −z)``.
    """
    return jnp.asarray(v) * FLIP.astype(jnp.result_type(float, v))


def flip_rotation(R: Float[ArrayLike, "*B 3 3"]) -> Float[Array, "*B 3 3"]:
    """An attitude matrix (body to world) from one convention to the other: ``F R F``.

    Args:
        R: (..., 3, 3) rotation matrices, body to world, in either convention.

    Returns:
        The rotation matrices in the other convention.
    """
    R = jnp.asarray(R)
    f = FLIP.astype(R.dtype)
    return R * f[:, None] * f[None, :]


def quat_wxyz_to_xyzw(q: Float[ArrayLike, "*B 4"]) -> Float[Array, "*B 4"]:
    """Reorder a quaternion, scalar first to scalar last (same rotation).

    Args:
        q: (..., 4) quaternions ``(w, x, y, z)``.

    Returns:
        The same quaternions as ``[x, y, z, w]``.
    """
    q = jnp.asarray(q)
    return jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(q: Float[ArrayLike, "*B 4"]) -> Float[Array, "*B 4"]:
    """Reorder a quaternion, scalar last to scalar first (same rotation).

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``.

    Returns:
        The same quaternions as ``(w, x, y, z)``.
    """
    q = jnp.asarray(q)
    return jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_to_zup(q_wxyz: Float[ArrayLike, "*B 4"]) -> Float[Array, "*B 4"]:
    """gpg's attitude quaternion as the z-up convention's, reordered scalar last.

    The frame change ``q_F ⊗ q ⊗ q_F⁻¹`` negates ``y`` and ``z``.

    Args:
        q_wxyz: (..., 4) gpg's attitude ``(w, x, y, z)``, FRD body to NED world.

    Returns:
        The attitude ``[x, y, z, w]``, FLU body to z-up world.
    """
    q = jnp.asarray(q_wxyz)
    return jnp.stack([q[..., 1], -q[..., 2], -q[..., 3], q[..., 0]], axis=-1)


def quat_from_zup(q_xyzw: Float[ArrayLike, "*B 4"]) -> Float[Array, "*B 4"]:
    """The z-up convention's attitude quaternion as gpg's: :func:`quat_to_zup`'s inverse.

    Args:
        q_xyzw: (..., 4) the attitude ``[x, y, z, w]``, FLU body to z-up world.

    Returns:
        gpg's attitude ``(w, x, y, z)``, FRD body to NED world.
    """
    q = jnp.asarray(q_xyzw)
    return jnp.stack([q[..., 3], q[..., 0], -q[..., 1], -q[..., 2]], axis=-1)


def rpm_to_rad_s(rpm: Float[ArrayLike, "*B"]) -> Float[Array, "*B"]:
    """Rotor speeds from rpm (gpg, Crazyflow, gym-pybullet-drones) to rad/s (RotorPy).

    Args:
        rpm: rotor speeds (rpm), any shape.

    Returns:
        The same speeds in rad/s.
    """
    return jnp.asarray(rpm) * RAD_S_PER_RPM


def rad_s_to_rpm(w: Float[ArrayLike, "*B"]) -> Float[Array, "*B"]:
    """Rotor speeds from rad/s (RotorPy) to rpm (gpg): :func:`rpm_to_rad_s`'s inverse.

    Args:
        w: rotor speeds (rad/s), any shape.

    Returns:
        The same speeds in rpm.
    """
    return jnp.asarray(w) / RAD_S_PER_RPM


def rotation_from_zup_quat(q_xyzw: Float[ArrayLike, " 4"]) -> Float[Array, "3 3"]:
    """gpg's attitude matrix ``R_WB`` (FRD to NED) from a z-up simulator's quaternion.

    Args:
        q_xyzw: (4,) the attitude ``[x, y, z, w]``, FLU body to z-up world; normalised here,
            so a simulator's slightly denormalised quaternion is accepted.

    Returns:
        The (3, 3) rotation matrix ``R_WB`` in gpg's frames.
    """
    q = quat_from_zup(q_xyzw)
    return quat_to_R(q / jnp.linalg.norm(q))


class ZUpWrench(eqx.Module):
    """An aerodynamic wrench in a z-up simulator's frames: world (``force_world``,
    ``torque_world``) and body FLU (``force_body``, ``torque_body``), with the surrogate's
    predictive variances of the body components (None for the mean alone or for ``M``) and
    ``in_domain``."""

    force_world: Float[Array, " 3"]
    torque_world: Float[Array, " 3"]
    force_body: Float[Array, " 3"]
    torque_body: Float[Array, " 3"]
    variance_body: Float[Array, " 6"] | None
    in_domain: Bool[Array, ""]


class ZUp(eqx.Module):
    """gpg's aerodynamics for a z-up simulator (RotorPy, Crazyflow, gym-pybullet-drones).

    ``aero`` is a :class:`gpg.Surrogate` (mean and variance) or any
    :class:`gpg.quadrotor.dynamics.AeroModel` (e.g. ``SimpleAero(M)``, mean only).
    ``rad_s`` says whether the simulator's rotor speeds are in rad/s (RotorPy) or rpm
    (Crazyflow, gym-pybullet-drones); ``with_var`` whether a surrogate's predictive variance
    is computed too. Call :meth:`wrench` with the simulator's own state; the
    result is in its frames: Crazyflow takes ``force_world``/``torque_world`` as its external
    wrench, gym-pybullet-drones ``applyExternalForce``/``applyExternalTorque`` with
    ``WORLD_FRAME`` (or the body components with ``LINK_FRAME``), RotorPy the body ones.
    """

    aero: eqx.Module
    rad_s: bool = eqx.field(static=True, default=False)
    with_var: bool = eqx.field(static=True, default=True)

    def wrench(
        self,
        rotor_speeds: Float[ArrayLike, " 4"],
        q_xyzw: Float[ArrayLike, " 4"],
        v_world: Float[ArrayLike, " 3"],
        wind_world: Float[ArrayLike, " 3"] | None = None,
        body_rates: Float[ArrayLike, " 3"] | None = None,
    ) -> ZUpWrench:
        """The aerodynamic wrench for a z-up simulator's state, in that simulator's frames.

        The state is converted to gpg's frames, the surrogate (body-frame prediction) or the
        ``AeroModel`` evaluated at airspeed ``v − wind``, and the wrench converted back.

        Args:
            rotor_speeds: (4,) rotor speeds, rad/s or rpm as ``rad_s`` says, in the
                simulator's rotor order (which is gpg's r1..r4).
            q_xyzw: (4,) the attitude ``[x, y, z, w]``, FLU body to z-up world.
            v_world: (3,) the vehicle's velocity (z-up world, m/s).
            wind_world: (3,) the wind (z-up world, m/s); None for calm air.
            body_rates: (3,) body rates (FLU, rad/s); only an ``AeroModel`` reads them; None
                for zero.

        Returns:
            The wrench in world and body (FLU) components, the surrogate's body variances
            (with ``with_var``; None for an ``AeroModel``) and ``in_domain``.
        """
        w = jnp.asarray(rotor_speeds)
        rpm = rad_s_to_rpm(w) if self.rad_s else w
        R = rotation_from_zup_quat(q_xyzw)  # gpg R_WB
        v_air = flip(jnp.asarray(v_world) - (0.0 if wind_world is None else wind_world))
        omega = jnp.zeros(3) if body_rates is None else flip(body_rates)
        if isinstance(self.aero, Surrogate):
            p = predict_state(self.aero, rpm, euler_from_R(R), v_air, self.with_var, body=True)
            f_b, t_b, ok = p.force, p.torque, p.in_domain
            var = None if p.variance is None else p.variance[:6]
        else:
            wr = self.aero.wrench(rpm, R, v_air, omega)
            f_b, t_b, ok, var = matvec(R.T, wr.force), matvec(R.T, wr.torque), wr.in_domain, None
        return ZUpWrench(
            force_world=flip(matvec(R, f_b)),
            torque_world=flip(matvec(R, t_b)),
            force_body=flip(f_b),
            torque_body=flip(t_b),
            variance_body=var,  # a variance is unchanged by a sign flip of its axis
            in_domain=ok,
        )
