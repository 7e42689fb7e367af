"""Flights with known truth: a vehicle flown by gpg's closed-loop simulator and logged through
realistic sensors, for the sim-to-real benchmark and for tests.

The "real" vehicle's aerodynamics are the built-in blade-element-momentum physics
(:func:`gpg.quadrotor.bemt.aero`, what the generator runs) evaluated at every step for a
vehicle that may differ from the one a prior was trained on (:func:`perturbed`). The geometric
controller flies it through waypoints; the log records what sensors would: position,
velocity, attitude and body rates with noise, the accelerometer's specific force with noise and
a bias, rotor speeds from ESC telemetry with noise and a delay, the motor commands through a
static curve with a sagging battery (:class:`Sensors`). The true aerodynamic wrench at each
sample is kept beside the log, so that every error can be measured against the truth rather
than against noisy labels.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from gpg._dtype import float64
from gpg._precision import highest
from gpg.flight.labels import MotorCurve, _euler_batch
from gpg.flight.log import FlightLog, matrix_to_quat, quat_to_matrix
from gpg.quadrotor import bemt
from gpg.quadrotor.control import GeometricController, Reference, WaypointPlan
from gpg.quadrotor.dynamics import (
    AeroModel,
    Quadrotor,
    Rotation,
    RotorSpeeds,
    State,
    Vector3,
    Wind,
    Wrench,
)
from gpg.quadrotor.vehicle import Vehicle, vehicle_config

__all__ = [
    "BEMTAero",
    "Flight",
    "Lemniscate",
    "Sensors",
    "figure_eight",
    "fly",
    "perturbed",
    "perturbed_config",
    "random_plan",
]


class BEMTAero(AeroModel):
    """The blade-element-momentum physics as a flight simulator's aerodynamics (the truth of a
    synthetic flight): rotor loads with body-rate hub velocities, wake interference, airframe
    drag. Some milliseconds per call: a simulator, not a real-time model."""

    vehicle: Vehicle
    config: bemt.BEMTConfig = bemt.BEMTConfig()

    @highest
    def wrench(self, rpm: RotorSpeeds, R_WB: Rotation, v_air: Vector3, omega: Vector3) -> Wrench:
        """The BEMT aerodynamic wrench on the vehicle at one state, world frame.

        Args:
            rpm: (4,) rotor speeds, rpm.
            R_WB: (3, 3) attitude, body to world.
            v_air: (3,) air velocity (velocity minus wind), world, m/s.
            omega: (3,) body rates, rad/s (the hubs' own velocities).

        Returns:
            The force and torque (world frame), no levels, always in the domain.
        """
        r = bemt.aero(self.vehicle, self.config, rpm, R_WB, v_air, omega)
        return Wrench(r.force_W, r.torque_W, jnp.zeros(0, r.force_W.dtype), jnp.asarray(True))


def perturbed(
    vehicle: str | Mapping[str, Any] = "sui_endurance", changes: Mapping[str, Any] | None = None
) -> Vehicle:
    """A vehicle with some of its file's values changed: the "real" vehicle of a benchmark.

    Args:
        vehicle: a name in ``conf/vehicle``, a YAML path or the file's mapping.
        changes: dotted keys of the file (``airfoil.cd0``, ``mass``, ``motor.time_constant``)
            to a new value, or to ``{"scale": s}`` for ``s`` times the file's (element-wise
            for lists); None: no change.

    Returns:
        The vehicle of :func:`perturbed_config`.

    Raises:
        ValueError: a key the file does not have, or a mapping other than ``{"scale": s}``.
    """
    return Vehicle.from_config(perturbed_config(vehicle, changes))


def perturbed_config(
    vehicle: str | Mapping[str, Any] = "sui_endurance", changes: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The vehicle file's mapping with some of its values changed (:func:`perturbed`'s).

    Args:
        vehicle: a name in ``conf/vehicle``, a YAML path or the file's mapping.
        changes: as :func:`perturbed`'s.

    Returns:
        A new mapping (``vehicle``'s is not changed), its name suffixed ``_real``.

    Raises:
        ValueError: a key the file does not have, or a mapping other than ``{"scale": s}``.
    """
    cfg = copy.deepcopy(dict(vehicle) if isinstance(vehicle, Mapping) else vehicle_config(vehicle))
    name = cfg.get("name", "vehicle")
    for key, value in (changes or {}).items():
        *path, last = key.split(".")
        node = cfg
        for p in path:
            if not isinstance(node, dict) or p not in node:
                raise ValueError(f"vehicle {name!r} has no {key!r} to change")
            node = node[p]
        if last not in node:
            raise ValueError(f"vehicle {name!r} has no {key!r} to change")
        if isinstance(value, Mapping):
            if set(value) != {"scale"}:
                raise ValueError(f"change of {key!r} must be a value or {{scale: s}}, got {value}")
            old = node[last]
            s = float(value["scale"])
            node[last] = [s * float(v) for v in old] if isinstance(old, list) else s * float(old)
        else:
            node[last] = value
    cfg["name"] = f"{cfg['name']}_real"
    return cfg


