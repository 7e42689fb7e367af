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
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpg._checks import as_float_array
from gpg._io import atomic_write
from gpg.flight.kinematics import HINTS, Agreement, consistency, quat_to_matrix

__all__ = [
    "CsvFormat",
    "FlightLog",
    "FlightLogWarning",
    "checked_rotor_order",
    "enforce",
    "read_csv",
    "write_csv",
]

# |‖q‖ − 1| above this is not rounding: a wrong column, order or unit (the rows are named).
QUAT_NORM_TOL = 0.02
# A step this many times the median step is a gap: warned about, with counts.
GAP_FACTOR = 5.0
# A median step shorter than this (s) is no flight log's: time in a unit smaller than declared.
MIN_STEP_S = 2e-4
# Motor commands are normalised to 0..1; this much outside is rounding, more is another range.
COMMAND_TOL = 1e-6


class FlightLogWarning(UserWarning):
    """Data that may be intended but deserves a look (gaps, dropped segments), with counts."""


def enforce(checks: Sequence[Agreement], name: str, *, stacklevel: int = 3) -> None:
    """Refuse a flight whose signals disagree, warn of one whose signals may.

    Args:
        checks: :func:`~gpg.flight.consistency`'s result.
        name: the flight's name or file, for the messages.
        stacklevel: the warning's, as :func:`warnings.warn`'s.

    Raises:
        ValueError: a check ``inconsistent``: which signal disagrees with which, by how much,
            the usual causes, and how to read the log unchecked.

    Warns:
        FlightLogWarning: a check ``doubtful``, the same way.
    """
    bad = [c for c in checks if c.verdict == "inconsistent"]
    if bad:
        lines = "; ".join(f"{c.describe()} ({HINTS[c.rate]})" for c in bad)
        raise ValueError(
            f"{name}: the signals disagree with each other: {lines}. Fix the log's format "
            "(units, frames, column order), or read it with check=False to take it as it is"
        )
    doubt = [c for c in checks if c.verdict == "doubtful"]
    if doubt:
        warnings.warn(
            f"{name}: signals that agree only loosely: "
            + "; ".join(f"{c.describe()} ({HINTS[c.rate]})" for c in doubt),
            FlightLogWarning,
            stacklevel=stacklevel,
        )


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
        source: the file the flight was read from (None: made in memory); :func:`write_csv`
            will not overwrite it unless asked.

    The arrays are copies of those given (read-only; the caller's stay the caller's).

    Raises:
        ValueError: naming the signal and its rows, for a wrong shape, NaN or inf, time not
            strictly increasing (repeated or backwards stamps), time that looks like ms or
            us (median steps of half a second or more) or like seconds declared smaller
            (under :data:`MIN_STEP_S`), quaternions far from unit norm, negative rotor speeds,
            commands outside 0..1, a voltage of 0 V or less, neither rotor speeds nor
            commands. A gap (a step over :data:`GAP_FACTOR` times the median) is a
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
    source: str | None = field(default=None, compare=False)

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a string, got {type(self.name).__name__}")
        if self.source is not None and not isinstance(self.source, str):
            raise ValueError(f"source must be a path string or None, got {self.source!r}")
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
            if f.name not in ("name", "source")
        }
        return FlightLog(**kw, name=self.name, source=self.source)

    def replace(self, **changes: np.ndarray | str | None) -> FlightLog:
        """A copy with some fields changed, checked again as a new flight.

        Args:
            **changes: new values of fields, by name (``rpm=...``, ``name=...``).

        Returns:
            The changed flight.
        """
        return dataclasses.replace(self, **changes)


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

    Raises:
        ValueError: naming the field: ``columns`` not a mapping of gpg's names to column
            names (or two names on one column), an unknown frame or unit, ``rotor_order``
            not a permutation of 0..3.
    """

    columns: Mapping[str, str] = field(default_factory=dict)
    world: str = "ned"
    body: str = "frd"
    time_unit: str = "s"
    rotor_speed: str = "rpm"
    rotor_order: Sequence[int] = (0, 1, 2, 3)

    def __post_init__(self):
        if not isinstance(self.columns, Mapping):
            raise ValueError(
                "columns must be a mapping of gpg's names to the log's column names "
                f"({{'t': 'time', ...}}), got {type(self.columns).__name__}"
            )
        unknown = sorted(str(k) for k in set(self.columns) - set(DEFAULT_COLUMNS))
        if unknown:
            raise ValueError(
                f"columns maps unknown name(s) {unknown}; gpg's names are {list(DEFAULT_COLUMNS)}"
            )
        bad = {k: v for k, v in self.columns.items() if not (isinstance(v, str) and v.strip())}
        if bad:
            raise ValueError(f"columns must name each column by a non-empty string, got {bad}")
        names = [self.name(k) for k in DEFAULT_COLUMNS]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"columns gives one column to two of gpg's names: {twice}")
        for what, value, allowed in (
            ("world", self.world, WORLD_FRAMES),
            ("body", self.body, BODY_FRAMES),
            ("time_unit", self.time_unit, TIME_UNITS),
            ("rotor_speed", self.rotor_speed, ROTOR_SPEED_UNITS),
        ):
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(f"{what} must be one of {sorted(allowed)}, got {value!r}")
        order = checked_rotor_order(self.rotor_order, motors=4)
        object.__setattr__(self, "rotor_order", order)

    def name(self, key: str) -> str:
        """The log's column name for one of gpg's names.

        Args:
            key: one of gpg's column names (:data:`DEFAULT_COLUMNS`).

        Returns:
            The name given in :attr:`columns`, else the default.
        """
        return self.columns.get(key, DEFAULT_COLUMNS[key]).strip()

    def to_gpg(
        self, raw: Mapping[str, np.ndarray], name: str, source: str | None = None
    ) -> FlightLog:
        """A :class:`FlightLog` from signals in this format's frames, units and rotor order.

        Positions, velocities and the wind turn by the world frame, rates and the specific
        force by the body frame, the attitude by both (``R_ned_frd = W R Bᵀ``); the quaternion
        keeps its norm so that :class:`FlightLog` checks the log's own values.

        Args:
            raw: signals by gpg's group names (``t``, ``position``, ``quaternion``, ``rpm``,
                ...), each (T,) or (T, k); optional ones absent or None.
            name: the flight's name.
            source: the file they were read from, if any.

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
        return FlightLog(**out, name=name, source=source)


