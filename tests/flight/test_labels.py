"""gpg.flight.labels: loads from measured motion against closed forms, noise, dropped segments,
delays, motor curves and calibration."""

import dataclasses
import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight.labels import Labels, MotorCurve, calibrate_simple, hover_samples, label
from gpg.flight.log import FlightLog, FlightLogWarning, matrix_to_quat
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import load_vehicle

RATE = 200.0
P_F, T_Z = 5.3e-7, 8.4e-9


@pytest.fixture(scope="module")
def veh():
    return load_vehicle("sui_endurance")


@pytest.fixture(scope="module")
def M(veh):
    return SimpleModel.from_vehicle(veh, P_F, T_Z)


def _yaw_quat(yaw):
    return np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], 1)


def _hover_rpm(veh, M):
    return float(M.hover_rpm(float(veh.weight)))


def _log(veh, M, T=10.0, *, v=None, f_B=None, w=None, yaw=None, rpm=None, **kw):
    t = np.arange(int(T * RATE)) / RATE
    n = t.size
    zeros = np.zeros((n, 3))
    return FlightLog(
        t=t,
        position=np.tile([0.0, 0.0, -10.0], (n, 1)),
        velocity=zeros if v is None else v,
        quaternion=_yaw_quat(np.zeros(n) if yaw is None else yaw),
        rates=zeros if w is None else w,
        rpm=np.full((n, 4), _hover_rpm(veh, M)) if rpm is None else rpm,
        specific_force=f_B,
        **kw,
    )


def test_force_from_velocity_closed_form(veh, M):
    """``F_W = m (v̇ − g e_z)`` by the spline derivative, level attitude: against ``v̇`` written
    out. The tolerance is the cubic smoothing spline's bias on these slow signals (at most
    1e-3 m/s² for periods of seconds sampled at 200 Hz, seen with a 20x margin) times m."""
    t = np.arange(int(10 * RATE)) / RATE
    v = np.stack([np.sin(t), 0.5 * np.cos(2 * t), 0.2 * np.sin(0.5 * t)], 1)
    a = np.stack([np.cos(t), -np.sin(2 * t), 0.1 * np.cos(0.5 * t)], 1)
    v = v + 1e-7 * np.random.default_rng(0).normal(size=v.shape)
    lab = label(_log(veh, M, v=v), veh, reference=M, delay=0.0)
    assert lab.source == "velocity" and len(lab) > 80
    i = np.searchsorted(t, lab.t)
    m, g = float(veh.mass), float(veh.gravity)
    expect = m * (a[i] - np.array([0.0, 0.0, g]))
    np.testing.assert_allclose(lab.force, expect, atol=m * 1e-3)
    # the residual is the measurement minus M at the same state (M: thrust along −z_B)
    thrust = P_F * 4 * _hover_rpm(veh, M) ** 2
    np.testing.assert_allclose(lab.model_force, np.tile([0, 0, -thrust], (len(lab), 1)), rtol=1e-12)
    np.testing.assert_allclose(lab.residual_force, lab.force - lab.model_force)