@dataclass(frozen=True)
class Sensors:
    """What the log records and how badly (σ of white noise unless said).

    Attributes:
        rate: Hz, the log's (and the simulation's) rate.
        accel_noise: m/s², the accelerometer.
        accel_bias: m/s², σ of a constant bias per axis and flight.
        gyro_noise: rad/s.
        gyro_bias: rad/s, σ of a constant bias per axis and flight.
        position_noise: m.
        velocity_noise: m/s.
        attitude_noise_deg: deg, per axis of a small rotation.
        rpm_noise: rpm, ESC telemetry.
        rpm_delay: s, the ESC telemetry's lag.
        voltage: V at the start and the end of a 10-minute flight (linear sag).
        curve: the motors' static curve (commands from rotor speeds).
        log_rate: Hz the log keeps (every ``rate / log_rate``-th sample); None: ``rate``.
        rpm_logged: the log has the ESC telemetry's rotor speeds (False: commands only).
        imu: the log has the accelerometer's specific force (False: none).
    """

    rate: float = 200.0
    accel_noise: float = 0.08
    accel_bias: float = 0.03
    gyro_noise: float = 0.004
    gyro_bias: float = 0.002
    position_noise: float = 0.02
    velocity_noise: float = 0.03
    attitude_noise_deg: float = 0.2
    rpm_noise: float = 15.0
    rpm_delay: float = 0.02
    voltage: tuple[float, float] = (16.6, 15.2)
    curve: MotorCurve = MotorCurve(c1=5200.0, c2=2100.0, v_ref=16.0, command_range=(0.0, 1.0))
    log_rate: float | None = None
    rpm_logged: bool = True
    imu: bool = True

    def __post_init__(self):
        if self.log_rate is not None:
            k = self.rate / self.log_rate
            if not (self.log_rate > 0 and abs(k - round(k)) < 1e-9 and round(k) >= 1):
                raise ValueError(
                    f"log_rate must divide rate ({self.rate} Hz) into whole steps, got "
                    f"{self.log_rate}"
                )

    @property
    def every(self) -> int:
        """Simulation steps per logged sample."""
        return 1 if self.log_rate is None else int(round(self.rate / self.log_rate))


@dataclass(frozen=True)
class Flight:
    """A synthetic flight: its log (what sensors saw) and the truth at every sample.

    Attributes:
        log: the :class:`~gpg.flight.log.FlightLog`.
        force, torque: (T, 3) the true aerodynamic force and torque, world frame.
        rpm: (T, 4) true rotor speeds.
        euler: (T, 3) true attitude (yaw, pitch, roll).
        v_air: (T, 3) true air velocity (velocity minus wind), world.
    """

    log: FlightLog
    force: np.ndarray
    torque: np.ndarray
    rpm: np.ndarray
    euler: np.ndarray
    v_air: np.ndarray


def random_plan(
    rng: np.random.Generator,
    duration: float,
    *,
    start: tuple[float, float, float] = (0.0, 0.0, -10.0),
    box: float = 25.0,
    step: tuple[float, float] = (5.0, 20.0),
    leg_time: tuple[float, float] = (4.0, 7.0),
) -> WaypointPlan:
    """A random walk of waypoints, the nose along each leg.

    The defaults peak near ``1.9 · 20 / 4 ≈ 9`` m/s (a minimum-jerk leg's peak speed is 1.875
    times its mean).

    Args:
        rng: the draws' generator.
        duration: s to cover (legs are added past it, so that the plan outlasts the flight).
        start: the first waypoint (NED, m).
        box: m, the waypoints stay within ±``box`` of the origin horizontally (5 to 15 m up).
        step: m, the range each leg's length is drawn from, in a random horizontal direction.
        leg_time: s, the range of the time per leg (drawn once per flight).

    Returns:
        The plan, starting half a second in.
    """
    lt = float(rng.uniform(*leg_time))
    n = int(np.ceil(duration / lt)) + 2
    w = np.empty((n, 3))
    w[0] = start
    for i in range(1, n):
        a, d = rng.uniform(0, 2 * np.pi), rng.uniform(*step)
        xy = np.clip(w[i - 1, :2] + d * np.array([np.cos(a), np.sin(a)]), -box, box)
        w[i] = [xy[0], xy[1], rng.uniform(-15.0, -5.0)]
    return WaypointPlan.create(w, start_time=0.5, leg_time=lt, yaw="travel")


