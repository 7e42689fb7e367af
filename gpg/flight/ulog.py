"""PX4 flight logs (ULog) into a :class:`~gpg.flight.log.FlightLog`, through PX4's ``pyulog``.

PX4 logs each uORB topic at its own rate and with its own timestamps (µs since boot). The
reader takes the topics below, sorts and deduplicates their timestamps, and resamples them
all onto one uniform time base over the window that the required topics (position, attitude,
body rates) cover. Nothing is read as another flight: a file cut short or with corrupt data
is refused (``allow_damaged=True`` reads what is there, saying what was lost); a topic's
dropout is a gap of the log (the time base has no samples inside it), not interpolated
data; an optional topic (specific force, voltage) or one of the two rotor signals that covers
only part of the window is left out (warned), never a reason to cut the flight; a topic too
sparse to resample, a motor beyond the log's ``CA_ROTOR_COUNT`` and a rate faster than every
topic are refused. The signals are then checked against each other
(:mod:`gpg.flight.kinematics`).

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
import mmap
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from gpg._checks import finite_number
from gpg.flight.kinematics import consistency
from gpg.flight.log import (
    GAP_FACTOR,
    QUAT_NORM_TOL,
    ULOG_MAGIC,
    FlightLog,
    FlightLogWarning,
    _checked_path,
    checked_rotor_order,
    enforce,
)

__all__ = ["cut_bytes", "read_ulog"]

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

# The signals that make a flight (their common window is the log's), the rotor signals (one is
# needed), and the optional ones: a rotor or optional signal that covers less is left out.
REQUIRED = ("position", "velocity", "quaternion", "rates")
ROTOR = ("rpm", "command")
OPTIONAL = ("specific_force", "voltage")
# A topic logged less often than once per this many seconds is too sparse to resample.
MAX_STEP_S = 1.0

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
    allow_damaged: bool = False,
    check: bool = True,
) -> FlightLog:
    """Read a PX4 ULog file into gpg's conventions, every topic on one time base.

    Args:
        path: the ``.ulg`` file (only read).
        rate: the time base's rate in Hz; None: that of ``vehicle_local_position`` (the
            median of its steps). At most the fastest topic's rate (no samples invented).
        rotor_order: for each of gpg's rotors r1..r4, the PX4 motor index (0-based) that is
            it; for ``actuator_outputs``, the output channel (0-based). The default maps PX4's
            quad-X numbering onto gpg's. Below the log's ``CA_ROTOR_COUNT`` where it has one.
        instance: the multi-instance of ``actuator_outputs`` to read (PX4 logs one per output
            driver, e.g. 0 for MAIN, 1 for AUX); the other topics are read at instance 0.
        pwm_range: the PWM pulse widths (µs) of command 0 and command 1, for
            ``actuator_outputs``; commands are clipped to 0..1.
        name: the flight's label; the file's stem by default.
        allow_damaged: read what can be read of a file cut short or with corrupt data (warned,
            saying what was lost) instead of refusing it.
        check: compare the signals with each other (:func:`~gpg.flight.consistency`), as
            :func:`~gpg.flight.log.read_csv` does.

    Returns:
        The flight (:class:`~gpg.flight.log.FlightLog`): time from 0 at the start of the
        window that the required topics (position, attitude, body rates) cover, at ``rate``,
        without the samples inside any used topic's dropout (a gap of the log, not
        interpolated data); ``rpm`` where the ESCs report rotor speeds, ``command`` where
        motor commands are logged (both in gpg's rotor order), the attitude quaternion
        continuous in sign (its first sample with ``w ≥ 0``); ``source`` the file.

    Raises:
        ImportError: pyulog is not installed (``pip install 'gpg[logs]'``).
        ValueError: not a ULog file; a file cut short or with corrupt data (without
            ``allow_damaged``); a required topic or field missing (named, with the topics the
            file has), or logged too sparsely to resample (under one sample a second); neither
            rotor speeds nor motor commands over the window (the topics tried, their spans);
            a motor index beyond the log's motors; no common time window (each topic's span);
            attitude quaternions far from unit norm; signals that disagree (``check``); a bad
            argument (named); and every check of :class:`~gpg.flight.log.FlightLog`.

    Warns:
        FlightLogWarning: a topic's timestamps repeated or going backwards (sorted, the
            repeats dropped: the counts given); a topic's dropouts (gaps of the log: their
            count and length); an optional topic (specific force, voltage) or one of two rotor
            signals that covers only part of the window, or a voltage of 0 V (left out, with
            its span); the logger's own dropouts; estimator resets or samples flagged invalid
            in ``vehicle_local_position`` within the window (counted); what a damaged file
            lost (``allow_damaged``).
    """
    try:
        from pyulog import ULog
    except ImportError as exc:
        raise ImportError("read_ulog needs the pyulog package: pip install 'gpg[logs]'") from exc
    path = _checked_path(path)
    rate = _checked_rate(rate)
    order = checked_rotor_order(rotor_order, motors=None)
    if isinstance(instance, bool) or not isinstance(instance, (int, np.integer)) or instance < 0:
        raise ValueError(f"instance must be a non-negative integer, got {instance!r}")
    lo, hi = _checked_pwm_range(pwm_range)
    if name is not None and not isinstance(name, str):
        raise ValueError(f"name must be a string or None, got {name!r}")
    name = name if name is not None else path.stem
    ulog, damage = _parsed(ULog, path, allow_damaged)
    topics = {(d.name, d.multi_id): d.data for d in ulog.data_list}

    def all_topics() -> list[str]:
        return sorted({d.name for d in ULog(str(path)).data_list})

    motors = ulog.initial_parameters.get("CA_ROTOR_COUNT")
    if motors is not None and int(motors) > 0:
        checked_rotor_order(order, motors=int(motors))
    series = _select(topics, order, instance, (lo, hi), all_topics, label=str(path))
    series, start, end = _window(series, name)
    rate = _time_base_rate(series, rate, name)
    series = _covering(series, start, end, rate, name)
    # the kept signals end within a few of their steps of the window: trimmed to all of them
    start = max(int(s[1][0]) for s in series.values())
    end = min(int(s[1][-1]) for s in series.values())
    gaps = _gaps(series, start, end, rate, name)
    _check_local_position(topics[(LOCAL_POSITION, 0)], start, end, name)
    _warn_dropouts(ulog.dropouts, name)
    log = _resample(series, start, end, rate, name, gaps, str(path))
    if damage:
        warnings.warn(
            f"{name}: {damage}; read what is there: the flight ends at {log.duration:.3f} s "
            f"of the window, {log.t.size} samples (anything after the damage in a cut file, "
            "or inside it, is lost)",
            FlightLogWarning,
            stacklevel=2,
        )
    if check:
        enforce(consistency(log), name)
    return log


def _parsed(ULog, path: Path, allow_damaged: bool):
    """pyulog's reading of ``path`` and its damage in words ('' when whole); a damaged file
    refused unless ``allow_damaged``."""
    with open(path, "rb") as f:
        if f.read(len(ULOG_MAGIC)) != ULOG_MAGIC:
            raise ValueError(f"{path}: not a PX4 ULog file (no ULog header); a CSV? read_csv")
    short = cut_bytes(path)
    try:
        ulog = ULog(str(path), message_name_filter_list=list(TOPICS))
    except Exception as exc:  # pyulog raises what its parser meets: name the file with it
        raise ValueError(f"{path}: pyulog cannot parse it ({type(exc).__name__}: {exc})") from None
    damage = _damage(ulog.file_corruption, short, path)
    if damage and not allow_damaged:
        raise ValueError(
            f"{path}: {damage}; refused, as it would read as a different flight. Pass "
            "allow_damaged=True to read what is there"
        )
    return ulog, damage


def _warn_dropouts(dropouts, name: str) -> None:
    """Warn of the logger's own dropouts (PX4's dropout messages, their durations in ms)."""
    if dropouts:
        lost = sum(float(d.duration) for d in dropouts) * 1e-3
        warnings.warn(
            f"{name}: the logger dropped data {len(dropouts)} time(s), {lost:.3g} s in all "
            "(PX4's own dropout messages); longer ones are gaps of the log",
            FlightLogWarning,
            stacklevel=3,
        )


def _checked_rate(rate) -> float | None:
    if rate is None:
        return None
    want = "a positive number of Hz or None"
    if not finite_number("rate", rate, want) > 0:
        raise ValueError(f"rate must be {want}, got {rate!r}")
    return float(rate)


def _checked_pwm_range(pwm_range) -> tuple[float, float]:
    want = "(low, high) pulse widths in µs with low < high, e.g. (1000, 2000)"
    if isinstance(pwm_range, (str, bytes)) or not isinstance(pwm_range, (Sequence, np.ndarray)):
        raise ValueError(f"pwm_range must be {want}, got {pwm_range!r}")
    try:
        lo, hi = (finite_number("pwm_range", v) for v in pwm_range)
    except ValueError:  # not two numbers: named as the pair
        raise ValueError(f"pwm_range must be {want}, got {pwm_range!r}") from None
    if not hi > lo:
        raise ValueError(f"pwm_range must be {want}, got {pwm_range!r}")
    return lo, hi


def cut_bytes(path: str | Path) -> int:
    """How many bytes a ULog file ends short of its last message: a file cut short.

    ULog is a 16-byte header, then messages of a 3-byte header (size: uint16, type) and
    ``size`` bytes; pyulog stops silently at a message the file cuts, so the chain is walked
    here. A file cut exactly between two messages reads as whole (it is a shorter log), and
    past corrupt bytes the chain means nothing (pyulog's ``file_corruption`` says so).

    Args:
        path: the ``.ulg`` file.

    Returns:
        0 where the file ends on a message's end, else the bytes its last message lacks.
    """
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size < 16:  # not even the file header (mmap refuses an empty file)
            return 16 - size
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            return _walk(m)


def _walk(m) -> int:
    """:func:`cut_bytes` on the file's bytes."""
    n, pos = len(m), 16
    while pos + 3 <= n:
        pos += 3 + (m[pos] | (m[pos + 1] << 8))
    if pos == n:
        return 0
    return pos - n if pos > n else 3 - (n - pos)


def _damage(corrupt: bool, short: int, path: Path) -> str:
    """The file's damage in words ('' when whole)."""
    if corrupt:  # the chain of sizes is not to be trusted past corrupt bytes
        return (
            "holds corrupt data (pyulog's file_corruption: bytes that are no message, skipped "
            "to the next sync marker)"
        )
    if short:
        return (
            f"is cut short: it ends {short} byte(s) into a message, at byte "
            f"{path.stat().st_size}; the rest of the flight is missing"
        )
    return ""


def _time_base_rate(series: Mapping[str, _Series], rate: float | None, name: str) -> float:
    """The time base's rate: the position's by default; never faster than the fastest signal
    (samples in between would be invented)."""

    def median_rate(s: _Series) -> float:
        return 1e6 / _median_step_us(s[1])

    if rate is None:
        return median_rate(series["position"])
    fastest = max(median_rate(s) for s in series.values())
    if rate > 1.05 * fastest:
        raise ValueError(
            f"{name}: rate {rate:g} Hz is faster than every topic read (the fastest: "
            f"{fastest:.4g} Hz); the samples in between would be invented"
        )
    return rate


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
        unset = [m for m, ok in zip(order, np.any(np.isfinite(u), axis=0), strict=True) if not ok]
        if unset:  # PX4 leaves a motor it does not have NaN throughout
            raise ValueError(
                f"rotor_order names PX4 motor index(es) {unset} that the log's vehicle does not "
                "have (actuator_motors control[i] is NaN throughout)"
            )
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
    """The signals with monotonic time, and the window (µs) that the required ones cover.

    A required signal logged less often than once per :data:`MAX_STEP_S` is refused: too
    sparse to stand for the flight between its samples."""
    series, warned = {}, set()
    for key, s in raw.items():
        if s is not None:
            series[key] = _monotonic(s, warn=s[0] not in warned)
            warned.add(s[0])
    required = {k: s for k, s in series.items() if k in REQUIRED}
    for s in required.values():
        step = _median_step_us(s[1]) * 1e-6
        if step > MAX_STEP_S:
            raise ValueError(
                f"{name}: {s[0]} has {s[1].size} sample(s), one per {step:.3g} s (median): too "
                f"sparse to resample (at least one per {MAX_STEP_S:g} s)"
            )
    spans = {s[0]: (int(s[1][0]), int(s[1][-1])) for s in required.values()}
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


def _median_step_us(ts: np.ndarray) -> float:
    """A topic's median step between stamps, µs (infinite for one sample)."""
    return float(np.median(np.diff(ts))) if ts.size > 1 else math.inf


def _gap_threshold(ts: np.ndarray, rate: float) -> float:
    """µs: a step longer than this is a dropout (:data:`GAP_FACTOR` times the longer of the
    topic's median step and the time base's)."""
    return GAP_FACTOR * max(_median_step_us(ts), 1e6 / rate)


def _covering(
    series: Mapping[str, _Series], start: int, end: int, rate: float, name: str
) -> dict[str, _Series]:
    """The signals, less the optional and rotor ones that do not cover the window (warned):
    a partial topic is left out, never a reason to cut the flight."""
    kept = dict(series)
    for key in ROTOR + OPTIONAL:
        s = kept.get(key)
        if s is None:
            continue
        topic, ts, v = s
        tol = _gap_threshold(ts, rate)
        why = ""
        if _median_step_us(ts) * 1e-6 > MAX_STEP_S or ts[0] > start + tol or ts[-1] < end - tol:
            why = (
                f"covers {(ts[0] - start) * 1e-6:.3f}..{(ts[-1] - start) * 1e-6:.3f} s of the "
                f"window 0..{(end - start) * 1e-6:.3f} s ({ts.size} samples)"
            )
        elif key == "voltage":
            inside = (ts >= start - tol) & (ts <= end + tol)
            low = int(np.count_nonzero(v[inside, 0] <= 0))
            if low:
                why = f"is 0 V or less in {low} of its samples in the window"
        if why:
            warnings.warn(
                f"{name}: {topic} {why}: {key} left out (None), the flight kept whole",
                FlightLogWarning,
                stacklevel=4,
            )
            del kept[key]
    if "rpm" not in kept and "command" not in kept:
        spans = ", ".join(
            f"{series[k][0]} {(series[k][1][0] - start) * 1e-6:.3f}.."
            f"{(series[k][1][-1] - start) * 1e-6:.3f} s"
            for k in ROTOR
            if series.get(k) is not None
        )
        raise ValueError(
            f"{name}: neither rotor speeds nor motor commands cover the window "
            f"0..{(end - start) * 1e-6:.3f} s of position, attitude and rates: {spans}"
        )
    return kept


def _gaps(
    series: Mapping[str, _Series], start: int, end: int, rate: float, name: str
) -> list[tuple[int, int]]:
    """Every used topic's dropouts inside the window, as open intervals (µs), warned of."""
    gaps: list[tuple[int, int]] = []
    notes = []
    for topic, ts, _ in {s[0]: s for s in series.values()}.values():
        steps = np.diff(ts)
        inside = (ts[1:] > start) & (ts[:-1] < end)
        idx = np.flatnonzero((steps > _gap_threshold(ts, rate)) & inside)
        if idx.size:
            here = [(int(ts[i]), int(ts[i + 1])) for i in idx]
            gaps += here
            at = ", ".join(f"{(a - start) * 1e-6:.2f}" for a, _ in here[:5])
            longest = max(b - a for a, b in here) * 1e-6
            notes.append(f"{topic} {len(here)} (longest {longest:.3g} s, after {at} s)")
    if notes:
        warnings.warn(
            f"{name}: dropouts: {'; '.join(notes)}: gaps of the log, not interpolated "
            "data; segments across them are labelled apart",
            FlightLogWarning,
            stacklevel=4,
        )
    return gaps


def _resample(
    series: Mapping[str, _Series],
    start: int,
    end: int,
    rate: float,
    name: str,
    gaps: Sequence[tuple[int, int]] = (),
    source: str | None = None,
) -> FlightLog:
    """Every signal on one uniform time base over the window ``start..end`` (µs), less the
    instants inside ``gaps``."""
    from scipy.spatial.transform import Rotation, Slerp

    n = int(math.floor((end - start) * 1e-6 * rate + 1e-9)) + 1
    t = np.arange(n) / rate
    keep = np.ones(n, bool)
    for a, b in gaps:
        at = start + t * 1e6
        keep &= ~((at > a) & (at < b))
    t = t[keep]
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
        source=source,
    )