def checked_rotor_order(value: Any, *, motors: int | None) -> tuple[int, int, int, int]:
    """``rotor_order`` as four distinct motor indices, or a ``ValueError`` naming it.

    Args:
        value: for each of gpg's rotors r1..r4, the log's motor index (0-based).
        motors: how many motors the log has (indices below it); None: not known.

    Returns:
        The four indices as integers.

    Raises:
        ValueError: not a sequence of four distinct non-negative integers (a string, floats,
            another length), or an index of a motor the log does not have.
    """
    want = "4 distinct integer motor indices (0-based), e.g. (0, 1, 2, 3)"
    if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, np.ndarray)):
        raise ValueError(f"rotor_order must be {want}, got {value!r}")
    items = list(value)
    bad = [i for i in items if isinstance(i, bool) or not isinstance(i, (int, np.integer))]
    if len(items) != 4 or bad:
        raise ValueError(f"rotor_order must be {want}, got {value!r}")
    order = tuple(int(i) for i in items)
    if len(set(order)) != 4 or min(order) < 0:
        raise ValueError(f"rotor_order must be {want}, got {value!r}")
    if motors is not None and max(order) >= motors:
        raise ValueError(
            f"rotor_order {order} names motor index {max(order)}, but the log has {motors} "
            f"motors (indices 0..{motors - 1})"
        )
    return order  # type: ignore[return-value]


# A PX4 log begins with these bytes (ULog's magic).
ULOG_MAGIC = b"ULog\x01\x12\x35"