class Lemniscate(eqx.Module):
    """A figure-eight reference flown continuously (a lemniscate of Gerono in the horizontal
    plane, ``x = a sin s``, ``y = b sin s cos s``), its phase ``s`` accelerated uniformly from
    rest over ``ramp`` seconds: position, velocity and acceleration in closed form, at one
    heading. The reference of :func:`figure_eight`.

    Attributes:
        center: (3,) NED, m.
        size: (2,) ``(a, b)``, m.
        omega: rad/s, the phase's rate once up to speed (``2π`` per lap).
        start: s, the hover before the phase starts.
        ramp: s, the phase's run-up.
        yaw: rad, the heading.
    """

    center: Float[Array, " 3"]
    size: Float[Array, " 2"]
    omega: Float[Array, ""]
    start: Float[Array, ""]
    ramp: Float[Array, ""]
    yaw: Float[Array, ""]

    def __call__(self, t: Float[Array, ""]) -> Reference:
        tt = jnp.maximum(t - self.start, 0.0)
        up = tt < self.ramp
        w = self.omega
        s = jnp.where(up, 0.5 * w * tt**2 / self.ramp, w * (tt - 0.5 * self.ramp))
        sd = jnp.where(up, w * tt / self.ramp, w)
        sdd = jnp.where(up & (t > self.start), w / self.ramp, 0.0)
        a, b = self.size[0], self.size[1]
        zero = jnp.zeros_like(s)
        p = jnp.stack([a * jnp.sin(s), 0.5 * b * jnp.sin(2 * s), zero])
        dp = jnp.stack([a * jnp.cos(s), b * jnp.cos(2 * s), zero])
        ddp = jnp.stack([-a * jnp.sin(s), -2 * b * jnp.sin(2 * s), zero])
        return Reference(p=self.center + p, v=dp * sd, a=ddp * sd**2 + dp * sdd, yaw=self.yaw)


def figure_eight(
    *,
    center: tuple[float, float, float] = (0.0, 0.0, -10.0),
    size: tuple[float, float] = (4.0, 2.0),
    period: float = 8.0,
    yaw: float = 0.0,
    hold_s: float = 0.5,
    ramp_s: float | None = None,
) -> Lemniscate:
    """A figure-eight flown again and again, as in a wind tunnel: the smooth manoeuvres that
    make drag and wind separable (:class:`Lemniscate`).

    Args:
        center: its centre (NED, m).
        size: ``(a, b)``, m: half its length along x and its half-width along y.
        period: s per lap.
        yaw: the heading (rad).
        hold_s: s of hover at the centre first.
        ramp_s: s of the phase's run-up from rest (default: one lap).

    Returns:
        The reference.

    Raises:
        ValueError: a period or run-up not positive, or a negative hold.
    """
    ramp = period if ramp_s is None else ramp_s
    if not (period > 0 and ramp > 0 and hold_s >= 0):
        raise ValueError(f"period and ramp_s must be > 0 and hold_s >= 0, got {period}, {ramp}, "
                         f"{hold_s}")  # fmt: skip
    return Lemniscate(
        center=jnp.asarray(center, float),
        size=jnp.asarray(size, float),
        omega=jnp.asarray(2 * np.pi / period),
        start=jnp.asarray(float(hold_s)),
        ramp=jnp.asarray(float(ramp)),
        yaw=jnp.asarray(float(yaw)),
    )


_PHYSICS = bemt.BEMTConfig()  # the generator's own settings