def test_torque_from_rates_closed_form(veh, M):
    """``τ_B = J ω̇ + ω × J ω`` by the spline derivative against ``ω̇`` written out; the body
    turns about z (yaw = 0.3 t), so ``τ_W = R_z(yaw) τ_B``."""
    t = np.arange(int(10 * RATE)) / RATE
    w = np.stack([0.3 * np.sin(2 * t), 0.2 * np.cos(t), 0.1 * np.sin(3 * t)], 1)
    wd = np.stack([0.6 * np.cos(2 * t), -0.2 * np.sin(t), 0.3 * np.cos(3 * t)], 1)
    yaw = 0.3 * t
    f_B = np.tile([0.0, 0.0, -float(veh.gravity)], (t.size, 1))
    lab = label(_log(veh, M, w=w + 1e-8, yaw=yaw, f_B=f_B), veh, reference=M, delay=0.0)
    assert lab.source == "imu"
    i = np.searchsorted(t, lab.t)
    J = np.asarray(veh.inertia)
    tau_B = J * wd[i] + np.cross(w[i], J * w[i])
    c, s = np.cos(yaw[i]), np.sin(yaw[i])
    tau_W = np.stack(
        [c * tau_B[:, 0] - s * tau_B[:, 1], s * tau_B[:, 0] + c * tau_B[:, 1], tau_B[:, 2]], 1
    )
    np.testing.assert_allclose(lab.torque, tau_W, atol=float(J.max()) * 1e-3)
    # hovering with the accelerometer reading −g: the force is −m g along z, rotated nowhere
    np.testing.assert_allclose(
        lab.force, np.tile([0, 0, -float(veh.weight)], (len(lab), 1)), atol=1e-9
    )
    np.testing.assert_allclose(lab.euler[:, 0], np.angle(np.exp(1j * yaw[i])), atol=1e-9)


def test_noise_estimate_matches_the_scatter(veh, M):
    """White noise of known σ on the accelerometer: the labels' estimated variance against
    their actual scatter about the truth (100 labels: the ratio of standard deviations is
    known to about 10 %; the upper end of the band also holds the smoothing's own bias, which
    the estimate leaves out: up to half the noise again where the smoothing is longest)."""
    rng = np.random.default_rng(1)
    t = np.arange(int(10 * RATE)) / RATE
    truth = np.stack([0.5 * np.sin(t), 0.3 * np.cos(1.5 * t), -9.81 + 0.4 * np.sin(0.7 * t)], 1)
    sigma = 0.05
    lab = label(
        _log(veh, M, f_B=truth + sigma * rng.normal(size=truth.shape)), veh, reference=M, delay=0.0
    )
    i = np.searchsorted(t, lab.t)
    z = (lab.force - float(veh.mass) * truth[i]) / np.sqrt(lab.force_var)
    assert np.all((z.std(0) > 0.75) & (z.std(0) < 1.8)), z.std(0)
    # the estimate is of the smoothed label, far below the raw noise
    assert np.all(np.sqrt(lab.force_var) < float(veh.mass) * sigma)


def test_dropped_segments_counted(veh, M):
    n = int(20 * RATE)
    rpm = np.full((n, 4), _hover_rpm(veh, M))
    rpm[:400] = 0.0  # on the ground for 2 s
    rpm[2000:2010, 1] = float(veh.rpm_max)  # a rotor saturated for 10 samples
    f_B = np.tile([0.0, 0.0, -9.81], (n, 1))
    lab = label(_log(veh, M, T=20.0, f_B=f_B, rpm=rpm), veh, reference=M, delay=0.0, takeoff_s=1.0)
    d = lab.dropped
    assert d["total"] == n and d["ground"] == 400
    assert d["takeoff_landing"] == 200  # the first second in the air
    assert 10 <= d["saturated"] <= 10 + 2 * 20 + 2  # padded by 0.1 s on each side
    assert d["edges"] == 20  # the segment's last 0.1 s (its first is on the ground)
    assert not np.any((lab.t > 9.89) & (lab.t < 10.16))


