"""6-DoF rigid-body quadrotor dynamics with motor lag, wind, and a pluggable aerodynamic wrench.

World frame x forward, y right, z down; body frame FRD; gravity ``+g e_z``. State: position
and velocity (world), attitude quaternion ``q`` (body to world, scalar first), body rates ``ω``
and rotor speeds (rpm). Rotor speeds follow their commands with a first-order lag and are
clipped to the motor range. The aerodynamic force and moment come from an :class:`AeroModel`:
the paper's simplified model ``M`` (:class:`SimpleAero`) or a GP surrogate
(:class:`gpg.surrogate.SurrogateAero`: the physics never imports the learning layer), behind
one interface, so the same controller flies both.

Integration is classical RK4 inside ``lax.scan``. By default the aerodynamic wrench is
evaluated once per step at its start and held over the four stages (a zero-order hold at the
simulation rate, as a simulator querying an aerodynamic model at a fixed rate does); with
``hold_aero=False`` it is evaluated at every stage.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from gpg._deprecated import deprecated
from gpg.quadrotor.frames import matvec
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle

__all__ = [
    "AeroModel",
    "Quadrotor",
    "Rotation",
    "RotorSpeeds",
    "SimpleAero",
    "State",
    "Vector3",
    "Wind",
    "Wrench",
    "body_parameters",
    "quat_from_euler",
    "quat_to_R",
]

# The arguments of AeroModel.wrench, named once for its implementations.
RotorSpeeds = Float[Array, " 4"]
"""(4,) rotor speeds r1..r4, rpm."""
Rotation = Float[Array, "3 3"]
"""(3, 3) rotation, body to world (``R_WB``)."""
Vector3 = Float[Array, " 3"]
"""(3,) vector: a velocity or a rate."""


class State(eqx.Module):
    """``p`` (3,) m and ``v`` (3,) m/s in the world frame, ``q`` (4,) body-to-world quaternion
    (w, x, y, z), ``w`` (3,) body rates rad/s, ``rpm`` (4,) rotor speeds."""

    p: Float[Array, " 3"]
    v: Float[Array, " 3"]
    q: Float[Array, " 4"]
    w: Float[Array, " 3"]
    rpm: Float[Array, " 4"]

    @classmethod
    def hover(
        cls,
        p: Float[ArrayLike, " 3"],
        rpm: Float[ArrayLike, "..."],
        euler: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    ) -> State:
        """A state at rest, e.g. for the random resets of RL environments.

        Args:
            p: position (m, world frame).
            rpm: rotor speeds (rpm), one for all four rotors or one each.
            euler: attitude ``(yaw, pitch, roll)`` (rad); level by default.

        Returns:
            The state with zero velocity and body rates.
        """
        return cls(
            p=jnp.asarray(p, dtype=float),
            v=jnp.zeros(3),
            q=quat_from_euler(jnp.asarray(euler, dtype=float)),
            w=jnp.zeros(3),
            rpm=jnp.broadcast_to(jnp.asarray(rpm, dtype=float), (4,)),
        )

    @property
    def R(self) -> Float[Array, "3 3"]:
        return quat_to_R(self.q)


def quat_to_R(q: Float[Array, " 4"]) -> Float[Array, "3 3"]:
    """Rotation matrix of a unit quaternion.

    The quaternion is not normalised here: the integrator keeps it unit length after every step.

    Args:
        q: (4,) unit quaternion ``(w, x, y, z)``, scalar first, body to world.

    Returns:
        The (3, 3) rotation ``R_WB``.
    """
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def quat_from_euler(euler: Float[Array, " 3"]) -> Float[Array, " 4"]:
    """Quaternion of ``R_WB = Rz(yaw) Ry(pitch) Rx(roll)``.

    Args:
        euler: (3,) angles ``(yaw, pitch, roll)`` (rad), the dataset's order.

    Returns:
        The (4,) unit quaternion ``(w, x, y, z)``, scalar first.
    """
    cy, sy = jnp.cos(euler[0] / 2), jnp.sin(euler[0] / 2)
    cp, sp = jnp.cos(euler[1] / 2), jnp.sin(euler[1] / 2)
    cr, sr = jnp.cos(euler[2] / 2), jnp.sin(euler[2] / 2)
    return jnp.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def _quat_rate(q: Float[Array, " 4"], w: Float[Array, " 3"]) -> Float[Array, " 4"]:
    """``q̇ = ½ q ⊗ (0, ω)`` for body rates ``ω``."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    return 0.5 * jnp.stack(
        [
            -qx * w[0] - qy * w[1] - qz * w[2],
            qw * w[0] + qy * w[2] - qz * w[1],
            qw * w[1] - qx * w[2] + qz * w[0],
            qw * w[2] + qx * w[1] - qy * w[0],
        ]
    )