def read_csv(
    path: str | Path, fmt: CsvFormat | None = None, *, check: bool = True, **format_options: Any
) -> FlightLog:
    """Read a CSV flight log (module docstring) into gpg's conventions.

    The file is UTF-8 text (a byte-order mark is fine), a header row of column names and one
    row of numbers per sample, each with the header's number of fields.

    Args:
        path: the CSV file (a header row of column names, one row per sample).
        fmt: how the log differs from gpg's conventions; None: the defaults, or the
            keywords.
        check: compare the signals with each other (:func:`~gpg.flight.consistency`):
            refuse the log where they disagree (a unit, order or frame mistake), warn where
            they agree only loosely. False: take the log as it is.
        **format_options: the fields of a :class:`CsvFormat`, instead of ``fmt``
            (``columns={...}, world="enu", rotor_speed="rad/s"``).

    Returns:
        The flight, checked (:class:`FlightLog`), its ``source`` the file.

    Raises:
        ValueError: both ``fmt`` and keywords; an empty file; a file that is not UTF-8 text
            (UTF-16, Latin-1, a PX4 log); broken quoting (the line); a column that a used name
            appears in twice; a row with more or fewer fields than the header (a decimal
            comma?); a required column missing (named, with the columns the file has); a value
            that is not a number (its column and row); neither rotor speed nor command
            columns; signals that disagree (``check``); every check of :class:`CsvFormat` and
            :class:`FlightLog`.

    Warns:
        FlightLogWarning: a file that does not end with a line break: its last line may be
            cut short and is left out; signals that agree only loosely.
    """
    if fmt is not None and format_options:
        raise ValueError("give fmt or its fields as keywords, not both")
    if fmt is not None and not isinstance(fmt, CsvFormat):
        raise ValueError(f"fmt must be a CsvFormat or None, got {type(fmt).__name__}")
    fmt = CsvFormat(**format_options) if fmt is None else fmt
    path = _checked_path(path)
    header, rows, line_of = _csv_table(path)
    index = {h: i for i, h in enumerate(header)}
    used = {fmt.name(k) for k in DEFAULT_COLUMNS}
    twice = sorted({h for h in header if h in used and header.count(h) > 1})
    if twice:
        raise ValueError(f"{path}: column(s) {twice} appear more than once in the header")
    raw: dict[str, np.ndarray | None] = {}

    def column(key: str) -> np.ndarray:
        col = fmt.name(key)
        i = index[col]
        vals = np.empty(len(rows))
        for r, row in enumerate(rows):
            try:
                vals[r] = float(row[i])
            except ValueError:
                raise ValueError(
                    f"{path}: column {col!r} line {line_of[r]} is not a number: {row[i]!r}"
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
    log = fmt.to_gpg(raw, path.stem, source=str(path))
    if check:
        enforce(consistency(log), f"{path}")
    return log


def _checked_path(path: Any) -> Path:
    """``path`` as a Path, or a ``ValueError`` for an empty or non-path value."""
    if not isinstance(path, (str, os.PathLike)) or not str(os.fspath(path)).strip():
        raise ValueError(f"path must be a file path, got {path!r}")
    return Path(path)


def _csv_table(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    """The header, the rows (blank lines left out) and each row's line in the file."""
    data = path.read_bytes()
    if data.startswith(ULOG_MAGIC):
        raise ValueError(f"{path}: a PX4 ULog file, not CSV: read it with gpg.flight.read_ulog")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path}: not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start}): a "
            "UTF-16 or Latin-1 file? save it as UTF-8"
        ) from None
    if "\x00" in text:
        raise ValueError(f"{path}: holds NUL bytes, not CSV text (a UTF-16 file?)")
    if text and not text.endswith(("\n", "\r")):
        cut = max(text.rfind("\n"), text.rfind("\r")) + 1
        warnings.warn(
            f"{path}: the file does not end with a line break: its last line "
            f"({text[cut:][:40]!r}) may be cut short and is left out",
            FlightLogWarning,
            stacklevel=3,
        )
        text = text[:cut]
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    try:
        header = [h.strip() for h in next(reader)]
        lines: list[tuple[int, list[str]]] = []
        for row in reader:
            if row:  # a blank line
                lines.append((reader.line_num, row))
    except StopIteration:
        raise ValueError(f"{path}: empty file, no header row") from None
    except csv.Error as exc:
        raise ValueError(
            f"{path}: line {reader.line_num} is not valid CSV ({exc}): an unclosed quote?"
        ) from None
    for line, row in lines:
        if len(row) != len(header):
            raise ValueError(
                f"{path}: line {line} has {len(row)} fields, the header {len(header)}: a "
                "decimal comma, or a separator inside an unquoted value?"
            )
    return header, [r for _, r in lines], [n for n, _ in lines]