def test_every_sample_holds_the_labels_as_they_are(veh, M):
    """An online filter's stream (every sample, a saturated rotor's too) holds the default
    labels at their instants: the loads are estimated on the whole log before any sample
    is chosen (bit for bit), and the rotor speeds' lag on the samples the default keeps.
    Here the telemetry lags the IMU by 30 ms but leads it where a rotor is saturated (62 % of
    the time), so a lag estimated on every sample would differ."""
    rng = np.random.default_rng(5)
    n = int(20 * RATE)
    t = np.arange(n) / RATE
    wiggle = np.convolve(rng.normal(size=n + 200), np.hanning(41), "same")[100:-100]
    wiggle /= np.abs(wiggle).max()
    rpm_true = _hover_rpm(veh, M) * (1 + 0.05 * wiggle)[:, None] * np.ones(4)
    sat = (t % 4.0) >= 1.5
    lo, hi = float(veh.rpm_min), float(veh.rpm_max)
    rpm_true[sat, 1] = lo + (0.99 + 0.005 * wiggle[sat]) * (hi - lo)  # under 1.0 of the range
    f_B = np.stack([np.zeros(n), np.zeros(n), -P_F * (rpm_true**2).sum(1) / float(veh.mass)], 1)
    lag = 6  # samples: 30 ms
    late = np.concatenate([np.repeat(rpm_true[:1], lag, 0), rpm_true[:-lag]])
    early = np.concatenate([rpm_true[lag:], np.repeat(rpm_true[-1:], lag, 0)])
    log = _log(veh, M, T=20.0, f_B=f_B, rpm=np.where(sat[:, None], early, late))
    labels = label(log, veh, reference=M)
    stream = label(log, veh, reference=M, rate=RATE, saturation=1.0)
    assert abs(labels.delay - lag / RATE) < 1 / RATE and stream.delay == labels.delay
    assert labels.dropped["saturated"] >= 0.6 * n and stream.dropped["saturated"] == 0
    assert len(stream) > 15 * len(labels)
    at = np.isin(stream.t, labels.t)
    assert at.sum() == len(labels)
    shared = stream.take(at)
    for key in ("t", "rpm", "v_air", "force", "torque", "force_var", "torque_var"):
        np.testing.assert_array_equal(getattr(shared, key), getattr(labels, key), err_msg=key)
    # JAX computes these in batches of another size (the attitude's angles, M's loads): a
    # compiler may round them apart, by a few units in the last place of their magnitudes
    for key in ("euler", "model_force", "model_torque"):
        b = getattr(labels, key)
        atol = 16 * np.finfo(float).eps * max(np.abs(b).max(), np.pi)
        np.testing.assert_allclose(getattr(shared, key), b, rtol=0, atol=atol, err_msg=key)
    assert np.any(stream.rpm[:, 1] > lo + 0.98 * (hi - lo))  # the saturated stretches are in


def test_rotor_speed_units_and_rate_checked(veh, M):
    rpm = np.full((2000, 4), _hover_rpm(veh, M) * 2 * np.pi / 60)
    with pytest.raises(ValueError, match="look like rad/s"):
        label(_log(veh, M, rpm=rpm, f_B=np.tile([0, 0, -9.81], (2000, 1))), veh, reference=M)
    with pytest.raises(ValueError, match=r"at most\), got 500"):
        label(_log(veh, M), veh, reference=M, rate=500.0)
    with pytest.raises(ValueError, match="no specific force"):
        label(_log(veh, M), veh, reference=M, source="imu")
    with pytest.raises(ValueError, match="no simple_model coefficients"):
        label(_log(veh, M), veh)


def _lagged_logs(veh, M, k, sigma, T=6.0, lag=6):
    """``k`` logs whose rotor speeds come ``lag`` samples late, each with its own band-limited
    speed changes and white noise ``sigma`` (m/s²) on the specific force."""
    out = []
    for i in range(k):
        rng = np.random.default_rng(10 + i)
        n = int(T * RATE)
        wiggle = np.convolve(rng.normal(size=n + 200), np.hanning(41), "same")[100:-100]
        rpm = _hover_rpm(veh, M) * (1 + 0.02 * wiggle / np.abs(wiggle).max())[:, None] * np.ones(4)
        f_B = np.zeros((n, 3))
        f_B[:, 2] = -P_F * (rpm**2).sum(1) / float(veh.mass)
        f_B += sigma * rng.normal(size=(n, 3))
        late = np.concatenate([np.repeat(rpm[:1], lag, 0), rpm[:-lag]])
        out.append(_log(veh, M, T=T, f_B=f_B, rpm=late))
    return out