class Wrench(eqx.Module):
    """Aerodynamic force and moment (world frame, about the centre of mass), tonal noise levels
    at the microphones (dB; empty without a noise model), and whether the model was queried
    inside its domain."""

    force: Float[Array, " 3"]
    torque: Float[Array, " 3"]
    levels: Float[Array, " K"]
    in_domain: Bool[Array, ""]

    @property
    def noise(self) -> Float[Array, " K"]:
        """Deprecated name of :attr:`levels`."""
        deprecated("Wrench.noise", "Wrench.levels")
        return self.levels


class AeroModel(eqx.Module):
    """The aerodynamic wrench as a function of rotor speeds, attitude, airspeed and body rates."""

    @abc.abstractmethod
    def wrench(self, rpm: RotorSpeeds, R_WB: Rotation, v_air: Vector3, omega: Vector3) -> Wrench:
        """The aerodynamic wrench at one flight state.

        Args:
            rpm: (4,) rotor speeds r1..r4 (rpm).
            R_WB: (3, 3) body-to-world rotation.
            v_air: (3,) airspeed ``v_vehicle − v_wind`` in the world frame (m/s).
            omega: (3,) body rates (rad/s).

        Returns:
            The force and moment in the world frame about the centre of mass, the noise levels
            and whether the query was inside the model's domain.
        """


class SimpleAero(AeroModel):
    """The paper's simplified model ``M``: rotor thrust and drag torque only, no airspeed."""

    model: SimpleModel

    def wrench(self, rpm: RotorSpeeds, R_WB: Rotation, v_air: Vector3, omega: Vector3) -> Wrench:
        """``M``'s body-frame thrust and drag torque, rotated to the world frame.

        The airspeed and body rates do not enter ``M``; there are no noise levels, and every
        query is in domain.

        Args:
            rpm: (4,) rotor speeds (rpm).
            R_WB: (3, 3) body-to-world rotation.
            v_air: (3,) airspeed (m/s, world frame); unused.
            omega: (3,) body rates (rad/s); unused.

        Returns:
            The world-frame force and moment, no levels, ``in_domain`` True.
        """
        F, tau = self.model.wrench_body(rpm)
        return Wrench(matvec(R_WB, F), matvec(R_WB, tau), jnp.zeros(0, F.dtype), jnp.asarray(True))


class Wind(eqx.Module):
    """Constant wind plus a sinusoidal gust (world frame, m/s): ``mean + A sin(2πt/T + φ)``."""

    mean: Float[Array, " 3"]
    gust_amplitude: Float[Array, " 3"]
    gust_period: Float[Array, ""]
    gust_phase: Float[Array, ""]

    @classmethod
    def calm(cls) -> Wind:
        """No wind and no gust.

        Returns:
            The zero wind (a unit gust period keeps the sine defined).
        """
        return cls(jnp.zeros(3), jnp.zeros(3), jnp.asarray(1.0), jnp.asarray(0.0))

    @classmethod
    def constant(cls, mean: Float[ArrayLike, " 3"]) -> Wind:
        """A constant wind in its own float dtype (a float32 mean stays float32).

        Args:
            mean: (3,) wind velocity (m/s, world frame); an integer array becomes float.

        Returns:
            The wind with zero gust, in ``mean``'s float dtype.
        """
        m = jnp.asarray(mean)
        m = m if jnp.issubdtype(m.dtype, jnp.floating) else m.astype(float)
        one = jnp.ones((), m.dtype)
        return cls(m, jnp.zeros(3, m.dtype), one, 0.0 * one)

    def __call__(self, t: Float[Array, ""]) -> Float[Array, " 3"]:
        return self.mean + self.gust_amplitude * jnp.sin(
            2 * jnp.pi * t / self.gust_period + self.gust_phase
        )


def body_parameters(vehicle: Vehicle) -> dict[str, Any]:
    """The rigid body and motors of ``vehicle`` as the dynamics read them.

    Args:
        vehicle: the vehicle (a minimal one suffices).

    Returns:
        A mapping with ``mass``, ``inertia``, ``gravity``, ``motor_time_constant``,
        ``rpm_min`` and ``rpm_max``: the keyword arguments of :class:`Quadrotor` besides its
        aerodynamics.
    """
    return {
        "mass": vehicle.mass,
        "inertia": vehicle.inertia,
        "gravity": vehicle.gravity,
        "motor_time_constant": vehicle.motor_time_constant,
        "rpm_min": vehicle.rpm_min,
        "rpm_max": vehicle.rpm_max,
    }