def write_csv(log: FlightLog, path: str | Path, *, replace_source: bool = False) -> Path:
    """Write a flight in gpg's CSV form (default names, gpg's conventions), atomically.

    :func:`read_csv` reads it back with defaults (values written with ``repr``, at full
    precision); absent signals have no columns. An existing file is replaced whole (a
    symbolic link's target, keeping the link; the file's permissions kept).

    Args:
        log: the flight.
        path: the file to write (its folder made; replaced whole, never half-written).
        replace_source: allow writing over the file the flight was read from.

    Returns:
        The path written.

    Raises:
        ValueError: an empty path, a file name longer than the file system allows, or the
            flight's own source file without ``replace_source`` (saying what would be lost:
            the columns the flight did not read, the file's own names, units and frames).
    """
    if not isinstance(log, FlightLog):
        raise ValueError(f"log must be a FlightLog, got {type(log).__name__}")
    path = _checked_path(path)
    cols: list[tuple[str, np.ndarray]] = [("t", log.t)]
    for key, names in _GROUPS.items():
        v = getattr(log, key)
        if v is not None:
            cols += [(n, v[:, i]) for i, n in enumerate(names)]
    if log.voltage is not None:
        cols.append(("voltage", log.voltage))
    if not replace_source and log.source is not None and _same_file(path, log.source):
        raise ValueError(
            f"{path} is the file this flight was read from; writing it would lose "
            f"{_what_is_lost(path, [c for c, _ in cols])}. Write elsewhere, or pass "
            "replace_source=True"
        )
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([c for c, _ in cols])
    data = np.stack([v for _, v in cols], axis=1)
    for row in data:
        w.writerow([repr(float(x)) for x in row])
    return atomic_write(path, buf.getvalue().encode())


def _same_file(path: Path, source: str) -> bool:
    try:
        return os.path.samefile(path, source)
    except OSError:  # either does not exist
        return False


def _what_is_lost(path: Path, written: list[str]) -> str:
    """What rewriting ``path`` in gpg's form drops of it, in words."""
    with open(path, "rb") as f:
        head = f.read(len(ULOG_MAGIC))
    if head == ULOG_MAGIC:
        return "the PX4 log itself (every topic, at its own rate)"
    try:
        first = open(path, encoding="utf-8-sig", newline="").readline()
        header = [h.strip() for h in next(csv.reader([first]), [])]
    except (UnicodeDecodeError, csv.Error):
        header = []
    extra = [h for h in header if h not in written]
    what = f"its column(s) {extra} that the flight did not read, and " if extra else ""
    return f"{what}its own column names, units and frames (rewritten as gpg's: NED, FRD, s, rpm)"


def _checked_time(log: str, t) -> np.ndarray:
    """The time base, checked: finite, strictly increasing, in seconds; gaps warned about."""
    t = np.array(as_float_array(f"{log}: t", t, ndim=1), dtype=np.float64, copy=True)
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
    if med < MIN_STEP_S:
        raise ValueError(
            f"{log}: t steps by {med:.3g} s per sample (median; {1 / med:.4g} Hz), faster than "
            f"any flight log ({MIN_STEP_S:g} s): time looks like seconds declared as ms or us; "
            "give time_unit='s'"
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
        a = np.array(a, dtype=np.float64, copy=True)  # the caller's array stays the caller's
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
    cmd = arrays["command"]
    if cmd is not None:
        out = np.flatnonzero(((cmd < -COMMAND_TOL) | (cmd > 1 + COMMAND_TOL)).any(1))
        if out.size:
            raise ValueError(
                f"{log.name}: command is outside 0..1 at {out.size} row(s): {_rows(out)} "
                f"(range {cmd.min():.4g}..{cmd.max():.4g}); commands are normalised 0..1 "
                "(a -1..1 command: (u + 1) / 2; PWM: read_ulog's pwm_range)"
            )
    volt = arrays["voltage"]
    if volt is not None:
        low = np.flatnonzero(volt <= 0)
        if low.size:
            raise ValueError(
                f"{log.name}: voltage is 0 V or less at {low.size} row(s): {_rows(low)}; a "
                "battery not connected? leave the voltage out (None)"
            )
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