def test_delay_estimated_from_many_logs(veh, M):
    """``estimate_delay``: each log alone is ``label``'s own estimate exactly (the same curve
    and peak), a log twice is the log once (the curve doubled, the same peak); six noisy logs
    whose own estimates scatter by more than a sample give, summed, the 30 ms closer than
    their own RMS error (the sum averages their noise: about RMS/√6 expected) and within a
    sample. No log, a log without rotor speeds, or none long enough to tell: refused by
    name."""
    from gpg.flight.labels import estimate_delay

    logs = _lagged_logs(veh, M, 6, sigma=0.5)
    alone = [estimate_delay([lg], veh, reference=M, takeoff_s=0.0) for lg in logs]
    assert alone[0] == label(logs[0], veh, reference=M, takeoff_s=0.0).delay
    assert estimate_delay(logs[:1] * 2, veh, reference=M, takeoff_s=0.0) == alone[0]
    err = np.array(alone) - 6 / RATE
    assert np.max(np.abs(err)) > 1 / RATE  # alone, a sample off or more
    pooled = estimate_delay(logs, veh, reference=M, takeoff_s=0.0) - 6 / RATE
    assert abs(pooled) < min(np.sqrt(np.mean(err**2)), 1 / RATE)
    with pytest.raises(ValueError, match="one or more flight logs"):
        estimate_delay([], veh, reference=M)
    no_rpm = dataclasses.replace(_log(veh, M, T=2.0, f_B=np.zeros((400, 3))), rpm=None,
                                 command=np.full((400, 4), 0.5), name="calm")  # fmt: skip
    with pytest.raises(ValueError, match="calm: no rotor speeds"):
        estimate_delay([no_rpm], veh, reference=M)
    with pytest.raises(ValueError, match="none of the 1 log"):
        estimate_delay(_lagged_logs(veh, M, 1, sigma=0.5, T=0.3), veh, reference=M,
                       takeoff_s=0.0)  # fmt: skip


def test_delay_estimated(veh, M):
    """Rotor speeds logged 30 ms late: the lag that best aligns M's thrust with the measured one
    is found to within a sample, and removed."""
    rng = np.random.default_rng(2)
    n = int(20 * RATE)
    hover = _hover_rpm(veh, M)
    # band-limited rotor-speed changes (a few Hz), as a controller makes them
    wiggle = np.convolve(rng.normal(size=n + 200), np.hanning(41), "same")[100:-100]
    rpm_true = hover * (1 + 0.05 * wiggle / np.abs(wiggle).max())[:, None] * np.ones(4)
    thrust = P_F * (rpm_true**2).sum(1)
    f_B = np.stack([np.zeros(n), np.zeros(n), -thrust / float(veh.mass)], 1)
    lag = 6  # samples: 30 ms
    rpm_log = np.concatenate([np.repeat(rpm_true[:1], lag, 0), rpm_true[:-lag]])
    lab = label(_log(veh, M, T=20.0, f_B=f_B, rpm=rpm_log), veh, reference=M)
    assert abs(lab.delay - lag / RATE) < 1 / RATE
    # aligned, M now explains the thrust
    assert np.sqrt(np.mean(lab.residual_force[:, 2] ** 2)) < 0.02 * float(veh.weight)


def test_motor_curve_fits(veh, M):
    rng = np.random.default_rng(3)
    true = MotorCurve(c1=5000.0, c2=2500.0, v_ref=16.0)
    u = rng.uniform(0.1, 0.9, (300, 4))
    V = rng.uniform(14.5, 16.8, 300)
    rpm = true.rpm(u, V[:, None])
    fit = MotorCurve.fit_speeds(u, rpm, V)
    assert fit.source == "speeds" and fit.residual_rpm < 1e-6
    np.testing.assert_allclose(fit.rpm(u, V[:, None]), rpm, rtol=1e-9)
    with pytest.warns(FlightLogWarning, match="outside the calibration's range"):
        fit.rpm(np.full((2, 4), 0.99), np.full((2, 1), 16.0))


