"""Geometric SE(3) tracking control (Lee, Leok & McClamroch 2010; Mellinger & Kumar 2011).

Frames as everywhere in gpg: world z down, body FRD, thrust along ``−z_B``. From position and
velocity errors the controller forms the force the rotors should produce,
``F = m(a_d − g e_z) − K_p e_p − K_v e_v``; the desired body z axis is ``−F/‖F‖``, the desired
heading fixes the rest of ``R_d``; the collective thrust is ``F`` projected on the current
``−z_B``; the moment is ``−K_R e_R − K_ω e_ω + ω × Jω`` with ``e_R = ½ vee(R_dᵀR − RᵀR_d)``.
Thrust and moment go to rotor speeds through the inverse of the simplified model's allocation
matrix (derived from the rotor geometry), clipped to the motor range. The controller knows only
the simplified model, as in the paper: against the GP surrogate it meets drag and rotor
aerodynamics it was not designed for.

Reference trajectories are minimum-jerk polynomials between waypoints (:class:`WaypointPlan`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg._precision import highest
from gpg.quadrotor.dynamics import State
from gpg.quadrotor.frames import matmul, matvec
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle

__all__ = ["GeometricController", "Reference", "WaypointPlan", "vee"]


class Reference(eqx.Module):
    """Desired position, velocity, acceleration (world) and yaw."""

    p: Float[Array, " 3"]
    v: Float[Array, " 3"]
    a: Float[Array, " 3"]
    yaw: Float[Array, ""]


class WaypointPlan(eqx.Module):
    """Minimum-jerk legs between consecutive waypoints, each lasting ``leg_time`` seconds,
    starting at ``start_time``; before the first leg and after the last the reference holds.

    ``yaw`` holds one heading per leg (rad); the reference turns from the previous heading
    (``yaw0`` before the first leg) to the leg's along the shorter way, with a minimum-jerk
    profile over the first ``turn_fraction`` of the leg.
    """

    waypoints: Float[Array, "W 3"]
    start_time: Float[Array, ""]
    leg_time: Float[Array, ""]
    yaw: Float[Array, " L"]
    yaw0: Float[Array, ""]
    turn_fraction: float = eqx.field(static=True, default=0.4)

    @classmethod
    def create(
        cls,
        waypoints: ArrayLike,
        *,
        start_time: float = 1.0,
        leg_time: float = 4.0,
        yaw: float | str = "travel",
        yaw0: float = 0.0,
    ) -> WaypointPlan:
        """A plan through ``waypoints`` from plain numbers (checked).

        ``yaw="travel"`` points the nose along each leg, so the airflow meets the vehicle from
        the front as in the dataset; a number holds one heading throughout.

        Args:
            waypoints: (W, 3) positions in the world frame (m, z down), ``W >= 2``.
            start_time: when the first leg starts (s); the reference holds the first waypoint
                before it.
            leg_time: the duration of every leg (s, > 0).
            yaw: ``"travel"`` (each leg's heading along its direction) or one heading (rad).
            yaw0: the heading before the first leg (rad).

        Returns:
            The plan, with one heading per leg.

        Raises:
            ValueError: if ``waypoints`` is not (W >= 2, 3), ``leg_time`` is not positive, or
                ``yaw`` is a string other than ``"travel"``.
        """
        w = np.asarray(waypoints, dtype=float)
        if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2:
            raise ValueError(f"waypoints must be (W >= 2, 3), got {w.shape}")
        if not leg_time > 0:
            raise ValueError(f"leg_time must be > 0, got {leg_time}")
        d = np.diff(w, axis=0)
        if isinstance(yaw, str):
            if yaw != "travel":
                raise ValueError(f"yaw must be a number or 'travel', got {yaw!r}")
            yaws = np.arctan2(d[:, 1], d[:, 0])
        else:
            yaws = np.full(len(d), float(yaw))
        return cls(
            waypoints=jnp.asarray(w),
            start_time=jnp.asarray(float(start_time)),
            leg_time=jnp.asarray(float(leg_time)),
            yaw=jnp.asarray(yaws),
            yaw0=jnp.asarray(float(yaw0)),
        )

    @property
    def end_time(self) -> Float[Array, ""]:
        return self.start_time + (self.waypoints.shape[0] - 1) * self.leg_time

    def __call__(self, t: Float[Array, ""]) -> Reference:
        n_legs = self.waypoints.shape[0] - 1
        tau = (t - self.start_time) / self.leg_time
        leg = jnp.clip(jnp.floor(tau), 0, n_legs - 1).astype(int)
        s = jnp.clip(tau - leg, 0.0, 1.0)
        s = jnp.where(tau < 0, 0.0, s)
        p0, p1 = self.waypoints[leg], self.waypoints[leg + 1]
        d = p1 - p0
        # Minimum jerk: 10s³ − 15s⁴ + 6s⁵ and its derivatives (per unit leg time).
        pos = 10 * s**3 - 15 * s**4 + 6 * s**5
        vel = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.leg_time
        acc = (60 * s - 180 * s**2 + 120 * s**3) / self.leg_time**2
        moving = (tau > 0) & (tau < n_legs)
        prev = jnp.where(leg == 0, self.yaw0, self.yaw[jnp.maximum(leg - 1, 0)])
        turn = jnp.angle(jnp.exp(1j * (self.yaw[leg] - prev)))  # shorter way, in (-π, π]
        u = jnp.clip(s / self.turn_fraction, 0.0, 1.0)
        yaw = prev + turn * (10 * u**3 - 15 * u**4 + 6 * u**5)
        return Reference(
            p=p0 + pos * d,
            v=jnp.where(moving, vel, 0.0) * d,
            a=jnp.where(moving, acc, 0.0) * d,
            yaw=yaw,
        )


def vee(S: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """The vector of a skew-symmetric matrix, the inverse of the hat map: ``S = [s]×``.

    Only the entries below and above the diagonal that ``[s]×`` fills are read,
    ``(S₃₂, S₁₃, S₂₁)``; a matrix that is not skew-symmetric is not checked.

    Args:
        S: a (3, 3) skew-symmetric matrix, such as ``R_dᵀR − RᵀR_d``.

    Returns:
        The (3,) vector ``s`` with ``S v = s × v``.
    """
    return jnp.stack([S[2, 1], S[0, 2], S[1, 0]])


class GeometricController(eqx.Module):
    """Gains are diagonal (x, y, z components); see the module docstring for the law."""

    kp: Float[Array, " 3"]
    kv: Float[Array, " 3"]
    kR: Float[Array, " 3"]
    kw: Float[Array, " 3"]
    mass: Float[Array, ""]
    inertia: Float[Array, " 3"]
    gravity: Float[Array, ""]
    alloc_inv: Float[Array, "4 4"]
    rpm_min: Float[Array, ""]
    rpm_max: Float[Array, ""]
    max_tilt: Float[Array, ""]

    @classmethod
    def create(
        cls, vehicle: Vehicle, simple: SimpleModel, gains: Mapping[str, Any] | None = None
    ) -> GeometricController:
        """The controller of ``vehicle`` with gains from natural frequencies and damping.

        ``K_p = m ω_p²``, ``K_v = 2 ζ m ω_p``, and per axis ``K_R = J ω_R²``,
        ``K_ω = 2 ζ J ω_R`` (defaults tuned for the SUI-like vehicle). The allocation it
        inverts is ``simple``'s: the controller knows only ``M``.

        Args:
            vehicle: mass, inertia, gravity and the motor range.
            simple: the simplified model whose allocation matrix maps rotor speeds² to thrust
                and moment.
            gains: overrides of ``position_hz`` (ω_p/2π per axis), ``attitude_hz`` (ω_R/2π per
                axis), ``damping`` (ζ) and ``max_tilt_deg`` (the tilt limit of the position
                loop); None keeps the defaults.

        Returns:
            The controller, its gains as arrays.

        Raises:
            ValueError: if ``gains`` has a key other than the four above.
        """
        g = {
            "position_hz": [0.35, 0.35, 0.45],
            "attitude_hz": [2.5, 2.5, 1.2],
            "damping": 0.9,
            "max_tilt_deg": 50.0,
            **dict(gains or {}),
        }
        unknown = sorted(set(g) - {"position_hz", "attitude_hz", "damping", "max_tilt_deg"})
        if unknown:
            raise ValueError(f"unknown controller gains {unknown}")
        m, J = vehicle.mass, vehicle.inertia
        wp = 2 * np.pi * np.asarray(g["position_hz"], dtype=float)
        wa = 2 * np.pi * np.asarray(g["attitude_hz"], dtype=float)
        z = float(g["damping"])
        A = np.asarray(simple.allocation)
        return cls(
            kp=jnp.asarray(m * wp**2),
            kv=jnp.asarray(2 * z * m * wp),
            kR=jnp.asarray(J * wa**2),
            kw=jnp.asarray(2 * z * J * wa),
            mass=m,
            inertia=J,
            gravity=vehicle.gravity,
            alloc_inv=jnp.asarray(np.linalg.inv(A)),
            rpm_min=vehicle.rpm_min,
            rpm_max=vehicle.rpm_max,
            max_tilt=jnp.asarray(np.deg2rad(float(g["max_tilt_deg"]))),
        )

    def __call__(self, s: State, ref: Reference) -> Float[Array, " 4"]:
        """Rotor speed commands (rpm)."""
        thrust, R_d = self.thrust_and_attitude(s, ref)
        R = s.R
        e_R = 0.5 * vee(matmul(R_d.T, R) - matmul(R.T, R_d))
        e_w = s.w  # the references here have no angular rate
        tau = -self.kR * e_R - self.kw * e_w + jnp.cross(s.w, self.inertia * s.w)
        return self.mix(thrust[0], tau)

    @highest
    def thrust_and_attitude(
        self, s: State, ref: Reference
    ) -> tuple[Float[Array, " 1"], Float[Array, "3 3"]]:
        """The position loop: collective thrust and desired attitude ``R_d``.

        ``F = m(a_d − g e_z) − K_p e_p − K_v e_v`` with its horizontal part shrunk to the tilt
        limit (and at least a fifth of the weight upward); ``R_d`` has ``z_d = −F/‖F‖`` and
        the reference heading; the thrust is ``F`` projected on the current ``−z_B``.

        Args:
            s: the current state.
            ref: the desired position, velocity, acceleration and yaw.

        Returns:
            The collective thrust (N, ≥ 0, shape (1,)) and ``R_d`` (3, 3), body to world.
        """
        R = s.R
        e_p, e_v = s.p - ref.p, s.v - ref.v
        F = self.mass * ref.a.at[2].add(-self.gravity) - self.kp * e_p - self.kv * e_v
        # Limit the tilt: keep the upward component, shrink the horizontal one if needed.
        up = jnp.minimum(F[2], -0.2 * self.mass * self.gravity)
        horiz = F[:2]
        h_max = -up * jnp.tan(self.max_tilt)
        h_norm = jnp.sqrt(jnp.sum(horiz**2) + 1e-12)
        horiz = horiz * jnp.minimum(1.0, h_max / h_norm)
        F = jnp.concatenate([horiz, up[None]])
        z_b = -F / jnp.linalg.norm(F)
        x_c = jnp.stack([jnp.cos(ref.yaw), jnp.sin(ref.yaw), jnp.zeros_like(ref.yaw)])
        y_b = jnp.cross(z_b, x_c)
        y_b = y_b / jnp.linalg.norm(y_b)
        x_b = jnp.cross(y_b, z_b)
        R_d = jnp.stack([x_b, y_b, z_b], axis=1)
        thrust = -jnp.dot(F, R[:, 2])
        return jnp.maximum(thrust, 0.0)[None], R_d

    def mix(self, thrust: Float[Array, ""], tau: Float[Array, " 3"]) -> Float[Array, " 4"]:
        """Rotor speeds for collective thrust and moment, through the inverse allocation.

        Yaw yields first when a rotor would leave its range (the rotors' drag torque is a weak
        yaw actuator, and spending thrust margin on it costs altitude and attitude): the yaw
        moment is clipped to what keeps every ``r²`` in range, then the speeds are clipped.

        Args:
            thrust: collective thrust (N).
            tau: body moment (N·m) about x, y, z.

        Returns:
            The (4,) rotor speeds (rpm) in the motor range.
        """
        lo, hi = self.rpm_min**2, self.rpm_max**2
        base = matvec(
            self.alloc_inv, jnp.concatenate([thrust[None], tau[:2], jnp.zeros(1, tau.dtype)])
        )
        c = self.alloc_inv[:, 3]  # r² per unit yaw moment
        safe_c = jnp.where(jnp.abs(c) > 0, c, 1.0)
        a, b = (lo - base) / safe_c, (hi - base) / safe_c
        t_lo = jnp.max(jnp.where(jnp.abs(c) > 0, jnp.minimum(a, b), -jnp.inf))
        t_hi = jnp.min(jnp.where(jnp.abs(c) > 0, jnp.maximum(a, b), jnp.inf))
        tz = jnp.clip(tau[2], jnp.minimum(t_lo, 0.0), jnp.maximum(t_hi, 0.0))
        r2 = jnp.clip(base + tz * c, lo, hi)
        # sqrt has an infinite slope at 0: a rotor clipped to rest (rpm_min = 0) would turn the
        # clip's zero gradient into NaN. A floor of 1e-6 rpm² changes no speed that matters.
        return jnp.sqrt(jnp.maximum(r2, 1e-6))
