"""Force and torque labels from measured motion, and motor commands turned into rotor speeds.

The aerodynamic force is what the accelerometer measures, times the mass: the IMU's specific
force ``f_B = F_aero,B / m`` (body FRD; gravity is no force on it), so ``F_W = m R_WB f_B``.
Without an IMU it comes from the velocity: ``F_W = m (v̇_W − g e_z)`` (NED, z down), with
``v̇`` the derivative of a smoothing spline of the velocity (:func:`scipy.interpolate.
make_smoothing_spline`). The torque comes from the body rates: ``τ_B = J ω̇ + ω × J ω``
(Euler's equation about the centre of mass, ``J`` the vehicle's principal inertia), ``ω̇``
again the derivative of a smoothing spline; ``τ_W = R_WB τ_B``. Forces and torques are in the
world frame, as :meth:`gpg.Surrogate.predict` returns them; a label's *residual* is the
measurement minus a reference model at the same state: the simplified model ``M`` by default,
or a fitted surrogate.

Noise. Each raw signal's white-noise variance is estimated per sample from its second
differences (``Var Δ²y = 6σ²`` for white noise on a signal smooth at the sampling rate; a
rolling median of ``|Δ²y|`` over :data:`NOISE_WINDOW_S` keeps manoeuvres out of it), and
carried through the spline: a smoothing spline is a linear filter, so the variance of its value
(or derivative) at a sample is ``σ² Σ_k h_k²`` with ``h`` its impulse response, found once per
signal by smoothing a unit impulse. Labels are then taken at ``rate`` Hz, each with its
variance per component.

Dropped segments, counted in :attr:`Labels.dropped`: samples on the ground (``M``'s thrust
from the rotor speeds below :data:`GROUND_THRUST` of the weight and the speed under 1 m/s, for
:data:`GROUND_MIN_S` at least: there the accelerometer also feels the ground), the first
``takeoff_s`` seconds after each take-off (ground effect) and the last before each landing,
samples where a rotor is saturated (at ``saturation`` of its range, padded by
:data:`SATURATION_PAD_S`), and samples near the ends of segments split at gaps.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import jax
import numpy as np
from scipy import ndimage, optimize
from scipy.interpolate import make_smoothing_spline

from gpg._checks import as_float_array, finite_number
from gpg.flight.log import GAP_FACTOR, FlightLog, FlightLogWarning
from gpg.quadrotor.frames import euler_from_R
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle

if TYPE_CHECKING:
    from gpg.surrogate import Surrogate

__all__ = ["Labels", "MotorCurve", "calibrate_simple", "estimate_delay", "hover_samples", "label"]

GROUND_THRUST = 0.5  # M's thrust below this fraction of the weight: on the ground (if still)
GROUND_MIN_S = 0.5  # s: on the ground only for at least this long
SATURATION_PAD_S = 0.1  # s dropped on each side of a saturated sample
SATURATION = 0.98  # label's default: a rotor at this fraction of its range is saturated
NOISE_WINDOW_S = 1.0  # s, window of the rolling noise estimate
GCV_WINDOW = 300  # samples: the smoothing parameter is chosen by GCV on one such window
DELAY_HIGHPASS_S = 0.2  # s, the high-pass window of the delay's cross-correlation
EDGE_S = 0.1  # s dropped at each end of a segment, where the spline has one side only
MAX_DELAY_S = 0.5  # s: a rotor-speed channel's lag is tens of ms; more is a unit mistake
# Above this share of vanishing second differences a signal is an interpolation, not samples.
INTERPOLATED_SHARE = 0.5


# One compiled program for every batch of angles: vmapped op by op, each new batch size
# compiled a program for every operation of the rotation.
_euler_batch = jax.jit(jax.vmap(euler_from_R))


@dataclass(frozen=True)
class MotorCurve:
    """A static curve from motor command to rotor speed: ``q = c1 s + c2 s²`` with
    ``s = u V / V_ref`` (command ``u`` in 0..1 scaled by the battery voltage ``V``, the
    term that makes the same command spin faster on a full battery), lagged by the motors'
    time constant, and ``rpm = r_ref (q / r_ref)^p`` (``p = 1``: the quadratic itself). The
    exponent is what :func:`gpg.flight.identify` fits (``motor.exponent``) where a curve
    from a hover saw too narrow a range of commands to get its bend right.

    Attributes:
        c1: rpm per unit scaled command.
        c2: rpm per unit scaled command squared.
        v_ref: V, the voltage at which ``s = u`` (ignored when the log has no voltage).
        command_range: the commands the fit saw; others are extrapolation (warned, counted).
        residual_rpm: RMS residual of the fit, rpm (rotor speeds against the curve, or the
            thrust-balance residual converted to rpm for a fit from hover).
        source: ``"speeds"`` (fitted to measured rotor speeds), ``"hover"`` (thrust balances
            weight) or ``"given"``.
        time_constant: s, the motors' first-order lag behind the curve's static speed
            (0: none); applied where :meth:`rpm` is given the samples' times.
        exponent: ``p``, the power on the speed about ``rpm_ref`` (1: none).
        rpm_ref: ``r_ref``, rpm, the speed the exponent leaves unchanged.
    """

    c1: float
    c2: float = 0.0
    v_ref: float = 1.0
    command_range: tuple[float, float] = (0.0, 1.0)
    residual_rpm: float = float("nan")
    source: str = "given"
    time_constant: float = 0.0
    exponent: float = 1.0
    rpm_ref: float = 1.0

    def __post_init__(self):
        for key in ("c1", "c2", "v_ref", "time_constant", "exponent", "rpm_ref"):
            finite_number(f"MotorCurve.{key}", getattr(self, key))
        for key in ("exponent", "rpm_ref"):
            if not getattr(self, key) > 0:
                raise ValueError(f"MotorCurve.{key} must be positive, got {getattr(self, key)!r}")
        if not self.v_ref > 0:
            raise ValueError(f"MotorCurve.v_ref must be a positive voltage, got {self.v_ref!r}")
        if self.time_constant < 0:
            raise ValueError(f"MotorCurve.time_constant must be >= 0 s, got {self.time_constant!r}")
        if not self.c1 + self.c2 > 0:
            raise ValueError(
                f"MotorCurve: c1 + c2 (the speed at full command) must be positive, got "
                f"c1={self.c1!r}, c2={self.c2!r}"
            )
        rng = self.command_range
        if (
            isinstance(rng, (str, bytes))
            or len(tuple(rng)) != 2
            or not all(math.isfinite(finite_number("MotorCurve.command_range", v)) for v in rng)
            or not rng[0] <= rng[1]
        ):
            raise ValueError(f"MotorCurve.command_range must be (low, high), got {rng!r}")

    def rpm(
        self, command: np.ndarray, voltage: np.ndarray | None = None, t: np.ndarray | None = None
    ) -> np.ndarray:
        """Rotor speeds (rpm) of motor commands through the curve.

        Commands outside :attr:`command_range` warn (:class:`FlightLogWarning`) with their
        count: the curve is extrapolated there. Negative speeds are clipped to 0. Given the
        samples' times, the speeds follow the curve's static speed with the first-order lag
        :attr:`time_constant` (the motors' own: a command that jumps is not a speed that
        jumps).

        Args:
            command: (T, 4) motor commands, 0..1.
            voltage: (T,) battery voltage, V; None: the reference :attr:`v_ref`.
            t: (T,) the samples' times, s; None: no lag.

        Returns:
            (T, 4) rotor speeds, rpm.

        Raises:
            ValueError: a command not (T, 4) or (4,), a voltage or times of another length,
                a voltage not positive.
        """
        u = as_float_array("command", command, ndim=(1, 2))
        if u.shape[-1] != 4:
            raise ValueError(f"command must have shape (T, 4) or (4,), got {u.shape}")
        if voltage is not None:
            V = as_float_array("voltage", voltage, ndim=(0, 1, 2))
            if V.shape not in ((), u.shape[:-1], (*u.shape[:-1], 1)):
                raise ValueError(
                    f"voltage must have shape {u.shape[:-1]} (one per row of command), got "
                    f"{V.shape}"
                )
            if np.any(~(V > 0)):
                raise ValueError("voltage must be positive (V) and finite")
        if t is not None and np.shape(t) != u.shape[:-1]:
            raise ValueError(f"t must have shape {u.shape[:-1]}, got {np.shape(t)}")
        lo, hi = self.command_range
        out = (u < lo - 1e-9) | (u > hi + 1e-9)
        if out.any():
            rows = np.flatnonzero(out.any(axis=-1))
            warnings.warn(
                f"{out.sum()} command(s) in {rows.size} row(s) (first rows {rows[:5].tolist()}) "
                f"outside the calibration's range [{lo:.3g}, {hi:.3g}]: extrapolated",
                FlightLogWarning,
                stacklevel=2,
            )
        s = _scaled(u, voltage, self.v_ref)
        static = np.maximum(self.c1 * s + self.c2 * s * s, 0.0)
        q = static if t is None else first_order_lag(t, static, self.time_constant)
        if self.exponent == 1.0:
            return q
        return self.rpm_ref * (np.maximum(q, 0.0) / self.rpm_ref) ** self.exponent

    def scaled(self, gain: float = 1.0, exponent: float = 1.0, rpm_ref: float = 1.0) -> MotorCurve:
        """The curve whose speeds are ``gain · rpm_ref (rpm / rpm_ref)^exponent`` of this
        curve's ``rpm`` (what :func:`gpg.flight.identify` fits as ``motor.gain`` and
        ``motor.exponent``), as a curve of the same form.

        Args:
            gain: the factor on the speeds.
            exponent: the power on the speeds about ``rpm_ref``.
            rpm_ref: rpm, the speed the power leaves unchanged.

        Returns:
            The curve (``source`` and ``command_range`` kept; the residual scaled by the gain).

        Raises:
            ValueError: a gain, exponent or reference speed that is not positive and finite.
        """
        for key, v in (("gain", gain), ("exponent", exponent), ("rpm_ref", rpm_ref)):
            if not finite_number(key, v) > 0:
                raise ValueError(f"{key} must be positive, got {v!r}")
        # A curve without a power takes the new reference (any r0 is then equivalent).
        p0, p = self.exponent, float(exponent)
        r0 = float(rpm_ref) if p0 == 1.0 else self.rpm_ref
        # g r (r0 (q/r0)^p0 / r)^p = r0 (k q / r0)^(p0 p) with k as below: c1, c2 take k.
        k = (gain * (rpm_ref / r0) ** (1.0 - p)) ** (1.0 / (p0 * p))
        return dataclasses.replace(self, c1=self.c1 * k, c2=self.c2 * k, exponent=p0 * p,
                                   rpm_ref=r0, residual_rpm=self.residual_rpm * gain)  # fmt: skip

    @classmethod
    def fit_speeds(
        cls,
        command: np.ndarray,
        rpm: np.ndarray,
        voltage: np.ndarray | None = None,
        *,
        time_constant: float = 0.0,
    ) -> MotorCurve:
        """Fit the curve to measured rotor speeds by least squares.

        Idle commands (at most 0.02, the ESC's own floor) are left out; ``v_ref`` is the
        median voltage, so that ``s = u`` at a typical battery. The readings are taken as
        steady (a bench's, each speed settled at its command): the fit is the static curve.
        Read on a flight's commands, the rotors lag it by the motors' time constant: give it
        (the vehicle file's ``motor.time_constant``), or :func:`label` warns.

        Args:
            command: (T, 4) motor commands, 0..1.
            rpm: (T, 4) the rotor speeds measured with them.
            voltage: (T,) battery voltage, V; None: no voltage scaling.
            time_constant: s, the motors' first-order lag behind the static curve, kept in the
                curve for the flights it reads (0: none).

        Returns:
            The fitted curve (``source="speeds"``), with its RMS residual and command range.

        Raises:
            ValueError: commands and speeds of other shapes than (T, 4) each (or a voltage
                not (T,)), NaN or inf, fewer than two command levels above idle, or a
                negative ``time_constant``.
        """
        command = as_float_array("command", command, ndim=2)
        rpm = as_float_array("rpm", rpm, ndim=2)
        if command.shape[1:] != (4,) or rpm.shape != command.shape:
            raise ValueError(
                f"command and rpm must both have shape (T, 4), got {command.shape} and {rpm.shape}"
            )
        if voltage is not None and np.shape(voltage) != command.shape[:1]:
            raise ValueError(
                f"voltage must have shape {command.shape[:1]}, got {np.shape(voltage)}"
            )
        for what, a in (("command", command), ("rpm", rpm), ("voltage", voltage)):
            if a is not None and not np.all(np.isfinite(a)):
                raise ValueError(f"{what} holds NaN or inf")
        u, w = command.ravel(), rpm.ravel()
        V = None if voltage is None else np.repeat(np.asarray(voltage, float), 4)
        v_ref = 1.0 if V is None else float(np.median(V))
        s = _scaled(u, V, v_ref)
        keep = u > 0.02  # idle commands: the ESC's own floor, not the curve
        if np.unique(u[keep]).size < 2:
            raise ValueError(
                f"fit_speeds needs commands above idle (0.02) at two levels at least; got "
                f"{int(keep.sum())} command(s) above idle"
            )
        A = np.stack([s[keep], s[keep] ** 2], 1)
        (c1, c2), *_ = np.linalg.lstsq(A, w[keep], rcond=None)
        res = float(np.sqrt(np.mean((A @ [c1, c2] - w[keep]) ** 2)))
        rng = (float(u[keep].min()), float(u[keep].max()))
        return cls(float(c1), float(c2), v_ref, rng, res, "speeds", float(time_constant))

    @classmethod
    def fit_hover(
        cls,
        log: FlightLog,
        vehicle: Vehicle,
        simple: SimpleModel,
        *,
        max_speed: float = 1.0,
        max_tilt_deg: float = 10.0,
        moments: bool = False,
    ) -> MotorCurve:
        """Fit the curve where no rotor speeds are logged, from slow flight (hover by default).

        ``M``'s thrust of the curve's rotor speeds balances the measured thrust ``−F_z``
        (body z of the measured aerodynamic force: the accelerometer's specific force times
        the mass, or, without an IMU, the mass times the velocity's spline derivative less
        gravity, as :func:`label` measures it) on samples slower than ``max_speed``, tilted
        less than ``max_tilt_deg``, rotors turning; the speeds lag the curve by the vehicle
        file's ``motor.time_constant`` (kept in the curve). Measured, not assumed equal to
        the weight: the samples of a take-off's transient count as well as a steady hover's,
        and widen the commands the curve sees. At slow speed the drag is small against the
        thrust; raise ``max_speed`` to take in a calm flight's manoeuvres.

        The thrust needs the weighed mass only. ``moments=True`` also balances ``M``'s roll and
        pitch moments against the measured ones (Euler's equation on the body rates), which
        sees each rotor's command apart, but reads the file's inertia and takes every moment
        for the rotors' thrust difference: where the inertia is a guess, or the rotors' own
        moments (their rate damping, a wake's) are not small, it bends the curve.

        Args:
            log: the flight, with motor commands and slow flight.
            vehicle: its mass and gravity (and inertia, with ``moments``).
            simple: ``M``, whose allocation turns rotor speeds into thrust and moments.
            max_speed: m/s, the fastest samples used.
            max_tilt_deg: deg, the most tilted samples used.
            moments: also balance the roll and pitch moments.

        Returns:
            The fitted curve (``source="hover"``); its residual is the thrust balance's,
            converted to rpm (a relative thrust error ``e`` is a rotor-speed error ``e/2``).

        Raises:
            ValueError: the log has no motor commands, fewer than 20 samples to fit, or
                ``moments`` not a bool.
        """
        if not isinstance(moments, bool):
            raise ValueError(f"fit_hover: moments must be True or False, got {moments!r}")
        if log.command is None:
            raise ValueError(f"{log.name}: fit_hover needs motor commands in the log")
        m, g = float(vehicle.mass), float(vehicle.gravity)
        R = log.R_WB()
        tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
        dt = float(np.median(np.diff(log.t)))
        src = "imu" if log.specific_force is not None else "velocity"
        F_B, _, tau_B, _, edges = _measured_loads(log, vehicle, R, src, dt)
        hover = (np.linalg.norm(log.velocity, axis=1) < max_speed) & (tilt < max_tilt_deg)
        hover &= (log.command.min(1) > 0.05) & ~edges
        if hover.sum() < 20:
            raise ValueError(
                f"{log.name}: only {int(hover.sum())} samples to fit the motor curve on (speed "
                f"< {max_speed:g} m/s, tilt < {max_tilt_deg:g}°, rotors turning): give the "
                "curve in the vehicle file or log rotor speeds"
            )
        u = log.command[hover]
        V = None if log.voltage is None else log.voltage
        v_ref = 1.0 if V is None else float(np.median(V[hover]))
        s_all = _scaled(log.command, None if V is None else V[:, None], v_ref)
        # The speed lags the curve's static speed c1 s + c2 s²: linear in (c1, c2), so the
        # lag is applied to s and s² once, over the whole log.
        tau = float(vehicle.motor_time_constant)
        s, s2 = (first_order_lag(log.t, a, tau)[hover] for a in (s_all, s_all**2))
        thrust, torque = -F_B[hover, 2], tau_B[hover, :2]
        A = np.asarray(simple.allocation)

        def resid(c):
            w = c[0] * s + c[1] * s2
            load = (w * w) @ A.T  # (ΣT, τx, τy, τz)
            r = (load[:, 0] - thrust) / (m * g)
            return np.concatenate([r, (load[:, 1:3] - torque).ravel()]) if moments else r

        hover_rpm = float(simple.hover_rpm(m * g))
        c0 = np.array([hover_rpm / max(float(np.median(s)), 1e-3), 0.0])
        sol = optimize.least_squares(resid, c0, x_scale=np.abs(c0) + 1.0)
        r = sol.fun[: s.shape[0]]
        # a relative thrust error e is a relative rotor-speed error e/2
        res = float(np.sqrt(np.mean(r**2)) / 2 * hover_rpm)
        rng = (float(u.min()), float(u.max()))
        return cls(float(sol.x[0]), float(sol.x[1]), v_ref, rng, res, "hover", tau)


def first_order_lag(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    """``x`` (T, ...) passed through a first-order lag of time constant ``tau`` (s), starting
    at ``x_0``; ``tau`` 0 returns ``x``.

    A log's commands are samples of a faster controller's output, so between two samples the
    input is taken as the straight line through them (a first-order hold), and the lag is
    exact for it: with ``h = Δt``, ``e = e^{−h/τ}`` and ``b = 1 − τ (1 − e)/h``,
    ``y_k = e y_{k−1} + (1 − e − b) x_{k−1} + b x_k``. Holding ``x_k`` over the step before it
    (an earlier version) made the speeds lead the rotors by about a sample."""
    x = np.asarray(x, float)
    if tau <= 0:
        return x
    h = np.diff(np.asarray(t, float))
    e = np.exp(-h / tau)
    # for h ≪ τ both samples weigh h/(2τ) (the midpoint); b's series there avoids cancellation
    r = h / tau
    b = np.where(r < 1e-4, r / 2 - r * r / 6, 1.0 + np.expm1(-r) / np.where(r > 0, r, 1.0))
    y = np.empty_like(x)
    y[0] = x[0]
    shape = (-1,) + (1,) * (x.ndim - 1)
    e, b = e.reshape(shape), b.reshape(shape)
    for k in range(1, x.shape[0]):
        y[k] = e[k - 1] * y[k - 1] + (1 - e[k - 1] - b[k - 1]) * x[k - 1] + b[k - 1] * x[k]
    return y


def hover_samples(log: FlightLog, rpm: np.ndarray, *, min_height: float = 0.3) -> np.ndarray:
    """Which samples hover.

    Hovering: rotors turning (every rotor above a quarter of the flight's median turning
    speed), speed under 0.5 m/s, tilt under 10°, and, when the log has the vehicle on the
    ground (rotors below that), at least ``min_height`` above it (out of ground effect).

    Args:
        log: the flight.
        rpm: (T, 4) its rotor speeds (the log's, or from a :class:`MotorCurve`).
        min_height: m above the ground's height, where the log shows the ground.

    Returns:
        (T,) bool, True where the vehicle hovers.

    Raises:
        ValueError: ``rpm`` not one row of four rotor speeds per sample of the log.
    """
    rpm = as_float_array("rpm", rpm, ndim=2)
    if rpm.shape != (log.t.size, 4):
        raise ValueError(
            f"rpm must have shape {(log.t.size, 4)} (the log's samples, four rotors), got "
            f"{rpm.shape}"
        )
    R = log.R_WB()
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
    turning = rpm.min(1) > 0
    floor = 0.25 * np.median(rpm[turning]) if turning.any() else np.inf
    flying = rpm.min(1) > floor
    up = np.ones(flying.size, bool)
    if (~flying).any():
        ground_z = float(np.median(log.position[~flying, 2]))
        up = -(log.position[:, 2] - ground_z) > min_height
    return flying & (np.linalg.norm(log.velocity, axis=1) < 0.5) & (tilt < 10) & up


def calibrate_simple(
    log: FlightLog,
    vehicle: Vehicle,
    *,
    rpm: np.ndarray | None = None,
    torque_ratio: float | None = None,
    min_hover: int = 5,
) -> SimpleModel:
    """``M``'s coefficients fitted to a flight.

    ``P_F`` so that ``M``'s thrust balances the measured thrust ``−m f_z`` where the log
    hovers (:func:`hover_samples`; least squares), ``T_z`` so that ``M``'s yaw moment matches
    ``J_z ω̇_z`` (least squares over the airborne samples; ``T_z = torque_ratio · P_F`` where
    given (m: the rotor's drag torque per unit thrust), else the vehicle file's ratio where it
    has one). For a vehicle whose file has no ``simple_model`` section, or to check one
    against a flight.

    Args:
        log: the flight, with the IMU's specific force and a hover.
        vehicle: its mass, inertia, rotor spins and (if any) the file's coefficients.
        rpm: (T, 4) rotor speeds overriding the log's.
        torque_ratio: ``T_z / P_F`` (m); None: the vehicle file's, else fitted to yaw.
        min_hover: the fewest hover samples to calibrate on.

    Returns:
        ``M`` built from the vehicle with the fitted ``P_F`` and ``T_z``.

    Raises:
        ValueError: fewer than ``min_hover`` hover samples, a log without the specific force
            or rotor speeds (naming what is missing), or yaw moments that do not determine
            ``T_z`` (a flight without yaw manoeuvres: give ``torque_ratio``).
    """
    if log.specific_force is None:
        raise ValueError(f"{log.name}: calibrate_simple needs the IMU's specific force")
    rpm = log.rpm if rpm is None else rpm
    if rpm is None:
        raise ValueError(f"{log.name}: calibrate_simple needs rotor speeds (or rpm=)")
    hover = hover_samples(log, rpm)
    if hover.sum() < min_hover:
        raise ValueError(
            f"{log.name}: {int(hover.sum())} hover samples (speed < 0.5 m/s, tilt < 10°, above "
            f"0.3 m), fewer than {min_hover}: cannot calibrate M's thrust"
        )
    m = float(vehicle.mass)
    s = (rpm[hover] ** 2).sum(1)
    thrust = -m * log.specific_force[hover, 2]
    P_F = float(np.sum(thrust * s) / np.sum(s * s))
    if torque_ratio is None and vehicle.thrust_coefficient is not None:
        torque_ratio = float(vehicle.torque_coefficient) / float(vehicle.thrust_coefficient)
    if torque_ratio is not None:
        T_z = float(torque_ratio) * P_F
    else:
        w_dot, _ = _smooth(log.t, log.rates, deriv=True)
        J = np.asarray(vehicle.inertia, float)
        tau_z = J[2] * w_dot[:, 2] + (J[1] - J[0]) * log.rates[:, 0] * log.rates[:, 1]
        air = rpm.min(1) > 0
        d = (rpm[air] ** 2) @ np.asarray(vehicle.spin, float)
        T_z = float(-np.sum(tau_z[air] * d) / max(np.sum(d * d), 1e-300))
        if not T_z > 0:
            raise ValueError(
                f"{log.name}: the yaw moments do not determine T_z (got {T_z:.3g}): give "
                "torque_ratio (T_z/P_F, m)"
            )
    return SimpleModel.from_vehicle(vehicle, P_F, T_z)


def _scaled(u, voltage, v_ref):
    if voltage is None:
        return u
    V = np.asarray(voltage, float)
    if u.ndim == 2 and V.ndim == 1:  # one voltage per sample, four rotors
        V = V[:, None]
    return u * V / v_ref


@dataclass(frozen=True)
class Labels:
    """Measured aerodynamic loads at the states of a flight (N labels), world frame.

    Attributes:
        t: (N,) s.
        rpm: (N, 4) rotor speeds, aligned with the loads (:attr:`delay` applied).
        euler: (N, 3) (yaw, pitch, roll) of the body in the world, rad.
        v_air: (N, 3) velocity minus wind, world, m/s (the log's wind, else none).
        force, torque: (N, 3) the measured aerodynamic force (N) and torque (N·m).
        force_var, torque_var: (N, 3) their estimated noise variances.
        model_force, model_torque: (N, 3) the reference model at the same states.
        dropped: samples dropped, by reason (``ground``, ``takeoff_landing``, ``saturated``,
            ``edges``), of ``total`` samples in the log.
        delay: s, the rotor-speed channel's lag behind the IMU that was removed.
        source: ``"imu"`` or ``"velocity"``: where the force came from.
        name: the flight's name.
        rates: (N, 3) the body rates at the labels (the log's gyro), body frame, rad/s: the
            rotor hubs' motion that :func:`gpg.flight.identify`'s physics reads. None for
            labels made without them (read as a vehicle that does not rotate).
    """

    t: np.ndarray
    rpm: np.ndarray
    euler: np.ndarray
    v_air: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    force_var: np.ndarray
    torque_var: np.ndarray
    model_force: np.ndarray
    model_torque: np.ndarray
    dropped: dict[str, int] = field(default_factory=dict)
    delay: float = 0.0
    source: str = "imu"
    name: str = "flight"
    rates: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def columns(self) -> tuple[np.ndarray, ...]:
        """The labels as the columns of :func:`gpg.flight.update`'s arguments.

        Returns:
            ``(t, rpm, euler, v_air, force, torque, force_var, torque_var)``, each (N, ...):
            a ``lax.scan``'s ``xs``, or one row per call of the update.
        """
        return (self.t, self.rpm, self.euler, self.v_air, self.force, self.torque,
                self.force_var, self.torque_var)  # fmt: skip

    @property
    def residual_force(self) -> np.ndarray:
        """(N, 3) measured minus reference force, N."""
        return self.force - self.model_force

    @property
    def residual_torque(self) -> np.ndarray:
        """(N, 3) measured minus reference torque, N·m."""
        return self.torque - self.model_torque

    def take(self, rows: slice | np.ndarray | Sequence[int]) -> Labels:
        """A subset of the labels; the flight's other fields (``dropped``, ``name``) are kept.

        Args:
            rows: a slice, a boolean mask or indices.

        Returns:
            The labels ``rows``.
        """
        arrays = {
            f.name: getattr(self, f.name)[rows]
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }
        return dataclasses.replace(self, **arrays)

    def _steps(self) -> np.ndarray:
        """Each label's share of labelled time: the step to the one before, at most the
        median step (dropped stretches do not count); the first label one median step."""
        if len(self) < 2:
            return np.zeros(len(self))
        dt = np.diff(self.t, prepend=-np.inf)
        med = float(np.median(dt[1:]))
        return np.minimum(dt, med)

    @property
    def seconds(self) -> float:
        """Seconds of labelled flight (time in the air, not wall-clock)."""
        return float(self._steps().sum())

    def first(self, seconds: float) -> Labels:
        """The labels of the first ``seconds`` of labelled flight.

        Labelled time as in :attr:`seconds`: dropped stretches do not count.

        Args:
            seconds: s of labelled flight to keep.

        Returns:
            The first labels, up to ``seconds``.
        """
        return self.take(np.cumsum(self._steps()) <= seconds + 1e-9)

    @classmethod
    def concatenate(cls, parts: Sequence[Labels]) -> Labels:
        """Labels of several flights as one set.

        Times are kept as they are (not made continuous); ``dropped`` counts are summed and
        the names joined with ``+``; the other fields are the first part's.

        Args:
            parts: the flights' labels.

        Returns:
            The labels of all parts, in order.

        Raises:
            ValueError: ``parts`` is empty, or some parts have body rates and others not.
        """
        if not parts:
            raise ValueError("concatenate needs at least one Labels")
        with_rates = [p.rates is not None for p in parts]
        if any(with_rates) and not all(with_rates):
            raise ValueError(
                "concatenate: parts "
                f"{[p.name for p, w in zip(parts, with_rates, strict=True) if not w]} have no "
                "body rates (rates) where the others have them; label them again"
            )
        arrays = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in dataclasses.fields(cls)
            if isinstance(getattr(parts[0], f.name), np.ndarray)
        }
        dropped: dict[str, int] = {}
        for p in parts:
            for k, v in p.dropped.items():
                dropped[k] = dropped.get(k, 0) + v
        return dataclasses.replace(
            parts[0], **arrays, dropped=dropped, name="+".join(p.name for p in parts)
        )


def label(
    log: FlightLog,
    vehicle: Vehicle,
    *,
    reference: SimpleModel | Surrogate | None = None,
    rate: float = 10.0,
    source: str = "auto",
    delay: float | str = "estimate",
    max_delay: float = 0.1,
    curve: MotorCurve | None = None,
    takeoff_s: float = 2.0,
    saturation: float = SATURATION,
) -> Labels:
    """Aerodynamic force and torque labels of a flight, with their noise (module docstring).

    Args:
        log: the flight (:func:`gpg.flight.read_csv`, :func:`gpg.flight.read_ulog`).
        vehicle: its mass, inertia, gravity, rotor range and layout.
        reference: what the residuals are taken against: ``None`` for the simplified model
            ``M`` of the vehicle file (its ``simple_model`` coefficients), a
            :class:`~gpg.quadrotor.simple_model.SimpleModel`, or a fitted
            :class:`~gpg.Surrogate` (its mean prediction).
        rate: labels per second (Hz), at most the log's rate.
        source: ``"imu"`` (the specific force), ``"velocity"`` (spline derivative) or
            ``"auto"`` (the IMU when the log has it).
        delay: the rotor-speed channel's lag behind the IMU (s), or ``"estimate"``: the lag in
            ``[-max_delay, max_delay]`` that best correlates the fast parts (under
            :data:`DELAY_HIGHPASS_S`) of ``M``'s thrust and the measured one (rotor speeds from
            ESC telemetry lag the IMU); 0 for a log slower than 20 Hz, and 0 with a
            :class:`~gpg.flight.log.FlightLogWarning` where the best lag is at the bound; 0 for
            speeds from commands (the curve's ``time_constant`` is their lag). One log tells
            it roughly: :func:`estimate_delay` gives one lag from many logs.
        curve: motor commands to rotor speeds, for a log without rotor speeds (default: fitted
            from the log's hover, :meth:`MotorCurve.fit_hover`); its ``time_constant`` lags
            the speeds behind the commands (one of 0 on a vehicle whose motors lag is warned
            of: a :class:`~gpg.flight.log.FlightLogWarning`).
        takeoff_s: seconds dropped after each take-off and before each landing.
        saturation: a rotor at this fraction of its speed range (or command) is saturated;
            1.0 keeps every sample short of the bounds themselves (an online filter's
            stream, read at the log's own ``rate``: at the default's instants its loads,
            noise, rotor speeds and air velocity are the default labels' bit for bit, the
            attitude and the reference's loads, computed in batches of another size, to
            rounding). The rotor speeds' lag is estimated on the samples the default keeps,
            whatever this keeps.

    Returns:
        :class:`Labels` at ``rate`` Hz over the labelled stretches of the flight.

    Raises:
        ValueError: ``source="imu"`` on a log without specific force; ``reference=None`` for
            a vehicle file without ``simple_model`` coefficients; rotor speeds that look like
            rad/s (their airborne median far below the vehicle's hover speed and near it in
            rad/s); no sample left to label; a bad option.
    """
    _check_label_options(log, vehicle, reference, rate, source, delay, max_delay, curve)
    _check_segment_options(takeoff_s, saturation)
    src = _source(log, source)
    simple = _simple(vehicle, reference)
    m, g = float(vehicle.mass), float(vehicle.gravity)
    rpm = log.rpm
    if rpm is None:
        if curve is None:
            curve = MotorCurve.fit_hover(log, vehicle, simple)
        _warn_unlagged(log.name, curve, vehicle)
        rpm = curve.rpm(log.command, log.voltage, log.t)
    _check_rpm_unit(log.name, rpm, simple, m * g)
    thrust_M = (rpm**2).sum(1) * float(simple.P_F)
    R = log.R_WB()

    dt = float(np.median(np.diff(log.t)))
    _warn_interpolated(log, src)
    keep, clean, drop = _where_to_label(log, vehicle, rpm, thrust_M, dt, takeoff_s, saturation)
    F_B, F_var_B, tau_B, tau_var_B, edges = _measured_loads(log, vehicle, R, src, dt)
    drop["edges"] = int((keep & edges).sum())
    keep, clean = keep & ~edges, clean & ~edges

    # The rotor-speed channel's lag, removed by reading it that much later. Speeds from
    # commands have none to remove: the curve's own lag is the motors'.
    if delay == "estimate" and log.rpm is None:
        lag = 0.0
    elif delay == "estimate":
        lag = _estimate_delay(log.t, thrust_M, -F_B[:, 2], clean, max_delay)
    else:
        lag = float(delay)
    if lag != 0.0:
        rpm = np.stack([np.interp(log.t + lag, log.t, rpm[:, i]) for i in range(4)], 1)

    # Decimate to the label rate.
    step = max(1, int(round(1.0 / (rate * dt))))
    rows = np.flatnonzero(keep)
    rows = rows[(np.round((log.t[rows] - log.t[0]) / dt).astype(np.int64) % step) == 0]
    if rows.size == 0:
        raise ValueError(
            f"{log.name}: no sample left to label ({_dropped_text(drop)}); is the vehicle "
            "airborne in this log, and are the rotor speeds in rpm?"
        )
    loads = (F_B[rows], F_var_B[rows], tau_B[rows], tau_var_B[rows])
    return _labels(log, rows, R[rows], rpm[rows], loads, reference, simple, drop, lag, src)


def _warn_unlagged(name: str, curve: MotorCurve, vehicle: Vehicle) -> None:
    """A :class:`~gpg.flight.log.FlightLogWarning` where a curve without a lag reads the
    commands of a vehicle whose motors have one: its speeds lead the rotors' by the time
    constant, a bias the identification then spreads over the rotor and the drag."""
    tau = float(vehicle.motor_time_constant)
    if curve.time_constant == 0.0 and tau > 0.0:
        warnings.warn(
            f"{name}: the motor curve has no lag (time_constant 0) but the vehicle's "
            f"motor.time_constant is {tau:g} s: its speeds lead the rotors' by that much (a "
            f"bench curve is static); give the curve time_constant={tau:g} "
            "(MotorCurve.fit_speeds(..., time_constant=...))",
            FlightLogWarning,
            stacklevel=3,
        )


def _source(log: FlightLog, source: str) -> str:
    """``source`` with ``"auto"`` resolved: the IMU where the log has it, else the velocity;
    ``"imu"`` on a log without specific force refused by name."""
    if source == "imu" and log.specific_force is None:
        raise ValueError(f"{log.name}: source='imu' but the log has no specific force (ax..az)")
    if source == "auto":
        return "imu" if log.specific_force is not None else "velocity"
    return source


def _check_segment_options(takeoff_s, saturation) -> None:
    """``label``'s ``takeoff_s`` and ``saturation``, refused by name."""
    if (
        not (0 < finite_number("saturation", saturation) <= 1)
        or finite_number("takeoff_s", takeoff_s) < 0
    ):
        raise ValueError(f"saturation must be in (0, 1], got {saturation!r}; takeoff_s >= 0")


def _check_label_options(log, vehicle, reference, rate, source, delay, max_delay, curve):
    """``label``'s arguments, each refused by name with what was expected."""
    if not isinstance(log, FlightLog):
        raise ValueError(f"log must be a FlightLog (read_csv, read_ulog), got {type(log).__name__}")
    check_label_arguments(vehicle, reference, rate, source, delay, max_delay, curve,
                          max_rate=log.rate)  # fmt: skip


def check_label_arguments(
    vehicle, reference, rate, source, delay, max_delay, curve, *, max_rate: float = math.inf
) -> None:
    """:func:`label`'s arguments but the log, each refused by name with what was expected
    (``rate`` at most ``max_rate``, the log's rate where there is one): what
    :func:`gpg.flight.batch.label_logs` checks once before any log is read."""
    from gpg.surrogate import Surrogate

    if not isinstance(vehicle, Vehicle):
        raise ValueError(
            f"vehicle must be a Vehicle (gpg.quadrotor.vehicle.load_vehicle({vehicle!r}) for a "
            f"vehicle file's name), got {type(vehicle).__name__}"
        )
    if reference is not None and not isinstance(reference, (SimpleModel, Surrogate)):
        raise ValueError(
            f"reference must be None, a SimpleModel or a Surrogate, got {type(reference).__name__}"
        )
    if curve is not None and not isinstance(curve, MotorCurve):
        raise ValueError(f"curve must be a MotorCurve or None, got {type(curve).__name__}")
    if not isinstance(source, str) or source not in ("auto", "imu", "velocity"):
        raise ValueError(f"source must be 'auto', 'imu' or 'velocity', got {source!r}")
    if not (0 < finite_number("rate", rate) <= max_rate * 1.001):
        bound = "" if math.isinf(max_rate) else f" (the log's rate, {max_rate:.4g} Hz, at most)"
        raise ValueError(f"rate must be positive{bound}, got {rate!r}")
    if not 0 <= finite_number("max_delay", max_delay) <= MAX_DELAY_S:
        raise ValueError(f"max_delay must be in [0, {MAX_DELAY_S:g}] s, got {max_delay!r}")
    if isinstance(delay, str):
        if delay != "estimate":
            raise ValueError(f"delay must be 'estimate' or a number of seconds, got {delay!r}")
    elif abs(finite_number("delay", delay)) > MAX_DELAY_S:
        raise ValueError(
            f"delay is in seconds and at most {MAX_DELAY_S:g} s (a rotor-speed lag is tens of "
            f"ms: 20 ms is 0.02), got {delay!r}"
        )


def _warn_interpolated(log: FlightLog, src: str) -> None:
    """Warn where a signal the labels' noise is estimated from looks linearly interpolated
    between fewer samples: its second differences vanish, and so would the noise estimate."""
    force = ("specific_force", log.specific_force) if src == "imu" else ("velocity", log.velocity)
    for name, y in (("rates", log.rates), force):
        d1 = np.abs(np.diff(y, axis=0))
        scale = d1[1:] + d1[:-1]
        moving = scale > 0
        flat = np.abs(np.diff(y, 2, axis=0)) <= 1e-9 * scale
        share = float(flat[moving].mean()) if moving.any() else 0.0
        if share > INTERPOLATED_SHARE:
            warnings.warn(
                f"{log.name}: {name} looks linearly interpolated between fewer samples "
                f"({share:.0%} of its second differences vanish): the labels' noise estimate "
                "would see no noise there; read the log at the rate of its own samples",
                FlightLogWarning,
                stacklevel=3,
            )


def _labels(log, rows, Rk, rpm, loads, reference, simple, drop, lag, src) -> Labels:
    """The labels at ``rows``: the body-frame loads and variances rotated into the world, the
    state, the reference model there."""
    F_B, F_var_B, tau_B, tau_var_B = loads
    euler = np.asarray(_euler_batch(Rk))
    wind = np.zeros((rows.size, 3)) if log.wind is None else log.wind[rows]
    v_air = log.velocity[rows] - wind
    model_force, model_torque = _reference(reference, simple, rpm, euler, v_air)
    return Labels(
        t=log.t[rows],
        rpm=rpm,
        euler=euler,
        v_air=v_air,
        force=np.einsum("nij,nj->ni", Rk, F_B),
        torque=np.einsum("nij,nj->ni", Rk, tau_B),
        force_var=_rotate_var(Rk, F_var_B),
        torque_var=_rotate_var(Rk, tau_var_B),
        model_force=model_force,
        model_torque=model_torque,
        dropped=drop,
        delay=lag,
        source=src,
        name=log.name,
        rates=np.asarray(log.rates, float)[rows],
    )


def _where_to_label(log, vehicle, rpm, thrust_M, dt, takeoff_s, saturation):
    """Samples airborne, away from take-off and landing, unsaturated; the same at the default
    :data:`SATURATION` where ``saturation`` keeps more (the rotor speeds' lag is estimated
    there: a saturated rotor's speed does not follow its thrust, and a stream that keeps
    those samples keeps the default labels' lag, so it holds their rotor speeds); and the
    counts dropped."""
    m, g = float(vehicle.mass), float(vehicle.gravity)
    n = log.t.size
    # On the ground: little thrust, no motion, for a while (a brief low-thrust moment in the
    # air, a fast descent, is flight).
    still = (thrust_M < GROUND_THRUST * m * g) & (np.linalg.norm(log.velocity, axis=1) < 1.0)
    k = max(1, int(round(GROUND_MIN_S / dt)))
    ground = ndimage.binary_opening(still, structure=np.ones(k, bool)) if n > k else still
    drop = {"total": n, "ground": int(ground.sum())}
    air = ~ground
    near = _near_transitions(air, int(round(takeoff_s / dt)))
    drop["takeoff_landing"] = int((near & air).sum())

    def saturated(level):
        sat = rpm >= vehicle.rpm_min + level * (vehicle.rpm_max - vehicle.rpm_min)
        if log.command is not None:
            sat |= (log.command >= level) | (air[:, None] & (log.command <= 1 - level))
        return ndimage.binary_dilation(sat.any(1), iterations=max(1, int(SATURATION_PAD_S / dt)))

    sat = saturated(saturation)
    keep = air & ~near
    drop["saturated"] = int((keep & sat).sum())
    clean = keep & ~saturated(SATURATION) if saturation > SATURATION else keep & ~sat
    return keep & ~sat, clean, drop


def _measured_loads(log, vehicle, R, src: str, dt: float):
    """Body-frame force and torque from the motion, with their noise variances, per segment
    (split at gaps), and the samples at the segments' ends (one-sided splines)."""
    m, g = float(vehicle.mass), float(vehicle.gravity)
    J = np.asarray(vehicle.inertia, float)
    n = log.t.size
    F_B, F_var_B = np.zeros((n, 3)), np.zeros((n, 3))
    tau_B, tau_var_B = np.zeros((n, 3)), np.zeros((n, 3))
    edges = np.zeros(n, bool)
    for seg in _segments(log.t, dt):
        ts = log.t[seg]
        e = max(1, int(round(EDGE_S / dt)))
        edges[seg.start : seg.start + e] = True
        edges[seg.stop - e : seg.stop] = True
        if ts.size < 8:
            edges[seg] = True
            continue
        wdot, wdot_var = _smooth(ts, log.rates[seg], deriv=True)
        w = log.rates[seg]
        tau_B[seg] = J * wdot + np.cross(w, J * w)
        tau_var_B[seg] = J**2 * wdot_var
        if src == "imu":
            f, f_var = _smooth(ts, log.specific_force[seg], deriv=False)
            # The attitude's own noise turns the force: δF = R (δθ × F_B), |δF|² ≤ |F|²σ_θ².
            att = _attitude_noise_var(R[seg], max(3, int(round(NOISE_WINDOW_S / dt))))
            F_B[seg] = m * f
            F_var_B[seg] = m * m * (f_var + att[:, None] * np.sum(f * f, 1, keepdims=True))
        else:
            a, a_var = _smooth(ts, log.velocity[seg], deriv=True)
            F_W = m * (a - np.array([0.0, 0.0, g]))
            F_B[seg] = np.einsum("nji,nj->ni", R[seg], F_W)
            F_var_B[seg] = _rotate_var(np.swapaxes(R[seg], 1, 2), m * m * a_var)
    return F_B, F_var_B, tau_B, tau_var_B, edges


def _simple(vehicle: Vehicle, reference) -> SimpleModel:
    from gpg.surrogate import Surrogate

    if isinstance(reference, SimpleModel):
        return reference
    if isinstance(reference, Surrogate) and reference.simple is not None:
        return reference.simple
    if vehicle.thrust_coefficient is None:
        raise ValueError(
            f"vehicle {vehicle.name!r} has no simple_model coefficients: pass reference= a "
            "SimpleModel or a fitted Surrogate (its M)"
        )
    return SimpleModel.from_vehicle(vehicle, vehicle.thrust_coefficient, vehicle.torque_coefficient)


def _reference(reference, simple: SimpleModel, rpm, euler, v_air):
    from gpg.surrogate import Surrogate

    if isinstance(reference, Surrogate):
        p = reference.predict_batch(rpm, euler, v_air, mean_only=True)
        return np.asarray(p.force), np.asarray(p.torque)
    y = np.asarray(simple.values(np.concatenate([rpm, euler], 1)))
    return y[:, :3], y[:, 3:6]


def _check_rpm_unit(name: str, rpm: np.ndarray, simple: SimpleModel, weight: float) -> None:
    hover = float(simple.hover_rpm(weight))
    turning = rpm[rpm.max(1) > 0]
    if turning.size == 0:
        return
    med = float(np.median(turning))
    rad_s = hover * 2 * np.pi / 60
    if med < 0.3 * hover and abs(np.log(med / rad_s)) < np.log(3.0):
        raise ValueError(
            f"{name}: rotor speeds look like rad/s, not rpm: their median while turning is "
            f"{med:.4g}, the vehicle hovers near {hover:.4g} rpm = {rad_s:.4g} rad/s (read the "
            "log with rotor_speed='rad/s')"
        )


def _segments(t: np.ndarray, dt: float) -> list[slice]:
    cut = np.flatnonzero(np.diff(t) > GAP_FACTOR * dt) + 1
    bounds = np.concatenate([[0], cut, [t.size]])
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _near_transitions(air: np.ndarray, k: int) -> np.ndarray:
    """Samples within ``k`` of a ground/air change (take-off, landing)."""
    change = np.flatnonzero(np.diff(air.astype(np.int8)) != 0)
    near = np.zeros(air.size, bool)
    for c in change:
        near[max(0, c - k + 1) : c + k + 1] = True
    return near


def _noise_var(y: np.ndarray, window: int) -> np.ndarray:
    """Per-sample white-noise variance of ``y`` (T,) from its second differences."""
    d2 = np.zeros_like(y)
    d2[1:-1] = y[2:] - 2 * y[1:-1] + y[:-2]
    d2[0], d2[-1] = d2[1], d2[-2]
    # MAD → σ for a Gaussian; Var Δ²y = 6σ²
    mad = ndimage.median_filter(np.abs(d2), size=max(3, window), mode="nearest")
    return (1.4826 * mad) ** 2 / 6.0


def _attitude_noise_var(R: np.ndarray, window: int) -> np.ndarray:
    """Per-sample variance (rad²) of the attitude's white noise, per axis: the second
    differences of the increments ``log(R_kᵀ R_{k+1})`` (the rotation itself is smooth)."""
    from scipy.spatial.transform import Rotation

    if R.shape[0] < 4:
        return np.zeros(R.shape[0])
    inc = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec()
    d = np.diff(inc, axis=0)  # n_{k+2} − 2 n_{k+1} + n_k: variance 6σ² per axis
    mad = ndimage.median_filter(np.abs(d).mean(1), size=window, mode="nearest")
    var = (1.4826 * mad) ** 2 / 6.0
    return np.concatenate([var[:1], var, var[-1:]])


def _lam(t: np.ndarray, y: np.ndarray) -> float:
    """The smoothing parameter of one signal ``y`` (T,) by generalised cross-validation,
    ``GCV(λ) = RSS(λ) / (1 − tr H(λ)/n)²``, on the window of :data:`GCV_WINDOW` samples where
    the signal varies most (a manoeuvre: a calm window would choose a smoothing that flattens
    the manoeuvres). ``tr H/n`` is the smoother's weight on a sample's own value, from its
    frequency response on a uniform grid (:func:`_self_weight`)."""
    n = t.size
    w = min(n, GCV_WINDOW)
    a = 0
    if n > w:
        c = np.concatenate([[0.0], np.cumsum(y - y.mean())])
        c2 = np.concatenate([[0.0], np.cumsum((y - y.mean()) ** 2)])
        var = (c2[w:] - c2[:-w]) / w - ((c[w:] - c[:-w]) / w) ** 2
        a = int(np.argmax(var))
    ts, ys = t[a : a + w], y[a : a + w]
    dt = float(np.median(np.diff(ts)))

    def gcv(log_lam: float) -> float:
        lam = 10.0**log_lam
        rss = float(np.mean((make_smoothing_spline(ts, ys, lam=lam)(ts) - ys) ** 2))
        return rss / (1.0 - _self_weight(dt, lam)) ** 2

    # λ from a time scale (λ dt)^¼ of one sample to a tenth of the window: a window cannot
    # tell a slow signal from a polynomial, and would smooth it away over the whole flight.
    h_max = max(0.1 * (ts[-1] - ts[0]), 2 * dt)
    lo, hi = np.log10(dt**3), np.log10(h_max**4 / dt)
    res = optimize.minimize_scalar(gcv, bounds=(lo, hi), method="bounded", options={"xatol": 0.1})
    return float(10.0**res.x)


def _self_weight(dt: float, lam: float) -> float:
    """A uniform-grid smoothing spline's weight on each sample's own value: its transfer
    function ``1/(1 + λ dt ω⁴)`` (Reinsch's, per unit time) averaged up to the Nyquist rate."""
    w = np.linspace(0.0, np.pi / dt, 2049)
    return float(np.trapezoid(1.0 / (1.0 + lam * dt * w**4), w) * dt / np.pi)


def _gain(dt: float, lam: float, deriv: bool) -> float:
    """``Σ_k h_k²`` of the spline's impulse response at an interior sample (value or
    derivative), on a uniform grid of step ``dt``."""
    k = 801
    t = np.arange(k) * dt
    e = np.zeros(k)
    e[k // 2] = 1.0
    spl = make_smoothing_spline(t, e, lam=lam)
    h = spl.derivative()(t) if deriv else spl(t)
    return float(np.sum(h**2))


def _smooth(t: np.ndarray, y: np.ndarray, deriv: bool) -> tuple[np.ndarray, np.ndarray]:
    """Smoothing-spline value or derivative of ``y`` (T, C) and its noise variance (T, C),
    each component with its own smoothing parameter."""
    dt = float(np.median(np.diff(t)))
    window = max(3, int(round(NOISE_WINDOW_S / dt)))
    out = np.empty_like(y)
    var = np.empty_like(y)
    for j in range(y.shape[1]):
        lam = _lam(t, y[:, j])
        spl = make_smoothing_spline(t, y[:, j], lam=lam)
        out[:, j] = spl.derivative()(t) if deriv else spl(t)
        var[:, j] = _noise_var(y[:, j], window) * _gain(dt, lam, deriv)
    return out, var


def _rotate_var(R: np.ndarray, var: np.ndarray) -> np.ndarray:
    """``diag(R diag(var) Rᵀ)`` per row: independent components' variances, rotated."""
    return np.einsum("nij,nj->ni", R**2, var)


def _delay_correlation(t, model, measured, keep, max_delay: float):
    """The lags ``k`` (samples) within ``[-max_delay, max_delay]``, the correlation at each of
    the fast parts (under :data:`DELAY_HIGHPASS_S`) of ``M``'s thrust read ``k`` samples later
    against the measured one over the kept samples, and the sample step ``dt`` (s); None where
    the log cannot tell (too slow, or too few samples)."""
    dt = float(np.median(np.diff(t)))
    k = max(1, int(round(max_delay / dt)))
    if keep.sum() < 4 * k + 8:
        return None
    # Only the fast part carries the lag: slower changes of the measured thrust also follow
    # drag and attitude, which lead or lag the rotor speeds in closed loop.
    hp = int(round(DELAY_HIGHPASS_S / dt))
    if hp < 4:
        return None  # a log too slow to see a lag of this size

    def highpass(x):
        return x - ndimage.uniform_filter1d(x, hp, mode="nearest")

    a, b = highpass(model), highpass(measured)
    idx = np.flatnonzero(keep)
    idx = idx[(idx >= k) & (idx < t.size - k)]
    lags = np.arange(-k, k + 1)
    # model read at i + lag against the measurement at i
    return lags, np.array([np.dot(a[idx + lag], b[idx]) for lag in lags]), dt


def _delay_peak(lags: np.ndarray, c: np.ndarray, dt: float, max_delay: float,
                stacklevel: int) -> float:  # fmt: skip
    """The lag (s) of the correlation's peak (``lags`` in samples of ``dt``), refined by a
    parabola between samples; 0 with a :class:`FlightLogWarning` where the peak is at the
    bound."""
    j = int(np.argmax(c))
    if j in (0, lags.size - 1):
        warnings.warn(
            f"the rotor speeds' lag behind the IMU is not within ±{max_delay:g} s (the best "
            "alignment is at the bound): none removed; give delay= if it is known",
            FlightLogWarning,
            stacklevel=stacklevel,
        )
        return 0.0
    shift = float(lags[j])
    den = c[j - 1] - 2 * c[j] + c[j + 1]
    if den < 0:
        shift += 0.5 * (c[j - 1] - c[j + 1]) / den
    return shift * dt


def _estimate_delay(t, model, measured, keep, max_delay: float) -> float:
    corr = _delay_correlation(t, model, measured, keep, max_delay)
    return 0.0 if corr is None else _delay_peak(*corr, max_delay, stacklevel=4)


def estimate_delay(
    logs: Sequence[FlightLog],
    vehicle: Vehicle,
    *,
    reference: SimpleModel | Surrogate | None = None,
    source: str = "auto",
    max_delay: float = 0.1,
    takeoff_s: float = 2.0,
) -> float:
    """One rotor-speed lag behind the IMU for several logs of the same vehicle and telemetry.

    :func:`label` estimates the lag on each log alone, from the fast parts of ``M``'s thrust
    and the measured one; a minute of flight leaves that estimate tens of milliseconds off
    (the guide has the figures). The lag is the telemetry's, the same in every log of a
    vehicle: this sums every log's correlation curve (each weighted by its own length and
    excitation) and takes the one peak, for ``label(log, vehicle, delay=lag)``.

    Args:
        logs: flights with rotor speeds and an IMU or velocity (as :func:`label` reads them).
        vehicle: their vehicle (:func:`label`).
        reference: ``M`` as for :func:`label`.
        source: the measured force's source, as for :func:`label`.
        max_delay: s, the lags searched: ``[-max_delay, max_delay]``.
        takeoff_s: s dropped after each take-off and before each landing, as for
            :func:`label`.

    Returns:
        The lag, s (positive: the rotor speeds come late); 0 with a
        :class:`~gpg.flight.log.FlightLogWarning` where the summed curve peaks at a bound.
        For one log it is :func:`label`'s own estimate.

    Raises:
        ValueError: no log, a log without rotor speeds (speeds from commands have no
            telemetry lag: the curve's ``time_constant`` is the motors'), rotor speeds that
            look like rad/s, a bad option as :func:`label` refuses it, or no log long and fast
            enough to tell a lag.
    """
    logs = [logs] if isinstance(logs, FlightLog) else list(logs)
    if not logs:
        raise ValueError("estimate_delay needs one or more flight logs")
    _check_segment_options(takeoff_s, SATURATION)
    simple = _simple(vehicle, reference)
    weight = float(vehicle.mass) * float(vehicle.gravity)
    curves = []
    for log in logs:
        if not isinstance(log, FlightLog):
            raise ValueError(f"estimate_delay reads FlightLogs, got {type(log).__name__}")
        _check_label_options(log, vehicle, reference, 1.0, source, "estimate", max_delay, None)
        if log.rpm is None:
            raise ValueError(
                f"{log.name}: no rotor speeds, no telemetry lag to estimate (speeds from "
                "commands lag by the motor curve's time_constant)"
            )
        src = _source(log, source)
        _check_rpm_unit(log.name, log.rpm, simple, weight)
        thrust_M = (log.rpm**2).sum(1) * float(simple.P_F)
        dt = float(np.median(np.diff(log.t)))
        _, clean, _ = _where_to_label(log, vehicle, log.rpm, thrust_M, dt, takeoff_s,
                                      SATURATION)  # fmt: skip
        F_B, _, _, _, edges = _measured_loads(log, vehicle, log.R_WB(), src, dt)
        corr = _delay_correlation(log.t, thrust_M, -F_B[:, 2], clean & ~edges, max_delay)
        if corr is not None:
            curves.append(corr)
    if not curves:
        raise ValueError(
            f"estimate_delay: none of the {len(logs)} log(s) is long and fast enough to tell a "
            f"lag within ±{max_delay:g} s (20 Hz or faster, seconds of flight)"
        )
    # One grid: the finest log's samples; a log at another rate is read between its lags.
    grid, _, step = min(curves, key=lambda lc: lc[2])
    total = sum(np.interp(grid * step, lags * dt, c) for lags, c, dt in curves)
    return _delay_peak(grid, total, step, max_delay, stacklevel=3)


def _dropped_text(drop: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in drop.items())