def test_a_curve_without_the_motors_lag_warns(veh, M):
    """A static (bench) curve read on a flight's commands leads the rotors by the motors' time
    constant: ``label`` names it. ``fit_speeds(..., time_constant=τ)`` keeps the lag, and the
    labels' speeds are then the curve's lagged ones (SciPy's ``lsim`` of the lag)."""
    tau = float(veh.motor_time_constant)
    assert tau > 0  # the file's motors lag: the case the warning is for
    rng = np.random.default_rng(5)
    bench = rng.uniform(0.2, 0.9, (60, 4))
    static = MotorCurve(c1=5200.0, c2=2100.0).rpm(bench)
    n = int(6 * RATE)
    t = np.arange(n) / RATE
    s_hover = (-5200.0 + np.sqrt(5200.0**2 + 4 * 2100.0 * _hover_rpm(veh, M))) / (2 * 2100.0)
    # a command step at 3 s: the lag shows where the command changes
    u = np.where(t[:, None] < 3.0, s_hover, s_hover * 1.05) * np.ones((1, 4))
    log = _log(veh, M, T=6.0).replace(rpm=None, command=u)
    with pytest.warns(FlightLogWarning, match=r"no lag \(time_constant 0\).*time_constant=0\.05"):
        label(log, veh, reference=M, curve=MotorCurve.fit_speeds(bench, static))
    lagged = MotorCurve.fit_speeds(bench, static, time_constant=tau)
    assert lagged.time_constant == tau
    with pytest.raises(ValueError, match="time_constant must be >= 0"):
        MotorCurve.fit_speeds(bench, static, time_constant=-tau)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FlightLogWarning)
        lab = label(log, veh, reference=M, curve=lagged)
    # the first-order lag 1/(τs + 1) of the curve's speed, its input interpolated linearly
    # between samples (a first-order hold), by SciPy's lsim: two exact discretisations
    from scipy import signal

    q = lagged.rpm(u)
    lag = (np.array([[-1 / tau]]), np.array([[1 / tau]]), np.eye(1), np.zeros((1, 1)))
    want = np.column_stack([signal.lsim(lag, q[:, j], t, X0=[q[0, j]])[1] for j in range(4)])
    i = np.searchsorted(t, lab.t)
    np.testing.assert_allclose(lab.rpm, want[i], rtol=1e-9)
    assert np.max(np.abs(lab.rpm / q[i] - 1)) > 1e-3  # labels just after the step: it lags


