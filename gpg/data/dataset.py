"""The dataset file: one ``.npz`` of arrays plus a JSON sidecar (docs/design.md, "Dataset file").

Arrays: ``x (N, 8)`` (``(N, 7)`` in the body frame: ``meta["frame"] == "body"``, inputs
:func:`gpg.names.inputs`), ``y_aero (N, 6)``, ``jac_aero (N, 6, 7)``, ``y_noise (N, 3)``,
``jac_noise (N, 3, 7)``, and the raw finite-difference samples ``x_raw (8N, 8)``,
``y_raw (8N, 6 or 9)`` for the 8X baselines (point-major: rows ``8i..8i+7`` are point ``i``
and its seven perturbations). Noise, gradients and raw samples may each be absent (a user's
own CHARM, wind-tunnel or flight data); :attr:`Dataset.missing` says what is.

Sidecar: schema version, units, column names, bounds, generator and its parameters, seed.
Files are written atomically (temporary files, then rename) and deterministically (fixed zip
timestamps, sorted JSON), so the same data gives bit-identical files.
"""

from __future__ import annotations

import csv
import io
import json
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gpg._checks import as_float_array, require_finite, require_shape
from gpg._io import atomic_write
from gpg.names import AERO, FRAMES, GRAD_INPUTS, NOISE, UNITS, grad_inputs, inputs

__all__ = ["Dataset", "from_csv", "unit_factor"]

SCHEMA_VERSION = 1
_ARRAYS = ("x", "y_aero", "jac_aero", "y_noise", "jac_noise", "x_raw", "y_raw", "grad_dirs")
_PER_CASE = ("x", "y_aero", "jac_aero", "y_noise", "jac_noise", "grad_dirs")
_OPTIONAL = {
    "noise": ("y_noise",),
    "gradients": ("jac_aero",),
    "noise gradients": ("jac_noise",),
    "raw samples": ("x_raw", "y_raw"),
}