class Quadrotor(eqx.Module):
    """Rigid body + motors of a vehicle, with an aerodynamic model."""

    aero: AeroModel
    mass: Float[Array, ""]
    inertia: Float[Array, " 3"]
    gravity: Float[Array, ""]
    motor_time_constant: Float[Array, ""]
    rpm_min: Float[Array, ""]
    rpm_max: Float[Array, ""]
    hold_aero: bool = eqx.field(static=True, default=True)

    @classmethod
    def from_vehicle(
        cls, vehicle: Vehicle, aero: AeroModel, *, hold_aero: bool = True
    ) -> Quadrotor:
        """The rigid body and motors of ``vehicle`` flown with the aerodynamics ``aero``.

        Args:
            vehicle: mass, inertia, gravity, motor lag and range.
            aero: the aerodynamic model: :class:`SimpleAero` or a GP surrogate's.
            hold_aero: hold the wrench over each RK4 step (evaluated once at its start) rather
                than evaluate it at every stage.

        Returns:
            The quadrotor.
        """
        return cls(aero=aero, hold_aero=hold_aero, **body_parameters(vehicle))

    def wrench(self, s: State, wind_velocity: Float[Array, " 3"]) -> Wrench:
        """The aerodynamic model's wrench at a state, in the air moving at ``wind_velocity``.

        Args:
            s: the state (rotor speeds, attitude, velocity, body rates).
            wind_velocity: (3,) wind (m/s, world frame).

        Returns:
            The wrench of :meth:`AeroModel.wrench` at airspeed ``v − wind_velocity``.
        """
        return self.aero.wrench(s.rpm, s.R, s.v - wind_velocity, s.w)

    def derivatives(self, s: State, rpm_cmd: Float[Array, " 4"], wr: Wrench) -> State:
        """Time derivative of the state under a given aerodynamic wrench.

        Newton–Euler in the world frame (translation) and body frame (rotation), the
        quaternion rate ``½ q ⊗ (0, ω)``, and the first-order motor lag toward the clipped
        command (a zero rate without lag: :meth:`step` then sets the speeds directly).

        Args:
            s: the state.
            rpm_cmd: (4,) rotor speed commands (rpm), clipped to the motor range.
            wr: the aerodynamic wrench (world frame) acting over the stage.

        Returns:
            The time derivative as a :class:`State` (each field the rate of the state's).
        """
        R = s.R
        acc = (wr.force / self.mass).at[2].add(self.gravity)
        tau_b = matvec(R.T, wr.torque)
        Jw = self.inertia * s.w
        w_dot = (tau_b - jnp.cross(s.w, Jw)) / self.inertia
        cmd = jnp.clip(rpm_cmd, self.rpm_min, self.rpm_max)
        lag = self.motor_time_constant
        # No lag (time constant 0): the rotor speed is set to the command in step, not integrated.
        rpm_rate = jnp.where(lag > 0, (cmd - s.rpm) / jnp.where(lag > 0, lag, 1.0), 0.0)
        return State(p=s.v, v=acc, q=_quat_rate(s.q, s.w), w=w_dot, rpm=rpm_rate)

    def step(
        self, s: State, rpm_cmd: Float[Array, " 4"], t: Float[Array, ""], dt: float, wind: Wind
    ) -> tuple[State, Wrench]:
        """One RK4 step of length ``dt``.

        With ``hold_aero`` the wrench of the step's start is used at all four stages;
        otherwise it is evaluated at each (with the wind at each stage's time). The quaternion
        is renormalised after the step.

        Args:
            s: the state at ``t``.
            rpm_cmd: (4,) rotor speed commands (rpm), held over the step.
            t: the time at the step's start (s).
            dt: the step length (s).
            wind: the wind, evaluated at the stage times.

        Returns:
            The state at ``t + dt`` and the wrench at the step's start.
        """
        wr0 = self.wrench(s, wind(t))

        def f(x: State, tt) -> State:
            wr = wr0 if self.hold_aero else self.wrench(x, wind(tt))
            return self.derivatives(x, rpm_cmd, wr)

        def add(x, k, h):
            return jax.tree.map(lambda a, b: a + h * b, x, k)

        k1 = f(s, t)
        k2 = f(add(s, k1, dt / 2), t + dt / 2)
        k3 = f(add(s, k2, dt / 2), t + dt / 2)
        k4 = f(add(s, k3, dt), t + dt)
        new = jax.tree.map(
            lambda x, a, b, c, d: x + dt / 6 * (a + 2 * b + 2 * c + d), s, k1, k2, k3, k4
        )
        new = eqx.tree_at(lambda x: x.q, new, new.q / jnp.linalg.norm(new.q))
        instant = jnp.clip(rpm_cmd, self.rpm_min, self.rpm_max)
        new = eqx.tree_at(
            lambda x: x.rpm, new, jnp.where(self.motor_time_constant > 0, new.rpm, instant)
        )
        return new, wr0