def test_calibration_from_hover_labels_zero_within_noise(veh, M):
    """A hovering log whose thrust coefficient is 8 % above M's and whose rotor speeds are only
    commands: the motor curve fitted from the hover, M calibrated on it, and the hover's
    labels are then zero to within their estimated noise."""
    rng = np.random.default_rng(4)
    n = int(15 * RATE)
    curve = MotorCurve(c1=5200.0, c2=2100.0, v_ref=16.0)
    V = np.linspace(16.5, 15.8, n)
    P_true = 1.08 * P_F
    # a hover with small collective changes, so that the curve is seen at more than one point
    level = 1 + 0.03 * np.sin(2 * np.pi * 0.3 * np.arange(n) / RATE)
    rpm_true = np.sqrt(float(veh.weight) * level / (4 * P_true))[:, None] * np.ones(4)
    a = curve.c2
    s = (-curve.c1 + np.sqrt(curve.c1**2 + 4 * a * rpm_true)) / (2 * a)
    u = s * curve.v_ref / V[:, None]
    f_B = np.stack([np.zeros(n), np.zeros(n), -P_true * (rpm_true**2).sum(1) / float(veh.mass)], 1)
    f_B += 0.03 * rng.normal(size=f_B.shape)
    log = FlightLog(
        t=np.arange(n) / RATE,
        position=np.tile([0.0, 0, -5], (n, 1)),
        velocity=np.zeros((n, 3)),
        quaternion=_yaw_quat(np.zeros(n)),
        rates=np.zeros((n, 3)) + 1e-9 * rng.normal(size=(n, 3)),
        command=u,
        specific_force=f_B,
        voltage=V,
    )
    # this log's motors follow their commands at once: a vehicle without a motor lag
    veh = eqx.tree_at(lambda v: v.motor_time_constant, veh, jnp.asarray(0.0))
    fitted = MotorCurve.fit_hover(log, veh, M)
    assert fitted.source == "hover" and fitted.time_constant == 0.0
    # the curve absorbs the thrust coefficient's error: M's thrust of its speeds is the truth
    thrust_fit = P_F * (fitted.rpm(u, V[:, None]) ** 2).sum(1)
    np.testing.assert_allclose(thrust_fit, P_true * (rpm_true**2).sum(1), rtol=2e-3)
    # with the true rotor speeds logged instead, calibrating M itself
    log_rpm = log.replace(rpm=rpm_true, command=None)
    with pytest.raises(ValueError, match="give torque_ratio"):
        calibrate_simple(log_rpm, veh)  # a hover has no yaw manoeuvre to read T_z from
    M_cal = calibrate_simple(log_rpm, veh, torque_ratio=T_Z / P_F)
    np.testing.assert_allclose(float(M_cal.P_F), P_true, rtol=1e-3)
    lab = label(log_rpm, veh, reference=M_cal, delay=0.0)
    z = lab.residual_force / np.sqrt(lab.force_var)
    assert np.sqrt(np.mean(z**2)) < 2.0, np.sqrt(np.mean(z**2, 0))
    # with commands only, the curve fitted inside label does the same
    lab_c = label(log, veh, reference=M, delay=0.0)
    z = lab_c.residual_force[:, 2] / np.sqrt(lab_c.force_var[:, 2])
    assert np.sqrt(np.mean(z**2)) < 2.0


def test_hover_curve_reads_the_thrust_not_a_guessed_inertia(veh, M):
    """A hover whose collective and roll/pitch rates move, the rotors' speeds solved from M
    for the thrust and Euler's moments: the thrust balance alone recovers the curve whatever
    inertia the file states; balancing the moments too recovers it with the true inertia and
    bends it with a file's inertia twice the truth (the moments read twice as large: a steeper
    curve). Noise-free, so the thrust-only fit is the truth to the solver's tolerance."""
    n = int(12 * RATE)
    t = np.arange(n) / RATE
    truth = MotorCurve(c1=5200.0, c2=2100.0)
    f1, f2 = 2 * np.pi * 0.5, 2 * np.pi * 0.7
    w = np.stack([0.4 * np.sin(f1 * t), 0.3 * np.sin(f2 * t + 1.0), 0 * t], 1)
    wd = np.stack([0.4 * f1 * np.cos(f1 * t), 0.3 * f2 * np.cos(f2 * t + 1.0), 0 * t], 1)
    J = np.asarray(veh.inertia, float)
    thrust = float(veh.weight) * (1 + 0.05 * np.sin(2 * np.pi * 0.2 * t))
    load = np.column_stack([thrust, J * wd + np.cross(w, J * w)])
    rpm2 = np.linalg.solve(np.asarray(M.allocation), load.T).T
    assert rpm2.min() > 0
    rpm = np.sqrt(rpm2)
    u = (-truth.c1 + np.sqrt(truth.c1**2 + 4 * truth.c2 * rpm)) / (2 * truth.c2)
    f_B = np.column_stack([0 * t, 0 * t, -thrust / float(veh.mass)])
    log = _log(veh, M, T=12.0, w=w, f_B=f_B).replace(rpm=None, command=u)
    veh = eqx.tree_at(lambda v: v.motor_time_constant, veh, jnp.asarray(0.0))
    guessed = eqx.tree_at(lambda v: v.inertia, veh, 2 * veh.inertia)
    grid = np.linspace(u.min(), u.max(), 7)[:, None] * np.ones((1, 4))
    want = truth.rpm(grid)
    # the solver stops at a relative cost change of 1e-8: speeds to ~1e-4 of themselves
    for v in (veh, guessed):
        np.testing.assert_allclose(MotorCurve.fit_hover(log, v, M).rpm(grid), want, rtol=1e-4)
    # the moments' spline derivative of the rates (200 Hz, periods over 1 s): 1e-3 of them
    both = MotorCurve.fit_hover(log, veh, M, moments=True)
    np.testing.assert_allclose(both.rpm(grid), want, rtol=3e-3)
    # five times what the true inertia's fit may bend across the range (2 x 3e-3)
    bent = MotorCurve.fit_hover(log, guessed, M, moments=True).rpm(grid) / want
    assert bent[-1, 0] / bent[0, 0] > 1 + 5 * 6e-3, bent[:, 0]
    with pytest.raises(ValueError, match="moments must be True or False"):
        MotorCurve.fit_hover(log, veh, M, moments=1)