@dataclass(frozen=True)
class Dataset:
    """Arrays and metadata of one dataset; see the module docstring for shapes and units."""

    x: np.ndarray
    y_aero: np.ndarray
    jac_aero: np.ndarray | None = None
    y_noise: np.ndarray | None = None
    jac_noise: np.ndarray | None = None
    x_raw: np.ndarray | None = None
    y_raw: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    # (N, 7, 7) or None: gradient column g of case i (jac_aero[i, :, g], jac_noise likewise) is
    # the derivative along Σ_h grad_dirs[i, g, h] e_h over the 7 gradient inputs, in their
    # units (None: along input g itself). Written by gpg.data.convert.to_body, whose angle
    # gradients become derivatives along directions of (u, v, w).
    grad_dirs: np.ndarray | None = None

    def __post_init__(self):
        for name in _ARRAYS:
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, as_float_array(name, v))
        self.validate()

    # -- structure ------------------------------------------------------------------------------

    @property
    def n(self) -> int:
        return self.x.shape[0]

    @property
    def frame(self) -> str:
        """``"airflow"`` (the paper's inputs, the default) or ``"body"`` (``meta["frame"]``)."""
        return self.meta.get("frame", "airflow")

    @property
    def inputs(self) -> tuple[str, ...]:
        """The names of the columns of ``x`` (:func:`gpg.names.inputs` of :attr:`frame`)."""
        return inputs(self.frame)

    @property
    def airspeed(self) -> np.ndarray:
        """Each case's airspeed (N,), m/s: the last input in the airflow frame, ``|(u, v, w)|``
        in the body frame."""
        return self.x[:, 7] if self.frame == "airflow" else np.linalg.norm(self.x[:, 4:7], axis=1)

    @property
    def has_noise(self) -> bool:
        return self.y_noise is not None

    @property
    def has_gradients(self) -> bool:
        return self.jac_aero is not None and (not self.has_noise or self.jac_noise is not None)

    @property
    def has_raw(self) -> bool:
        return self.x_raw is not None

    @property
    def missing(self) -> tuple[str, ...]:
        """What this dataset lacks: "noise", "gradients", "noise gradients", "raw samples"."""
        out = []
        for what, names in _OPTIONAL.items():
            if what == "noise gradients" and not self.has_noise:
                continue
            if all(getattr(self, nm) is None for nm in names):
                out.append(what)
        return tuple(out)

    @property
    def output_names(self) -> tuple[str, ...]:
        return AERO + NOISE if self.has_noise else AERO

    @property
    def y(self) -> np.ndarray:
        """All outputs (N, 6 or 9)."""
        return self.y_aero if not self.has_noise else np.concatenate([self.y_aero, self.y_noise], 1)

    @property
    def jac(self) -> np.ndarray | None:
        """All output gradients (N, 6 or 9, 7), or None without gradients."""
        if not self.has_gradients:
            return None
        return (
            self.jac_aero
            if not self.has_noise
            else np.concatenate([self.jac_aero, self.jac_noise], 1)
        )

    def summary(self) -> str:
        """A one-line description of the dataset.

        Returns:
            The number of points, the outputs, the source (generator or file) and what the
            dataset lacks.
        """
        lacks = ", ".join(self.missing) or "nothing"
        src = self.meta.get("generator", {}).get("name", self.meta.get("source", "unknown source"))
        return f"{self.n} points, outputs {list(self.output_names)}, from {src}; lacks: {lacks}"

    def validate(self) -> None:
        """Check the shapes, the finiteness and the box of the arrays (run on construction).

        Gradients may be NaN only where a perturbation was not run (for every output of the
        case and input); the rotor speeds and the airflow frame's airspeed must be ≥ 0; when
        ``meta["bounds"]`` is given, every case lies in that box (and the body frame's ball).

        Raises:
            ValueError: naming the array and, for NaN/inf or a case out of the box, the rows:
                an unknown frame, a wrong shape, ``jac_noise`` without ``y_noise``,
                ``grad_dirs`` without ``jac_aero``, raw samples not 8 per point, a value that
                is not finite, a negative rotor speed or airspeed, or a case out of the box.
        """
        if self.frame not in FRAMES:
            raise ValueError(f"meta['frame'] must be one of {list(FRAMES)}, got {self.frame!r}")
        d = len(self.inputs)
        require_shape("x", self.x, (None, d))
        n = self.x.shape[0]
        require_shape("y_aero", self.y_aero, (n, 6))
        if self.jac_aero is not None:
            require_shape("jac_aero", self.jac_aero, (n, 6, 7))
        if self.y_noise is not None:
            require_shape("y_noise", self.y_noise, (n, 3))
        if self.jac_noise is not None:
            if self.y_noise is None:
                raise ValueError("jac_noise given without y_noise")
            require_shape("jac_noise", self.jac_noise, (n, 3, 7))
        if self.grad_dirs is not None:
            if self.jac_aero is None:
                raise ValueError("grad_dirs given without jac_aero: it gives their directions")
            require_shape("grad_dirs", self.grad_dirs, (n, 7, 7))
        if (self.x_raw is None) != (self.y_raw is None):
            raise ValueError("x_raw and y_raw must be given together")
        if self.x_raw is not None:
            require_shape("x_raw", self.x_raw, (None, d))
            m = self.x_raw.shape[0]
            require_shape("y_raw", self.y_raw, (m, 9 if self.has_noise else 6))
            if m != 8 * n:
                raise ValueError(
                    f"x_raw has {m} rows; the raw finite-difference samples of {n} points are "
                    f"8 per point ({8 * n} rows: the base point and one step per input)"
                )
        for name in _ARRAYS:
            v = getattr(self, name)
            if v is not None and name not in ("jac_aero", "jac_noise"):
                require_finite(name, v)  # names the offending row indices
        self._validate_gradients()
        if np.any(self.x[:, :4] < 0):
            rows = np.flatnonzero(np.any(self.x[:, :4] < 0, axis=1))
            raise ValueError(f"x has negative rotor speeds in row(s) {rows[:10].tolist()}")
        if self.frame == "airflow" and np.any(self.x[:, 7] < 0):
            rows = np.flatnonzero(self.x[:, 7] < 0)
            raise ValueError(
                f"x has a negative airspeed (a speed, ≥ 0 m/s) in row(s) {rows[:10].tolist()}"
            )
        if "bounds" in self.meta:
            self._validate_inside_bounds()

    def _validate_inside_bounds(self) -> None:
        """The cases lie in the box the metadata declares (``meta["bounds"]``, the sampling
        box and the surrogate's ``in_domain``): a case outside it is a unit or sign slip
        (degrees read as radians, yaw 400°), or the box is wrong; either way it is refused,
        naming the rows, the input and its value in the box's units."""
        from gpg.data.bounds import Bounds

        box = Bounds.from_config(self.meta["bounds"], "meta['bounds']")
        lo, hi = box.arrays(self.frame)
        tol = 1e-9 * np.maximum(hi - lo, 1.0)  # the degree-to-radian conversion's rounding
        out = (self.x < lo - tol) | (self.x > hi + tol)
        if self.frame == "body":  # the ball of air velocities, not its bounding box
            speed = np.linalg.norm(self.x[:, 4:7], axis=1)
            far = speed > box.airspeed[1] * (1 + 1e-9)
            if far.any():
                rows = np.flatnonzero(far)
                raise ValueError(
                    f"x has {rows.size} case(s) outside the ball of air velocities the dataset "
                    f"declares (airspeed up to {box.airspeed[1]:g} m/s), in row(s) "
                    f"{rows[:10].tolist()}: row {rows[0]} has |(u, v, w)| = "
                    f"{speed[rows[0]]:g} m/s"
                )
        if not out.any():
            return
        rows = np.flatnonzero(out.any(axis=1))
        r, j = rows[0], int(np.flatnonzero(out[rows[0]])[0])
        names = self.inputs
        deg = 180.0 / np.pi if 4 <= j <= 6 and self.frame == "airflow" else 1.0
        unit = "°" if deg != 1.0 else f" {UNITS[names[j]]}"
        more = f" (and {rows.size - 10} more)" if rows.size > 10 else ""
        raise ValueError(
            f"x has {rows.size} case(s) outside the box the dataset declares (its 'bounds'), in "
            f"row(s) {rows[:10].tolist()}{more}: row {r} has {names[j]} = {self.x[r, j] * deg:g}"
            f"{unit}, outside [{lo[j] * deg:g}, {hi[j] * deg:g}]{unit}; check the units (angles "
            "in degrees need units={'yaw': 'deg', ...}) or widen the bounds"
        )

    def _validate_gradients(self) -> None:
        """Gradients are finite, or NaN for every output of a (case, input): a perturbation
        that was not run (:attr:`gradient_mask`). Anything else names the rows."""
        jac = self.jac if self.jac_aero is not None else None
        if jac is None:
            return
        nan = np.isnan(jac)
        if np.isinf(jac).any():
            require_finite("jac_aero" if np.isinf(self.jac_aero).any() else "jac_noise", jac)
        partial = np.any(nan.any(axis=1) & ~nan.all(axis=1), axis=1)
        if partial.any():
            rows = np.flatnonzero(partial)[:10].tolist()
            raise ValueError(
                f"gradients are NaN for some outputs but not others in row(s) {rows}: NaN "
                "marks a perturbation that was not run, so it is NaN for every output or none"
            )
        if self.jac_noise is not None and self.y_noise is not None:
            aero_nan, noise_nan = np.isnan(self.jac_aero), np.isnan(self.jac_noise)
            if np.any(aero_nan.all(axis=1) != noise_nan.all(axis=1)):
                raise ValueError("jac_aero and jac_noise must lack the same perturbations")

    def repeated_inputs(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Cases that share an input ``x`` exactly.

        Repeated runs of a noisy experiment are such groups; so are rows pasted twice with a
        typo. A group is conflicting when its outputs or gradients differ (NaN gradients, not
        run, compare equal).

        Returns:
            ``(conflicting, identical)``, each a list of row-index groups sorted by first row.
        """
        _, inverse, counts = np.unique(self.x, axis=0, return_inverse=True, return_counts=True)
        conflicting, identical = [], []
        for g in np.flatnonzero(counts > 1):
            rows = np.flatnonzero(inverse.ravel() == g)
            same = all(
                np.array_equal(a[rows], np.broadcast_to(a[rows[:1]], a[rows].shape), equal_nan=True)
                for a in (self.y, self.jac)
                if a is not None
            )
            (identical if same else conflicting).append(rows)
        return sorted(conflicting, key=lambda g: g[0]), sorted(identical, key=lambda g: g[0])

    @property
    def gradient_mask(self) -> np.ndarray | None:
        """(N, 7) which gradient inputs each case has (True: its perturbation was run), or
        None when the dataset has no gradients. A case's missing ones are NaN in ``jac_*``."""
        if self.jac_aero is None:
            return None
        return ~np.isnan(self.jac_aero[:, 0, :])

    @property
    def runs(self) -> int:
        """Simulator runs behind the dataset: per case one, plus one per gradient input run."""
        mask = self.gradient_mask
        return self.n + (0 if mask is None else int(mask.sum()))

    def subset(self, index: np.ndarray) -> Dataset:
        """The dataset of some of its points, their raw samples included.

        Args:
            index: the indices of the points to keep, in the order wanted.

        Returns:
            The :class:`Dataset` of those points; ``meta["subset_of"]`` names this one.
        """
        index = np.asarray(index)
        kw = {k: (None if getattr(self, k) is None else getattr(self, k)[index]) for k in _PER_CASE}
        if self.has_raw:
            per = self.x_raw.shape[0] // self.n
            raw = (index[:, None] * per + np.arange(per)).ravel()
            kw["x_raw"], kw["y_raw"] = self.x_raw[raw], self.y_raw[raw]
        return Dataset(**kw, meta={**self.meta, "subset_of": self.meta.get("name")})

    def without(self, *what: str) -> Dataset:
        """A copy without some optional parts.

        Dropping the noise also drops the noise gradients and the raw samples' levels;
        dropping the gradients also drops their directions (``grad_dirs``).

        Args:
            *what: the parts to drop: ``"noise"``, ``"gradients"``, ``"raw samples"``.

        Returns:
            The :class:`Dataset` without them.

        Raises:
            ValueError: if a part is none of those, naming it.
        """
        bad = [w for w in what if w not in ("noise", "gradients", "raw samples")]
        if bad:
            raise ValueError(f"unknown parts {bad}; valid: noise, gradients, raw samples")
        kw: dict[str, Any] = {}
        if "noise" in what:
            kw.update(y_noise=None, jac_noise=None)
            if self.has_raw:
                kw["y_raw"] = self.y_raw[:, :6]
        if "gradients" in what:
            kw.update(jac_aero=None, jac_noise=None, grad_dirs=None)
        if "raw samples" in what:
            kw.update(x_raw=None, y_raw=None)
        return replace(self, **kw)

    # -- files ----------------------------------------------------------------------------------

    def save(self, path: str | Path) -> tuple[Path, Path]:
        """Write the dataset as ``<path>.npz`` and its ``<path>.json`` sidecar, atomically.

        The arrays are written first, so a sidecar only ever describes arrays in place; equal
        data give bit-identical files (fixed zip timestamps, sorted JSON).

        Args:
            path: the files' path without suffix (a ``.npz`` or ``.json`` suffix is dropped).

        Returns:
            The paths of the ``.npz`` and the ``.json`` file.
        """
        self.validate()
        npz, side = _paths(path)
        npz.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            **self.meta,
            "schema_version": SCHEMA_VERSION,
            "n": self.n,
            "inputs": list(self.inputs),
            "outputs": list(self.output_names),
            "units": {k: UNITS[k] for k in self.inputs + self.output_names},
            "arrays": [k for k in _ARRAYS if getattr(self, k) is not None],
            "missing": list(self.missing),
        }
        zbytes = _npz_bytes({k: getattr(self, k) for k in meta["arrays"]})
        jbytes = (json.dumps(_jsonable(meta), indent=2, sort_keys=True) + "\n").encode()
        # Arrays first: a sidecar only ever describes arrays that are already in place.
        atomic_write(npz, zbytes)
        atomic_write(side, jbytes)
        return npz, side

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        """Read a dataset written by :meth:`save`.

        Args:
            path: the files' path without suffix (a ``.npz`` or ``.json`` suffix is dropped).

        Returns:
            The :class:`Dataset`, validated as on construction.

        Raises:
            ValueError: if a file is missing, the sidecar is not a JSON object or has another
                schema version, or the ``.npz`` is unreadable, holds non-numeric or unknown
                arrays, or lacks ``x`` or ``y_aero``.
        """
        npz, side = _paths(path)
        for p in (npz, side):
            if not p.is_file():
                raise ValueError(f"dataset file {p} does not exist")
        try:
            meta = json.loads(side.read_bytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{side} is not valid UTF-8 JSON: {exc}") from exc
        if not isinstance(meta, dict):
            raise ValueError(f"{side} must hold a JSON object, got {type(meta).__name__}")
        version = meta.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ValueError(
                f"{side} has schema version {version}; this gpg reads {SCHEMA_VERSION}"
            )
        try:
            with np.load(npz, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError, zlib.error) as exc:
            raise ValueError(f"{npz} is not a readable .npz file: {exc}") from exc
        bad = sorted(
            k
            for k, a in arrays.items()
            if not isinstance(a, np.ndarray) or not np.issubdtype(a.dtype, np.number)
        )
        if bad:
            raise ValueError(f"{npz} holds members that are not numeric arrays: {bad}")
        unknown = sorted(set(arrays) - set(_ARRAYS))
        if unknown:
            raise ValueError(f"{npz} holds unknown arrays {unknown}")
        for k in ("x", "y_aero"):
            if k not in arrays:
                raise ValueError(f"{npz} lacks the required array {k!r}")
        for k in ("schema_version", "n", "inputs", "outputs", "units", "arrays", "missing"):
            meta.pop(k, None)
        return cls(**arrays, meta=meta)


def _paths(path: str | Path) -> tuple[Path, Path]:
    p = Path(path)
    if p.suffix in (".npz", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".npz"), p.with_name(p.name + ".json")


def _npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """An ``.npz`` (zip of ``.npy``) with fixed timestamps, so equal data give equal bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            body = io.BytesIO()
            np.lib.format.write_array(body, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(info, body.getvalue())
    return buf.getvalue()


def _jsonable(o: Any) -> Any:
    if isinstance(o, Mapping):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return o


# ----------------------------------------------------------------------------------------------
# CSV import
# ----------------------------------------------------------------------------------------------

# Conversion factors to the schema's units (SI, rpm, rad), by quantity.
_UNIT_FACTORS = {
    "rpm": {"rpm": 1.0, "rad/s": 60.0 / (2 * np.pi), "hz": 60.0, "rps": 60.0},
    "rad": {"rad": 1.0, "deg": np.pi / 180.0},
    "m/s": {"m/s": 1.0, "km/h": 1 / 3.6, "kn": 1852.0 / 3600.0, "ft/s": 0.3048},
    "N": {"N": 1.0, "lbf": 4.4482216152605},
    "N*m": {
        "N*m": 1.0,
        "Nm": 1.0,
        "N.m": 1.0,
        "lbf*ft": 1.3558179483314,
        "lbf*in": 0.1129848290276,
    },
    "dB": {"dB": 1.0},
}
GRADIENT_COLUMNS = tuple(f"d{o}/d{i}" for o in AERO + NOISE for i in GRAD_INPUTS)
_BODY_GRADIENT_COLUMNS = tuple(f"d{o}/d{i}" for o in AERO + NOISE for i in grad_inputs("body"))


def unit_factor(field: str, unit: str | None) -> float:
    """The factor from a unit to the schema's unit of a field.

    Args:
        field: the schema field (``r1``, ``yaw``, ``airspeed``, ``Fx``, ``Mz``, ``L1``, ...).
        unit: the unit of the values (``"deg"``, ``"km/h"``, ``"lbf"``, ...); None for the
            schema's own.

    Returns:
        The factor that converts values in ``unit`` to the schema's unit (1 for None).

    Raises:
        ValueError: if ``unit`` is not known for ``field``'s quantity.
    """
    base = UNITS[field]
    if unit is None:
        return 1.0
    table = _UNIT_FACTORS[base]
    if unit not in table:
        raise ValueError(f"unknown unit {unit!r} for {field}; valid: {sorted(table)}")
    return table[unit]


# Long by design: one pass over the CSV whose steps (columns, units, gradients, raw samples,
# vehicle, bounds) each check and name their own input; split, they would pass a dozen
# half-built arrays between them.
def from_csv(
    path: str | Path,
    columns: Mapping[str, str],
    *,
    units: Mapping[str, str] | None = None,
    gradients: str | None = None,
    vehicle: Any = None,
    bounds: Mapping[str, Any] | None = None,
    meta: Mapping[str, Any] | None = None,
    frame: str = "airflow",
) -> Dataset:
    """Import a CSV file by mapping schema fields to its column names.

    Inputs and the six aerodynamic outputs are required, the levels optional. Gradients are
    optional and complete if present: map each one in ``columns`` (``"dFx/dr1": "..."``) or
    give a ``gradients`` pattern. An empty gradient cell means that perturbation was not run
    for that case (it must then be empty for every output). Gradients are converted with the
    units of their output and input. A NaN, inf or non-number in the file is reported by CSV
    line and column.

    Args:
        path: the CSV file (UTF-8, one header line).
        columns: schema fields (``r1..r4, yaw, pitch, roll, airspeed, Fx..Mz, L1..L3``; in
            the body frame ``r1..r4, u, v, w``) to the CSV's header names.
        units: a field's unit in the file where it is not the schema's (e.g.
            ``{"yaw": "deg", "airspeed": "km/h"}``; see :func:`unit_factor`).
        gradients: a pattern naming the CSV header of ``∂output/∂input`` from the CSV headers
            of the two (``{output}``, ``{input}``) or from their schema names
            (``{output_field}``, ``{input_field}``), e.g. ``"d{output}_d{input}"``.
        vehicle: a name in ``conf/vehicle`` or a YAML path, recorded in the dataset so that
            :meth:`gpg.Surrogate.fit` uses it.
        bounds: the input box the data were sampled in, in the ``data.bounds`` form (``rpm``,
            ``yaw_deg``, ``pitch_deg``, ``roll_deg``, ``airspeed``; in the body frame ``rpm``
            and ``airspeed``, the ball's radius), recorded for the surrogate's ``in_domain``.
        meta: more metadata to record.
        frame: ``"airflow"`` (the paper's inputs) or ``"body"`` (inputs ``r1..r4, u, v, w``:
            the air velocity in the body frame, m/s; outputs in the body frame; gradients
            along all seven inputs, ``"dFx/du"``).

    Returns:
        The :class:`Dataset`, in the schema's units.

    Raises:
        ValueError: if an argument has the wrong type or names an unknown field, unit or
            frame, a required field or gradient is missing, one CSV column feeds two fields,
            both gradient forms are given, the vehicle or bounds are invalid, a vehicle is
            given as an object, or the file is missing or unreadable or holds a bad value
            (naming the line and column).
    """
    for name, arg in (("columns", columns), ("units", units), ("meta", meta)):
        if arg is not None and not isinstance(arg, Mapping):
            raise ValueError(
                f"from_csv: {name} must be a mapping (schema field -> "
                f"{'CSV header' if name == 'columns' else 'value'}), got a "
                f"{type(arg).__name__}"
            )
    names, gnames = inputs(frame), grad_inputs(frame)  # a ValueError names a bad frame
    grad_fields = GRADIENT_COLUMNS if frame == "airflow" else _BODY_GRADIENT_COLUMNS
    if columns is None:
        raise ValueError(
            "from_csv: columns is required: a mapping of schema fields (r1..r4, yaw, pitch, roll, "
            "airspeed, Fx..Mz, optionally L1..L3) to the CSV's header names"
        )
    units = dict(units or {})
    columns = dict(columns)
    known = set(names + AERO + NOISE) | set(grad_fields)
    unknown = sorted(set(columns) - known)
    if unknown:
        raise ValueError(
            f"unknown schema fields {unknown} (frame {frame!r}); valid: "
            f"{list(names + AERO + NOISE)} and gradients like 'dFx/dr1'"
        )
    bad_units = sorted(set(units) - set(UNITS))
    if bad_units:
        raise ValueError(f"units given for unknown fields {bad_units}")
    for f, u in units.items():
        unit_factor(f, u)
    missing = [f for f in names + AERO if f not in columns]
    if missing:
        raise ValueError(f"columns mapping lacks required fields {missing}")
    noise = [f for f in NOISE if f in columns]
    if noise and len(noise) != 3:
        raise ValueError(f"noise needs all of {list(NOISE)}, got {noise}")
    _check_one_field_per_column(columns)
    outs = AERO + (NOISE if noise else ())
    if gradients is not None:
        if any(g in columns for g in grad_fields):
            raise ValueError("give gradient columns either one by one or by a pattern, not both")
        columns.update(_gradient_columns(gradients, columns, outs, gnames))
        _check_one_field_per_column(columns)
    grads = [g for g in grad_fields if g in columns]
    want_grads = [f"d{o}/d{i}" for o in outs for i in gnames]
    if grads and sorted(grads) != sorted(want_grads):
        lacking = sorted(set(want_grads) - set(grads))
        raise ValueError(f"gradients must be complete; missing {lacking[:6]} ...")
    extra_meta: dict[str, Any] = {}
    if vehicle is not None:
        from gpg.quadrotor.vehicle import Vehicle, vehicle_config

        if isinstance(vehicle, Vehicle):
            raise ValueError("pass the vehicle as a name or a YAML path, so that it is recorded")
        cfg = vehicle_config(vehicle)
        Vehicle.from_config(cfg)  # a broken vehicle file fails here, before the CSV is read
        extra_meta["vehicle"] = cfg
    if bounds is not None:
        from gpg.data.bounds import Bounds

        Bounds.from_config(bounds)
        extra_meta["bounds"] = {k: list(v) for k, v in bounds.items()}
    if frame != "airflow":
        extra_meta["frame"] = frame

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"CSV file {path} does not exist")
    data = _read_csv(path, columns, blank={columns[g] for g in grad_fields if g in columns})
    col = {k: data[:, j] for j, k in enumerate(columns)}

    def get(fields):
        return np.stack([col[k] * unit_factor(k, units.get(k)) for k in fields], axis=1)

    def grad(outputs):
        out = np.empty((data.shape[0], len(outputs), 7))
        for a, o in enumerate(outputs):
            for b, i in enumerate(gnames):
                out[:, a, b] = (
                    col[f"d{o}/d{i}"] * unit_factor(o, units.get(o)) / unit_factor(i, units.get(i))
                )
        return out

    return Dataset(
        x=get(names),
        y_aero=get(AERO),
        y_noise=get(NOISE) if noise else None,
        jac_aero=grad(AERO) if grads else None,
        jac_noise=grad(NOISE) if grads and noise else None,
        meta={"source": f"csv:{path.name}", **extra_meta, **dict(meta or {})},
    )


def _check_one_field_per_column(columns: Mapping[str, str]) -> None:
    """One CSV column cannot feed two fields (a typo that would silently copy data)."""
    by_column: dict[str, list[str]] = {}
    for name, head in columns.items():
        if not isinstance(head, str):
            raise ValueError(f"columns[{name!r}] must be a CSV header name, got {head!r}")
        by_column.setdefault(head, []).append(name)
    twice = {h: f for h, f in by_column.items() if len(f) > 1}
    if twice:
        h, f = next(iter(twice.items()))
        raise ValueError(
            f"CSV column {h!r} is mapped to {len(f)} fields {f}: one column, one field"
        )


def _gradient_columns(
    pattern: str, columns: Mapping[str, str], outs, gnames=GRAD_INPUTS
) -> dict[str, str]:
    """Schema gradient field -> CSV header, from a pattern (see :func:`from_csv`)."""
    out = {}
    for o in outs:
        for i in gnames:
            try:
                out[f"d{o}/d{i}"] = pattern.format(
                    output=columns[o], input=columns[i], output_field=o, input_field=i
                )
            except (KeyError, IndexError, ValueError) as exc:
                raise ValueError(
                    f"bad gradients pattern {pattern!r}: use {{output}}, {{input}}, "
                    f"{{output_field}} and {{input_field}} ({exc})"
                ) from exc
    if len(set(out.values())) != len(out):
        raise ValueError(f"gradients pattern {pattern!r} gives the same header twice")
    return out


def _read_csv(path: Path, columns: Mapping[str, str], blank=frozenset()) -> np.ndarray:
    """The mapped columns as floats. Refused, with the file, line and column: bytes that are
    not UTF-8, a duplicated header name, a row with more or fewer fields than the header (an
    unquoted thousands separator, ``3,600.5``, makes one more), an over-long cell, and every
    cell that is not a finite number, except an empty cell in a column of ``blank`` (a
    gradient whose perturbation was not run), read as NaN. A UTF-8 byte-order mark is read and
    dropped."""
    text = _decode(path)
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path.name} is empty: no header line")
        seen: dict[str, int] = {}
        for j, h in enumerate(header, start=1):
            if h in seen:
                raise ValueError(
                    f"{path.name}, line 1: header {h!r} appears twice (columns {seen[h]} and {j}); "
                    "one of them would silently win"
                )
            seen[h] = j
        absent = sorted(c for c in columns.values() if c not in seen)
        if absent:
            shown = absent[:8] + (["..."] if len(absent) > 8 else [])
            raise ValueError(f"CSV columns {shown} not in {path.name}; it has {header}")
        where = [(head, seen[head] - 1) for head in columns.values()]
        rows, bad = [], []
        for row in reader:
            line = reader.line_num
            if not row:  # a blank line
                continue
            if len(row) != len(header):
                hint = (
                    " (an unquoted thousands separator such as 3,600.5 adds a field)"
                    if len(row) > len(header)
                    else ""
                )
                raise ValueError(
                    f"{path.name}, line {line}: {len(row)} fields, but the header has "
                    f"{len(header)}{hint}"
                )
            vals = []
            for head, j in where:
                cell = row[j]
                if head in blank and not cell.strip():
                    vals.append(np.nan)
                    continue
                try:
                    v = float(cell)
                except ValueError:
                    bad.append(f"line {line}, column {j + 1} ({head!r}): not a number ({cell!r})")
                    v = np.nan
                else:
                    if not np.isfinite(v):
                        bad.append(f"line {line}, column {j + 1} ({head!r}): {cell}")
                vals.append(v)
            rows.append(vals)
    except csv.Error as exc:  # e.g. a cell beyond the csv module's field size limit
        raise ValueError(f"{path.name}, line {reader.line_num}: unreadable CSV: {exc}") from exc
    if bad:
        more = f" (and {len(bad) - 10} more)" if len(bad) > 10 else ""
        raise ValueError(f"{path.name} has bad values: " + "; ".join(bad[:10]) + more)
    if not rows:
        raise ValueError(f"{path.name} has a header but no data rows")
    return np.asarray(rows, dtype=float).reshape(-1, len(columns))


def _decode(path: Path) -> str:
    """The file as text: UTF-8 (a byte-order mark dropped), or a ``ValueError`` naming the
    line and column of the first byte that is not UTF-8."""
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        col = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ValueError(
            f"{path.name}, line {line}, byte {col}: not UTF-8 ({raw[exc.start : exc.start + 1]!r});"
            " save the file as UTF-8"
        ) from None
