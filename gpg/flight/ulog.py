"""PX4 flight logs (ULog) into a :class:`~gpg.flight.log.FlightLog`, through PX4's ``pyulog``.

PX4 logs each uORB topic at its own rate and with its own timestamps (µs since boot). The
reader takes the topics below, sorts and deduplicates their timestamps, and resamples them
all onto one uniform time base spanning only the window that every topic used covers:

==================  ==========================================================================
position, velocity  ``vehicle_local_position``: ``x, y, z``, ``vx, vy, vz`` (NED, m, m/s)
attitude            ``vehicle_attitude``: ``q[0..3]`` (``w, x, y, z``, FRD body to NED),
                    resampled by spherical interpolation
body rates          ``vehicle_angular_velocity``: ``xyz[0..2]`` (FRD, rad/s), else
                    ``sensor_combined``: ``gyro_rad[0..2]``
rotor speeds        ``esc_status``: ``esc[i].esc_rpm`` (its magnitude), only where the ESCs
                    report nonzero rpm; ``esc[i].actuator_function`` (101 = motor 1, …)
                    names each ESC's motor where logged, else ESC ``i`` is motor ``i + 1``
motor commands      ``actuator_motors``: ``control[i]`` (0..1; NaN, PX4's "stopped", read
                    as 0), else ``actuator_outputs``: ``output[i]`` (PWM µs, mapped from
                    ``pwm_range`` onto 0..1)
specific force      optional: ``vehicle_acceleration``: ``xyz[0..2]`` (FRD, m/s², what the
                    accelerometer measures: about ``(0, 0, -9.81)`` at rest), else
                    ``sensor_combined``: ``accelerometer_m_s2[0..2]``
battery voltage     optional: ``battery_status``: ``voltage_v``, else ``voltage_filtered_v``
==================  ==========================================================================

Topics are read at multi-instance 0, except ``actuator_outputs`` (its ``instance``: one per
output driver). PX4's quad-X numbering is motor 1 front-right, 2 rear-left, 3 front-left,
4 rear-right; gpg's rotors are r1 rear-right, r2 rear-left, r3 front-left, r4 front-right,
hence the default ``rotor_order=(3, 1, 2, 0)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from gpg.flight.log import QUAT_NORM_TOL, FlightLog, FlightLogWarning

__all__ = ["read_ulog"]

# One logged topic: field name -> column (pyulog's ``Data.data``), keyed by (name, multi_id).
Topics = Mapping[tuple[str, int], Mapping[str, np.ndarray]]

LOCAL_POSITION = "vehicle_local_position"
ATTITUDE = "vehicle_attitude"
# Each signal's candidates, tried in order: (topic, fields).
RATES = (
    ("vehicle_angular_velocity", ("xyz[0]", "xyz[1]", "xyz[2]")),
    ("sensor_combined", ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]")),
)
SPECIFIC_FORCE = (
    ("vehicle_acceleration", ("xyz[0]", "xyz[1]", "xyz[2]")),
    (
        "sensor_combined",
        ("accelerometer_m_s2[0]", "accelerometer_m_s2[1]", "accelerometer_m_s2[2]"),
    ),
)
VOLTAGE = (("battery_status", ("voltage_v",)), ("battery_status", ("voltage_filtered_v",)))
ROTOR_TOPICS = ("esc_status", "actuator_motors", "actuator_outputs")
TOPICS = tuple(  # every topic read, in a fixed order
    dict.fromkeys(
        [LOCAL_POSITION, ATTITUDE, *(t for t, _ in RATES + SPECIFIC_FORCE + VOLTAGE)]
        + list(ROTOR_TOPICS)
    )
)
# PX4's output function of motor k (0-based) is 101 + k (OutputFunction Motor1 = 101).
_MOTOR1_FUNCTION = 101
_MAX_MOTORS = 16

# A signal before resampling: (its topic's label, timestamps µs (int64), values (N, k)).
_Series = tuple[str, np.ndarray, np.ndarray]


def read_ulog(
    path: str | Path,
    *,
    rate: float | None = None,
    rotor_order: Sequence[int] = (3, 1, 2, 0),
    instance: int = 0,
    pwm_range: tuple[float, float] = (1000.0, 2000.0),
    name: str | None = None,
) -> FlightLog:
    """Read a PX4 ULog file into gpg's conventions, every topic on one time base.

    Args:
        path: the ``.ulg`` file (only read).
        rate: the time base's rate in Hz; None: that of ``vehicle_local_position`` (the
            median of its steps).
        rotor_order: for each of gpg's rotors r1..r4, the PX4 motor index (0-based) that is
            it; for ``actuator_outputs``, the output channel (0-based). The default maps PX4's
            quad-X numbering onto gpg's.
        instance: the multi-instance of ``actuator_outputs`` to read (PX4 logs one per output
            driver, e.g. 0 for MAIN, 1 for AUX); the other topics are read at instance 0.
        pwm_range: the PWM pulse widths (µs) of command 0 and command 1, for
            ``actuator_outputs``; commands are clipped to 0..1.
        name: the flight's label; the file's stem by default.

    Returns:
        The flight (:class:`~gpg.flight.log.FlightLog`): time from 0 at the start of the
        window that all topics used cover, at ``rate``; ``rpm`` where the ESCs report rotor
        speeds, ``command`` where motor commands are logged (both in gpg's rotor order), the
        attitude quaternion continuous in sign (its first sample with ``w ≥ 0``).

    Raises:
        ImportError: pyulog is not installed (``pip install 'gpg[logs]'``).
        ValueError: a required topic or field missing (named, with the topics the file has);
            neither rotor speeds nor motor commands (the topics tried); no common time window
            (each topic's span); attitude quaternions far from unit norm; a bad argument; and
            every check of :class:`~gpg.flight.log.FlightLog`.

    Warns:
        FlightLogWarning: a topic's timestamps repeated or going backwards (sorted, the
            repeats dropped: the counts given); estimator resets or samples flagged invalid
            in ``vehicle_local_position`` within the window (counted).
    """
    try:
        from pyulog import ULog
    except ImportError as exc:
        raise ImportError("read_ulog needs the pyulog package: pip install 'gpg[logs]'") from exc
    path = Path(path)
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive number of Hz or None, got {rate!r}")
    order = [int(i) for i in rotor_order]
    if len(order) != 4 or len(set(order)) != 4 or min(order) < 0:
        raise ValueError(
            f"rotor_order must give 4 distinct motor indices (0-based), got {rotor_order}"
        )
    lo, hi = (float(v) for v in pwm_range)
    if not hi > lo:
        raise ValueError(f"pwm_range must be (low, high) with low < high, got {pwm_range}")
    ulog = ULog(str(path), message_name_filter_list=list(TOPICS))
    topics = {(d.name, d.multi_id): d.data for d in ulog.data_list}

    def all_topics() -> list[str]:
        return sorted({d.name for d in ULog(str(path)).data_list})

    name = name if name is not None else path.stem
    series = _select(topics, order, instance, (lo, hi), all_topics, label=str(path))
    series, start, end = _window(series, name)
    _check_local_position(topics[(LOCAL_POSITION, 0)], start, end, name)
    return _resample(series, start, end, rate, name)


def _select(
    topics: Topics,
    order: Sequence[int],
    instance: int,
    pwm_range: tuple[float, float],
    all_topics=None,
    label: str = "log",
) -> dict[str, _Series | None]:
    """Each of gpg's signals from the logged topics, before resampling (module docstring).

    ``all_topics`` (a callable) lists the file's topics for the error messages; by default
    the names in ``topics``.
    """

    def have() -> list[str]:
        return all_topics() if all_topics is not None else sorted({n for n, _ in topics})

    def first(signal: str, candidates, required: bool) -> _Series | None:
        for topic, fields in candidates:
            data = topics.get((topic, 0))
            if data is not None and all(f in data for f in fields) and len(data["timestamp"]):
                return _series(topic, data, fields)
        if not required:
            return None
        tried = " or ".join(f"{t} ({', '.join(f)})" for t, f in candidates)
        raise ValueError(f"{label}: no {signal}: needs topic {tried}; the file has {have()}")

    out: dict[str, _Series | None] = {}
    out["position"] = first("position", [(LOCAL_POSITION, ("x", "y", "z"))], True)
    out["velocity"] = first("velocity", [(LOCAL_POSITION, ("vx", "vy", "vz"))], True)
    q_fields = ("q[0]", "q[1]", "q[2]", "q[3]")
    out["quaternion"] = first("attitude", [(ATTITUDE, q_fields)], True)
    out["rates"] = first("body rates", RATES, True)
    out["specific_force"] = first("specific force", SPECIFIC_FORCE, False)
    out["voltage"] = None
    for topic, fields in VOLTAGE:  # a battery not connected logs 0 V
        s = first("voltage", [(topic, fields)], False)
        if s is not None and np.any(s[2] > 0):
            out["voltage"] = s
            break
    out["rpm"] = _esc_rpm(topics.get(("esc_status", 0)), order)
    out["command"] = _commands(topics, order, instance, pwm_range)
    if out["rpm"] is None and out["command"] is None:
        raise ValueError(
            f"{label}: no rotor speeds nor motor commands for PX4 motors {list(order)}: tried "
            f"esc_status (esc[i].esc_rpm, nonzero), actuator_motors (control[i]) and "
            f"actuator_outputs instance {instance} (output[i]); the file has {have()}"
        )
    return out


def _series(topic: str, data: Mapping[str, np.ndarray], fields: Sequence[str]) -> _Series:
    t = np.asarray(data["timestamp"]).astype(np.int64)
    v = np.stack([np.asarray(data[f], dtype=np.float64) for f in fields], axis=1)
    return topic, t, v


def _esc_rpm(data: Mapping[str, np.ndarray] | None, order: Sequence[int]) -> _Series | None:
    """Rotor speeds (rpm magnitude) of the motors ``order`` from ``esc_status``, or None."""
    if data is None or not len(data["timestamp"]):
        return None
    escs = [i for i in range(_MAX_MOTORS) if f"esc[{i}].esc_rpm" in data]
    motor_of = {}
    for i in escs:
        f = data.get(f"esc[{i}].actuator_function")
        if f is not None and len(f):
            values, counts = np.unique(np.asarray(f, dtype=np.int64), return_counts=True)
            k = int(values[np.argmax(counts)]) - _MOTOR1_FUNCTION
            if 0 <= k < _MAX_MOTORS:
                motor_of[i] = k
    esc_of = {k: i for i, k in motor_of.items()} if motor_of else {i: i for i in escs}
    if not all(m in esc_of for m in order):
        return None
    fields = [f"esc[{esc_of[m]}].esc_rpm" for m in order]
    topic, t, rpm = _series("esc_status", data, fields)
    rpm = np.abs(rpm)  # some ESCs sign the speed by direction
    if not np.all(np.any(rpm > 0, axis=0)):
        return None  # ESCs without rpm telemetry report 0
    return topic, t, rpm


def _commands(
    topics: Topics, order: Sequence[int], instance: int, pwm_range: tuple[float, float]
) -> _Series | None:
    """Motor commands (0..1) of the motors ``order``, or None."""
    data = topics.get(("actuator_motors", 0))
    fields = [f"control[{m}]" for m in order]
    if data is not None and len(data["timestamp"]) and all(f in data for f in fields):
        topic, t, u = _series("actuator_motors", data, fields)
        if np.all(np.any(np.isfinite(u), axis=0)):  # an unconfigured motor is NaN throughout
            return topic, t, np.clip(np.nan_to_num(u, nan=0.0), 0.0, 1.0)
    data = topics.get(("actuator_outputs", instance))
    fields = [f"output[{m}]" for m in order]
    if data is not None and len(data["timestamp"]) and all(f in data for f in fields):
        _, t, pwm = _series("actuator_outputs", data, fields)
        lo, hi = pwm_range
        u = np.clip((np.nan_to_num(pwm, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
        return f"actuator_outputs instance {instance}", t, u
    return None


def _check_local_position(data: Mapping[str, np.ndarray], start: int, end: int, label: str) -> None:
    """Warn of estimator resets (jumps) and invalid samples of the local position within the
    window ``start..end`` (µs)."""
    t = np.asarray(data["timestamp"]).astype(np.int64)
    inside = (t >= start) & (t <= end)
    notes = []
    for key in ("xy_reset_counter", "z_reset_counter", "vxy_reset_counter", "vz_reset_counter"):
        if key in data and np.count_nonzero(inside) > 1:
            c = np.asarray(data[key], dtype=np.int64)[inside]
            n = int(np.count_nonzero(np.diff(c)))
            if n:
                notes.append(f"{key.removesuffix('_counter')} {n} time(s)")
    for key in ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid"):
        if key in data:
            n = int(np.count_nonzero(np.asarray(data[key])[inside] == 0))
            if n:
                notes.append(f"{key} false in {n} of {np.count_nonzero(inside)} samples")
    if notes:
        warnings.warn(
            f"{label}: {LOCAL_POSITION} (the estimator's): {'; '.join(notes)}; position and "
            "velocity may jump or be unreliable there",
            FlightLogWarning,
            stacklevel=3,
        )


def _monotonic(series: _Series, warn: bool) -> _Series:
    """``series`` sorted by time with repeated stamps dropped (the first kept), warned of."""
    topic, t, v = series
    steps = np.diff(t)
    if np.all(steps > 0):
        return series
    back = int(np.count_nonzero(steps < 0))
    idx = np.argsort(t, kind="stable")
    t, v = t[idx], v[idx]
    keep = np.concatenate([[True], np.diff(t) > 0])
    repeated = int(t.size - np.count_nonzero(keep))
    if warn:
        warnings.warn(
            f"{topic}: timestamps not increasing: {back} step(s) backwards, {repeated} "
            f"repeated of {t.size}: sorted, the {repeated} repeated sample(s) dropped (the "
            "first of each kept)",
            FlightLogWarning,
            stacklevel=4,
        )
    return topic, t[keep], v[keep]


def _window(raw: Mapping[str, _Series | None], name: str) -> tuple[dict[str, _Series], int, int]:
    """The signals with monotonic time, and the window (µs) that all of them cover."""
    series, warned = {}, set()
    for key, s in raw.items():
        if s is not None:
            series[key] = _monotonic(s, warn=s[0] not in warned)
            warned.add(s[0])
    spans = {s[0]: (int(s[1][0]), int(s[1][-1])) for s in series.values()}
    start = max(a for a, _ in spans.values())
    end = min(b for _, b in spans.values())
    if end <= start:
        t0 = min(a for a, _ in spans.values())
        listed = ", ".join(
            f"{topic} {(a - t0) * 1e-6:.3f}..{(b - t0) * 1e-6:.3f} s"
            for topic, (a, b) in spans.items()
        )
        raise ValueError(
            f"{name}: the topics share no time window (spans from the earliest stamp): {listed}"
        )
    return series, start, end


def _resample(
    series: Mapping[str, _Series], start: int, end: int, rate: float | None, name: str
) -> FlightLog:
    """Every signal on one uniform time base over the window ``start..end`` (µs)."""
    from scipy.spatial.transform import Rotation, Slerp

    if rate is None:
        rate = 1e6 / float(np.median(np.diff(series["position"][1])))
    n = int(math.floor((end - start) * 1e-6 * rate + 1e-9)) + 1
    t = np.arange(n) / rate
    out: dict[str, np.ndarray] = {}
    for key, (topic, ts, v) in series.items():
        s = (ts - start) * 1e-6
        if key == "quaternion":
            norm = np.linalg.norm(v, axis=1)
            off = np.flatnonzero(~(np.abs(norm - 1.0) <= QUAT_NORM_TOL))
            if off.size:
                raise ValueError(
                    f"{name}: {topic} q is far from unit norm in {off.size} of {norm.size} "
                    f"samples (e.g. sample {off[0]}: |q| = {norm[off[0]]:.4g})"
                )
            rot = Rotation.from_quat(v[:, [1, 2, 3, 0]])  # scipy is scalar last
            q = Slerp(s, rot)(np.clip(t, s[0], s[-1])).as_quat()[:, [3, 0, 1, 2]]
            flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
            q[1:] *= flip[:, None]
            out[key] = q if q[0, 0] >= 0 else -q
        else:
            cols = [np.interp(t, s, v[:, j]) for j in range(v.shape[1])]
            out[key] = cols[0] if key == "voltage" else np.stack(cols, axis=1)
    return FlightLog(
        t=t,
        position=out["position"],
        velocity=out["velocity"],
        quaternion=out["quaternion"],
        rates=out["rates"],
        rpm=out.get("rpm"),
        command=out.get("command"),
        specific_force=out.get("specific_force"),
        voltage=out.get("voltage"),
        name=name,
    )