def test_labels_first_and_concatenate(veh, M):
    """Labels carry the log's body rates at their instants (the gyro's, FRD); a part without
    them is not concatenated with parts that have them."""
    f_B = np.tile([0.0, 0.0, -9.81], (2000, 1))
    t = np.arange(2000) / RATE
    w = np.stack([0.3 * np.sin(t), 0.2 * np.cos(t), 0.1 * t], 1)
    lab = label(_log(veh, M, f_B=f_B, w=w), veh, reference=M, delay=0.0)
    assert isinstance(lab, Labels)
    np.testing.assert_array_equal(lab.rates, w[np.searchsorted(t, lab.t)])
    with pytest.raises(ValueError, match=r"\['bare'\] have no body rates"):
        Labels.concatenate([lab, dataclasses.replace(lab, rates=None, name="bare")])
    assert abs(lab.seconds - 0.1 * len(lab)) < 1e-9
    part = lab.first(3.0)
    assert abs(part.seconds - 3.0) < 0.1 + 1e-9 and len(part) == 30
    both = Labels.concatenate([part, lab.first(2.0)])
    assert len(both) == 50 and both.dropped["total"] == 4000
    with pytest.raises(ValueError, match="at least one"):
        Labels.concatenate([])


def test_attitude_noise_enters_the_force_variance(veh, M):
    """A noisy attitude turns a large force: its share (|F|² σ_θ²) is in the variance."""
    rng = np.random.default_rng(5)
    n = 2000
    from scipy.spatial.transform import Rotation

    sig = np.radians(0.3)
    R = Rotation.from_rotvec(sig * rng.normal(size=(n, 3))).as_matrix()
    f_B = np.tile([0.0, 0.0, -9.81], (n, 1))
    log = _log(veh, M, f_B=f_B).replace(quaternion=matrix_to_quat(R))
    lab = label(log, veh, reference=M, delay=0.0)
    sd = np.sqrt(lab.force_var[:, :2])
    # the horizontal force scatters by m g σ_θ; the estimate bounds it from above within 2x
    assert np.all(sd > 0.5 * float(veh.weight) * sig)
    assert np.all(sd < 3.0 * float(veh.weight) * sig)


def test_label_arguments_are_named(veh, M):
    log = _log(veh, M, T=2.0)
    for kw, match in [
        ({"rate": "10"}, "rate must be a number, got '10'"),
        ({"delay": "auto"}, "delay must be 'estimate' or a number of seconds"),
        ({"delay": 20}, r"delay is in seconds.*20 ms is 0.02"),
        ({"max_delay": -1.0}, r"max_delay must be in \[0, 0.5\]"),
        ({"source": None}, "source must be 'auto', 'imu' or 'velocity'"),
        ({"curve": "hover"}, "curve must be a MotorCurve"),
        ({"saturation": 1.5}, r"saturation must be in \(0, 1\]"),
    ]:
        with pytest.raises(ValueError, match=match):
            label(log, veh, reference=M, **kw)
    with pytest.raises(ValueError, match=r"vehicle must be a Vehicle.*load_vehicle\('sui_"):
        label(log, "sui_endurance", reference=M)


