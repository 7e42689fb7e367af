"""A measured flight on one time base, in gpg's conventions, and its CSV form.

gpg's conventions (the same as everywhere in gpg): world NED (x north/forward, y east/right,
z down), body FRD, the attitude quaternion ``(w, x, y, z)`` rotating body vectors into the
world (``R_WB``), SI units, rotor speeds in rpm in gpg's rotor order (r1 rear-right, r2
rear-left, r3 front-left, r4 front-right). :class:`FlightLog` holds a flight in them, checked
once when it is made; :func:`read_csv` reads any CSV into it, converting units and frames in
one place (:class:`CsvFormat`); :func:`gpg.flight.read_ulog` reads PX4 logs.

The CSV form (default column names; a ``columns`` map renames any of them):

========================  ===================================================================
``t``                     time (s; ``time_unit`` ms or us converted)
``x, y, z``               position (m, world frame ``world``)
``vx, vy, vz``            velocity (m/s, world frame)
``qw, qx, qy, qz``        attitude quaternion, body to world (``quaternion`` order is only a
                          naming: the four columns are read by name)
``p, q, r``               body rates (rad/s, body frame ``body``)
``rpm1 .. rpm4``          rotor speeds (``rotor_speed`` rpm or rad/s), in the log's rotor order
``u1 .. u4``              motor commands (0..1), instead of or beside the rotor speeds
``ax, ay, az``            optional: the IMU's specific force (m/s², body frame)
``wind_x .. wind_z``      optional: a measured or known wind (m/s, world frame)
``voltage``               optional: battery voltage (V)
========================  ===================================================================
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpg._checks import as_float_array
from gpg._io import atomic_write

__all__ = ["CsvFormat", "FlightLog", "FlightLogWarning", "read_csv", "write_csv"]

# |‖q‖ − 1| above this is not rounding: a wrong column, order or unit (the rows are named).
QUAT_NORM_TOL = 0.02
# A step this many times the median step is a gap: warned about, with counts.
GAP_FACTOR = 5.0


class FlightLogWarning(UserWarning):
    """Data that may be intended but deserves a look (gaps, dropped segments), with counts."""


@dataclass(frozen=True)
class FlightLog:
    """One flight, every signal on the time base ``t`` (T samples), in gpg's conventions.

    Attributes:
        t: (T,) time, s, strictly increasing.
        position: (T, 3) m, world NED.
        velocity: (T, 3) m/s, world NED.
        quaternion: (T, 4) ``(w, x, y, z)``, body FRD to world NED (unit norm).
        rates: (T, 3) body rates, rad/s, FRD.
        rpm: (T, 4) rotor speeds, rpm, gpg's rotor order; None if the log has only commands.
        command: (T, 4) motor commands (0..1), gpg's rotor order; None if not logged.
        specific_force: (T, 3) the accelerometer's specific force, m/s², FRD; None if absent.
        wind: (T, 3) m/s world NED; None if unknown.
        voltage: (T,) battery voltage, V; None if not logged.
        name: a label for tables and messages (the file's name by default).

    Raises:
        ValueError: naming the signal and its rows, for a wrong shape, NaN or inf, time not
            strictly increasing (repeated or backwards stamps), time that looks like ms or
            us, quaternions far from unit norm, negative rotor speeds, neither rotor speeds
            nor commands. A gap (a step over :data:`GAP_FACTOR` times the median) is a
            :class:`FlightLogWarning` with its count.
    """

    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    rates: np.ndarray
    rpm: np.ndarray | None = None
    command: np.ndarray | None = None
    specific_force: np.ndarray | None = None
    wind: np.ndarray | None = None
    voltage: np.ndarray | None = None
    name: str = field(default="flight", compare=False)

    def __post_init__(self):
        t = _checked_time(self.name, self.t)
        arrays = {"t": t, **_checked_signals(self, t.size)}
        for k, v in arrays.items():
            if v is not None:
                v.setflags(write=False)
            object.__setattr__(self, k, v)

    @property
    def duration(self) -> float:
        """Seconds from the first sample to the last."""
        return float(self.t[-1] - self.t[0])

    @property
    def rate(self) -> float:
        """Median samples per second."""
        return float(1.0 / np.median(np.diff(self.t)))

    def R_WB(self) -> np.ndarray:
        """The attitude as rotation matrices.

        Returns:
            (T, 3, 3) ``R_WB``, body FRD to world NED.
        """
        return quat_to_matrix(self.quaternion)

    def slice(self, rows: slice | np.ndarray | Sequence[int]) -> FlightLog:
        """Some samples as a flight of their own, checked again (gaps warned about).

        Args:
            rows: a slice, a boolean mask or indices of the samples.

        Returns:
            The flight of those samples, under the same name.
        """
        kw = {
            f.name: (None if getattr(self, f.name) is None else getattr(self, f.name)[rows])
            for f in dataclasses.fields(self)
            if f.name != "name"
        }
        return FlightLog(**kw, name=self.name)

    def replace(self, **changes: np.ndarray | str | None) -> FlightLog:
        """A copy with some fields changed, checked again as a new flight.

        Args:
            **changes: new values of fields, by name (``rpm=...``, ``name=...``).

        Returns:
            The changed flight.
        """
        return dataclasses.replace(self, **changes)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices of unit quaternions ``(w, x, y, z)`` (…, 4)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(w, x, y, z)`` with ``w ≥ 0`` of rotation matrices (…, 3, 3)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()  # scalar last
    q = np.concatenate([q[:, 3:], q[:, :3]], axis=1)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(*R.shape[:-2], 4)


# World frames a log may use, as the rotation taking their vectors into NED.
WORLD_FRAMES = {
    "ned": np.eye(3),
    "enu": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    # x forward, y left, z up (RotorPy, gym-pybullet-drones): a half turn about x
    "nwu": np.diag([1.0, -1.0, -1.0]),
}
# Body frames, as the rotation taking their vectors into FRD.
BODY_FRAMES = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
ROTOR_SPEED_UNITS = {"rpm": 1.0, "rad/s": 60.0 / (2.0 * math.pi)}

DEFAULT_COLUMNS = {
    "t": "t",
    "x": "x",
    "y": "y",
    "z": "z",
    "vx": "vx",
    "vy": "vy",
    "vz": "vz",
    "qw": "qw",
    "qx": "qx",
    "qy": "qy",
    "qz": "qz",
    "p": "p",
    "q": "q",
    "r": "r",
    "rpm1": "rpm1",
    "rpm2": "rpm2",
    "rpm3": "rpm3",
    "rpm4": "rpm4",
    "u1": "u1",
    "u2": "u2",
    "u3": "u3",
    "u4": "u4",
    "ax": "ax",
    "ay": "ay",
    "az": "az",
    "wind_x": "wind_x",
    "wind_y": "wind_y",
    "wind_z": "wind_z",
    "voltage": "voltage",
}
_GROUPS = {
    "position": ("x", "y", "z"),
    "velocity": ("vx", "vy", "vz"),
    "quaternion": ("qw", "qx", "qy", "qz"),
    "rates": ("p", "q", "r"),
    "rpm": ("rpm1", "rpm2", "rpm3", "rpm4"),
    "command": ("u1", "u2", "u3", "u4"),
    "specific_force": ("ax", "ay", "az"),
    "wind": ("wind_x", "wind_y", "wind_z"),
}
_REQUIRED = ("t", "position", "velocity", "quaternion", "rates")


@dataclass(frozen=True)
class CsvFormat:
    """How a CSV log differs from gpg's conventions: every conversion is read from here.

    Attributes:
        columns: the log's column name for each of gpg's names (:data:`DEFAULT_COLUMNS`);
            names not given keep their default.
        world: the world frame of position, velocity, wind and the attitude
            (:data:`WORLD_FRAMES`: ``ned``, ``enu``, ``nwu``).
        body: the body frame of rates, specific force and the attitude (``frd``, ``flu``).
        time_unit: ``s``, ``ms`` or ``us``.
        rotor_speed: ``rpm`` or ``rad/s``.
        rotor_order: for each of gpg's rotors r1..r4, the index (0..3) of the log's rotor
            column that is it (default: the same order).
    """

    columns: Mapping[str, str] = field(default_factory=dict)
    world: str = "ned"
    body: str = "frd"
    time_unit: str = "s"
    rotor_speed: str = "rpm"
    rotor_order: Sequence[int] = (0, 1, 2, 3)

    def __post_init__(self):
        unknown = sorted(set(self.columns) - set(DEFAULT_COLUMNS))
        if unknown:
            raise ValueError(
                f"columns maps unknown name(s) {unknown}; gpg's names are {list(DEFAULT_COLUMNS)}"
            )
        for what, value, allowed in (
            ("world", self.world, WORLD_FRAMES),
            ("body", self.body, BODY_FRAMES),
            ("time_unit", self.time_unit, TIME_UNITS),
            ("rotor_speed", self.rotor_speed, ROTOR_SPEED_UNITS),
        ):
            if value not in allowed:
                raise ValueError(f"{what} must be one of {sorted(allowed)}, got {value!r}")
        if sorted(int(i) for i in self.rotor_order) != [0, 1, 2, 3]:
            raise ValueError(f"rotor_order must be a permutation of 0..3, got {self.rotor_order}")

    def name(self, key: str) -> str:
        """The log's column name for one of gpg's names.

        Args:
            key: one of gpg's column names (:data:`DEFAULT_COLUMNS`).

        Returns:
            The name given in :attr:`columns`, else the default.
        """
        return self.columns.get(key, DEFAULT_COLUMNS[key])

    def to_gpg(self, raw: Mapping[str, np.ndarray], name: str) -> FlightLog:
        """A :class:`FlightLog` from signals in this format's frames, units and rotor order.

        Positions, velocities and the wind turn by the world frame, rates and the specific
        force by the body frame, the attitude by both (``R_ned_frd = W R Bᵀ``); the quaternion
        keeps its norm so that :class:`FlightLog` checks the log's own values.

        Args:
            raw: signals by gpg's group names (``t``, ``position``, ``quaternion``, ``rpm``,
                ...), each (T,) or (T, k); optional ones absent or None.
            name: the flight's name.

        Returns:
            The flight in gpg's conventions, checked.
        """
        W, B = WORLD_FRAMES[self.world], BODY_FRAMES[self.body]
        order = list(self.rotor_order)
        out: dict[str, np.ndarray | None] = {"t": raw["t"] * TIME_UNITS[self.time_unit]}
        for key in ("position", "velocity", "wind"):
            out[key] = None if raw.get(key) is None else raw[key] @ W.T
        for key in ("rates", "specific_force"):
            out[key] = None if raw.get(key) is None else raw[key] @ B.T
        q = raw["quaternion"]
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        R = quat_to_matrix(q / np.where(norm > 0, norm, 1.0))
        # R_ned_frd = W R_src Bᵀ; the norm is checked by FlightLog on the log's own values
        out["quaternion"] = matrix_to_quat(W @ R @ B.T) * norm
        rpm = raw.get("rpm")
        out["rpm"] = None if rpm is None else rpm[:, order] * ROTOR_SPEED_UNITS[self.rotor_speed]
        cmd = raw.get("command")
        out["command"] = None if cmd is None else cmd[:, order]
        out["voltage"] = raw.get("voltage")
        return FlightLog(**out, name=name)


def read_csv(path: str | Path, fmt: CsvFormat | None = None, **format_options: Any) -> FlightLog:
    """Read a CSV flight log (module docstring) into gpg's conventions.

    Args:
        path: the CSV file (a header row of column names, one row per sample).
        fmt: how the log differs from gpg's conventions; None: the defaults, or the
            keywords.
        **format_options: the fields of a :class:`CsvFormat`, instead of ``fmt``
            (``columns={...}, world="enu", rotor_speed="rad/s"``).

    Returns:
        The flight, checked (:class:`FlightLog`).

    Raises:
        ValueError: both ``fmt`` and keywords; an empty file; a required column missing
            (named, with the columns the file has), a value that is not a number (its column
            and row), neither rotor speed nor command columns; every check of
            :class:`CsvFormat` and :class:`FlightLog`.
    """
    if fmt is not None and format_options:
        raise ValueError("give fmt or its fields as keywords, not both")
    fmt = CsvFormat(**format_options) if fmt is None else fmt
    path = Path(path)
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ValueError(f"{path}: empty file, no header row") from None
        rows = list(reader)
    index = {h: i for i, h in enumerate(header)}
    raw: dict[str, np.ndarray | None] = {}

    def column(key: str) -> np.ndarray:
        col = fmt.name(key)
        i = index[col]
        vals = np.empty(len(rows))
        for r, row in enumerate(rows):
            try:
                vals[r] = float(row[i])
            except (ValueError, IndexError):
                cell = row[i] if i < len(row) else "<missing>"
                raise ValueError(
                    f"{path}: column {col!r} row {r + 2} is not a number: {cell!r}"
                ) from None
        return vals

    def group(key: str, required: bool) -> np.ndarray | None:
        names = _GROUPS.get(key, (key,))
        present = [fmt.name(k) in index for k in names]
        if not any(present) and not required:
            return None
        if not all(present):
            missing = [fmt.name(k) for k, p in zip(names, present, strict=True) if not p]
            raise ValueError(
                f"{path}: missing column(s) {missing} for {key}; the file has {header}"
            )
        cols = [column(k) for k in names]
        return cols[0] if len(cols) == 1 else np.stack(cols, axis=1)

    for key in _REQUIRED:
        raw[key] = group(key, True)
    for key in ("rpm", "command", "specific_force", "wind", "voltage"):
        raw[key] = group(key, False)
    if raw["rpm"] is None and raw["command"] is None:
        want = [fmt.name(k) for k in _GROUPS["rpm"] + _GROUPS["command"]]
        raise ValueError(f"{path}: needs rotor speed or command columns {want}; has {header}")
    return fmt.to_gpg(raw, path.stem)


def write_csv(log: FlightLog, path: str | Path) -> Path:
    """Write a flight in gpg's CSV form (default names, gpg's conventions), atomically.

    :func:`read_csv` reads it back with defaults (values written with ``repr``, at full
    precision); absent signals have no columns.

    Args:
        log: the flight.
        path: the file to write (its folder made; replaced whole, never half-written).

    Returns:
        The path written.
    """
    cols: list[tuple[str, np.ndarray]] = [("t", log.t)]
    for key, names in _GROUPS.items():
        v = getattr(log, key)
        if v is not None:
            cols += [(n, v[:, i]) for i, n in enumerate(names)]
    if log.voltage is not None:
        cols.append(("voltage", log.voltage))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([c for c, _ in cols])
    data = np.stack([v for _, v in cols], axis=1)
    for row in data:
        w.writerow([repr(float(x)) for x in row])
    return atomic_write(path, buf.getvalue().encode())


def _checked_time(log: str, t) -> np.ndarray:
    """The time base, checked: finite, strictly increasing, in seconds; gaps warned about."""
    t = as_float_array(f"{log}: t", t, ndim=1)
    if t.size < 4:
        raise ValueError(f"{log}: a flight log needs at least 4 samples, got {t.size}")
    _require_finite(log, "t", t)
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        kind = "repeated" if np.all(steps[bad] == 0) else "non-monotonic"
        raise ValueError(
            f"{log}: t is not strictly increasing ({kind} timestamps) at "
            f"{bad.size} row(s): {_rows(bad + 1)}; e.g. t[{bad[0]}]={t[bad[0]]!r}, "
            f"t[{bad[0] + 1}]={t[bad[0] + 1]!r}"
        )
    med = float(np.median(steps))
    if med >= 0.5:
        raise ValueError(
            f"{log}: t steps by {med:g} per sample (median): time looks like ms or "
            "us, not seconds; give time_unit='ms' or 'us'"
        )
    gaps = np.flatnonzero(steps > GAP_FACTOR * med)
    if gaps.size:
        warnings.warn(
            f"{log}: {gaps.size} gap(s) in t longer than {GAP_FACTOR:g}x the median "
            f"step {med:.4g} s (longest {steps[gaps].max():.4g} s, at rows "
            f"{_rows(gaps + 1)}); segments across a gap are labelled apart",
            FlightLogWarning,
            stacklevel=4,
        )
    return t


_SIGNALS = (  # name, width (None: one value per sample), required
    ("position", 3, True),
    ("velocity", 3, True),
    ("quaternion", 4, True),
    ("rates", 3, True),
    ("rpm", 4, False),
    ("command", 4, False),
    ("specific_force", 3, False),
    ("wind", 3, False),
    ("voltage", None, False),
)


def _checked_signals(log: FlightLog, n: int) -> dict[str, np.ndarray | None]:
    """Every signal of ``log`` checked against ``n`` samples; the quaternion normalised."""
    arrays: dict[str, np.ndarray | None] = {}
    for name, width, need in _SIGNALS:
        v = getattr(log, name)
        if v is None:
            if need:
                raise ValueError(f"{log.name}: {name} is required")
            arrays[name] = None
            continue
        a = as_float_array(f"{log.name}: {name}", v, ndim=1 if width is None else 2)
        shape = (n,) if width is None else (n, width)
        if a.shape != shape:
            raise ValueError(f"{log.name}: {name} must have shape {shape}, got {a.shape}")
        _require_finite(log.name, name, a)
        arrays[name] = a
    if arrays["rpm"] is None and arrays["command"] is None:
        raise ValueError(f"{log.name}: needs rotor speeds (rpm) or motor commands")
    if arrays["rpm"] is not None:
        neg = np.flatnonzero((arrays["rpm"] < 0).any(1))
        if neg.size:
            raise ValueError(f"{log.name}: rpm is negative at {neg.size} row(s): {_rows(neg)}")
    norm = np.linalg.norm(arrays["quaternion"], axis=1)
    off = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)
    if off.size:
        raise ValueError(
            f"{log.name}: quaternion is far from unit norm at {off.size} row(s): "
            f"{_rows(off)} (e.g. |q| = {norm[off[0]]:.4g}); a wrong column or order?"
        )
    arrays["quaternion"] = arrays["quaternion"] / norm[:, None]
    return arrays


def _rows(idx: np.ndarray, shown: int = 10) -> str:
    idx = np.asarray(idx)
    more = f" (and {idx.size - shown} more)" if idx.size > shown else ""
    return f"{idx[:shown].tolist()}{more}"


def _require_finite(log: str, name: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a.reshape(a.shape[0], -1)).all(1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise ValueError(f"{log}: {name} holds NaN or inf at {rows.size} row(s): {_rows(rows)}")