@float64
def fly(
    real: Vehicle,
    ctrl: GeometricController,
    plan: WaypointPlan,
    wind: Wind,
    duration: float,
    *,
    sensors: Sensors = Sensors(),
    seed: int = 0,
    wind_in_log: bool = True,
    bemt_config: bemt.BEMTConfig = _PHYSICS,
    name: str = "flight",
) -> Flight:
    """Fly ``real`` for ``duration`` seconds from hover at the plan's first waypoint.

    Args:
        real: the vehicle flown (its mass, inertia, motors and BEMT physics are the truth).
        ctrl: the controller (it knows only the simplified model of the nominal vehicle).
        plan: the reference trajectory (a function of time, e.g. a
            :class:`~gpg.quadrotor.control.WaypointPlan` or a :class:`Lemniscate`; the flight
            starts in hover at its position at t = 0).
        wind: the wind (world, m/s).
        duration: seconds.
        sensors: the sensor model.
        seed: the noise and biases.
        wind_in_log: write the wind as a column (a measured wind) or leave it unknown.
        bemt_config: the physics' settings (wake gain, interference).
        name: the log's name.

    Returns:
        The :class:`Flight`: its log and the truth.
    """
    dt = 1.0 / sensors.rate
    n = int(round(duration * sensors.rate))
    quad = Quadrotor.from_vehicle(real, BEMTAero(real, bemt_config))
    rpm0 = float(np.sqrt(float(real.weight) / (4 * float(ctrl_thrust_coefficient(ctrl)))))
    s0 = State.hover(plan(jnp.asarray(0.0)).p, jnp.full(4, rpm0))
    states, wrenches, t = _simulate(quad, ctrl, plan, wind, s0, dt, n)
    truth = jax.tree.map(np.asarray, (states, wrenches))
    (st, wr), t = truth, np.asarray(t)
    rng = np.random.default_rng(seed)
    R = quat_to_matrix(st.q / np.linalg.norm(st.q, axis=1, keepdims=True))
    f_B = np.einsum("nji,nj->ni", R, wr.force) / float(real.mass)
    f_B += rng.normal(0, sensors.accel_bias, 3) + rng.normal(0, sensors.accel_noise, (n, 3))
    gyro = st.w + rng.normal(0, sensors.gyro_bias, 3) + rng.normal(0, sensors.gyro_noise, (n, 3))
    small = np.radians(sensors.attitude_noise_deg) * rng.normal(size=(n, 3))
    R_meas = R @ _exp_so3(small)
    k = int(round(sensors.rpm_delay * sensors.rate))
    rpm_tel = np.concatenate([np.repeat(st.rpm[:1], k, 0), st.rpm[: n - k]]) if k else st.rpm
    rpm_tel = np.maximum(rpm_tel + rng.normal(0, sensors.rpm_noise, (n, 4)), 0.0)
    v0, v1 = sensors.voltage
    volt = v0 + (v1 - v0) * t / 600.0 + rng.normal(0, 0.02, n)
    cmd = _commands(sensors.curve, np.asarray(st.rpm_cmd), volt)
    v_wind = np.asarray(jax.vmap(wind)(jnp.asarray(t)))
    k = slice(None, None, sensors.every)
    log = FlightLog(
        t=t[k],
        position=(st.p + rng.normal(0, sensors.position_noise, (n, 3)))[k],
        velocity=(st.v + rng.normal(0, sensors.velocity_noise, (n, 3)))[k],
        quaternion=matrix_to_quat(R_meas)[k],
        rates=gyro[k],
        rpm=rpm_tel[k] if sensors.rpm_logged else None,
        command=cmd[k],
        specific_force=f_B[k] if sensors.imu else None,
        wind=v_wind[k] if wind_in_log else None,
        voltage=volt[k],
        name=name,
    )
    euler = np.asarray(_euler_batch(R[k]))
    return Flight(log, wr.force[k], wr.torque[k], st.rpm[k], euler, (st.v - v_wind)[k])


def ctrl_thrust_coefficient(ctrl: GeometricController) -> Float[Array, ""]:
    """``P_F`` of the simplified model the controller inverts (its allocation's first row)."""
    return 1.0 / jnp.sum(ctrl.alloc_inv[:, 0])


class _Record(eqx.Module):
    p: Array
    v: Array
    q: Array
    w: Array
    rpm: Array
    rpm_cmd: Array


@eqx.filter_jit
def _simulate(quad: Quadrotor, ctrl, plan, wind, s0: State, dt: float, n: int):
    def step(s: State, k):
        t = k * dt
        cmd = ctrl(s, plan(t))
        new, wr = quad.step(s, cmd, t, dt, wind)
        rec = _Record(p=s.p, v=s.v, q=s.q, w=s.w, rpm=s.rpm, rpm_cmd=cmd)
        return new, (rec, Wrench(wr.force, wr.torque, wr.levels, wr.in_domain), t)

    _, (rec, wr, t) = jax.lax.scan(step, s0, jnp.arange(n, dtype=float))
    return rec, wr, t


def _exp_so3(v: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


def _commands(curve: MotorCurve, rpm_cmd: np.ndarray, volt: np.ndarray) -> np.ndarray:
    """The commands ``u`` whose curve speed at ``volt`` is ``rpm_cmd`` (the quadratic's root)."""
    a, b = curve.c2, curve.c1
    s = (-b + np.sqrt(b * b + 4 * a * rpm_cmd)) / (2 * a) if a > 0 else rpm_cmd / b
    return np.clip(s * curve.v_ref / volt[:, None], 0.0, 1.0)