def test_motor_curve_refuses_what_it_cannot_use():
    for kw, match in [
        ({"c1": float("nan")}, "MotorCurve.c1 must be finite"),
        ({"c1": 0.0, "c2": 0.0}, "the speed at full command"),
        ({"c1": 5000.0, "v_ref": 0.0}, "v_ref must be a positive voltage"),
        ({"c1": 5000.0, "time_constant": -0.1}, "time_constant must be >= 0"),
        ({"c1": 5000.0, "command_range": (0.8, 0.2)}, r"command_range must be \(low, high\)"),
    ]:
        with pytest.raises(ValueError, match=match):
            MotorCurve(**kw)
    curve = MotorCurve(c1=5000.0)
    u = np.full((10, 4), 0.5)
    with pytest.raises(ValueError, match=r"voltage must have shape \(10,\)"):
        curve.rpm(u, voltage=np.full(9, 15.0))
    with pytest.raises(ValueError, match=r"command must have shape \(T, 4\)"):
        curve.rpm(u[:, :3])
    with pytest.raises(ValueError, match="commands above idle"):
        MotorCurve.fit_speeds(np.zeros((10, 4)), np.zeros((10, 4)))
    with pytest.raises(ValueError, match=r"command and rpm must both have shape \(T, 4\)"):
        MotorCurve.fit_speeds(u, np.ones((9, 4)))


def test_hover_samples_needs_four_rotors_per_sample(veh, M):
    log = _log(veh, M, T=2.0)
    with pytest.raises(ValueError, match=r"rpm must have shape \(400, 4\)"):
        hover_samples(log, log.rpm[:, :3])


def test_labels_from_an_interpolated_signal_warn(veh, M):
    """Velocity upsampled 4x by straight lines: three in four second differences vanish, and
    the noise estimate with them."""
    t = np.arange(int(4 * RATE)) / RATE
    coarse = t[::4]
    v = np.stack([np.sin(coarse), np.cos(coarse), 0 * coarse], 1)
    v = np.stack([np.interp(t, coarse, v[:, k]) for k in range(3)], 1)
    with pytest.warns(FlightLogWarning, match=r"velocity looks linearly interpolated .*\(7\d%"):
        label(_log(veh, M, T=4.0, v=v), veh, reference=M, source="velocity", delay=0.0)


def test_motor_curve_scaled_in_closed_form():
    """``scaled(g, p, r)`` gives the speeds ``g r (rpm / r)^p`` of the curve's (lag included),
    composes (a scaled curve scaled again), and refuses a power or gain that is not positive."""
    curve = MotorCurve(4500.0, 2600.0, 16.0, (0.2, 0.9), 30.0, "hover", 0.05)
    u = np.random.default_rng(0).uniform(0.25, 0.85, (50, 4))
    volt, t = np.full(50, 16.3), np.arange(50) * 0.02
    r = curve.rpm(u, volt, t)
    one = curve.scaled(1.1, 0.9, 3500.0)
    np.testing.assert_allclose(one.rpm(u, volt, t), 1.1 * 3500 * (r / 3500) ** 0.9, rtol=1e-12)
    two = one.scaled(0.95, 1.2, 4000.0)
    want = 0.95 * 4000 * ((1.1 * 3500 * (r / 3500) ** 0.9) / 4000) ** 1.2
    np.testing.assert_allclose(two.rpm(u, volt, t), want, rtol=1e-12)
    assert (two.command_range, two.source, two.time_constant) == ((0.2, 0.9), "hover", 0.05)
    assert two.residual_rpm == pytest.approx(30.0 * 1.1 * 0.95)
    with pytest.raises(ValueError, match="exponent must be positive"):
        curve.scaled(1.0, 0.0, 4000.0)
    with pytest.raises(ValueError, match="gain must be positive"):
        curve.scaled(-1.0, 1.0, 4000.0)
    with pytest.raises(ValueError, match="MotorCurve.rpm_ref must be positive"):
        MotorCurve(4500.0, rpm_ref=0.0)
