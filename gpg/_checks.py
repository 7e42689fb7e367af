"""Input validation shared by the public entry points.

Shape and structure problems raise ``ValueError`` naming the offending input. These helpers run
on concrete (non-traced) values, i.e. outside ``jit``; under ``jit`` the library uses
``eqx.error_if`` or a flag in the result instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def as_float_array(name: str, value, *, ndim: int | Sequence[int] | None = None) -> np.ndarray:
    """``value`` as a float64 NumPy array, with its number of dimensions checked. Complex and
    boolean arrays are refused (an imaginary part would be dropped, a mask taken for numbers)."""
    probe = np.asarray(value) if not isinstance(value, np.ndarray) else value
    if np.iscomplexobj(probe):
        raise ValueError(f"{name} must be real, got a complex array")
    if probe.dtype == np.bool_:
        raise ValueError(f"{name} must be numbers, got a boolean array")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array, got {type(value).__name__}") from exc
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in allowed:
            want = " or ".join(str(n) for n in allowed)
            raise ValueError(f"{name} must have {want} dimensions, got shape {arr.shape}")
    return arr


def bad_rows(arr: np.ndarray) -> np.ndarray:
    """Indices along axis 0 of the rows holding a NaN or an infinity."""
    if arr.ndim == 0:
        return np.zeros(0, dtype=int) if np.isfinite(arr) else np.zeros(1, dtype=int)
    flat = arr.reshape(arr.shape[0], -1)
    return np.flatnonzero(~np.all(np.isfinite(flat), axis=1))


def require_finite(name: str, arr: np.ndarray) -> None:
    """Raise ``ValueError`` listing the rows of ``arr`` that hold NaN or inf."""
    rows = bad_rows(arr)
    if rows.size:
        shown = ", ".join(str(int(r)) for r in rows[:10])
        more = f" (and {rows.size - 10} more)" if rows.size > 10 else ""
        raise ValueError(f"{name} holds NaN or inf in {rows.size} row(s): {shown}{more}")


def finite_number(name: str, value, what: str | None = None) -> float:
    """``value`` as a finite float, or a ``ValueError`` naming ``name``: a string, a bool, an
    array or NaN given for a number (``what`` replaces the message's "a number"/"finite")."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be {what or 'a number'}, got {value!r}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{name} must be {what or 'finite'}, got {value!r}")
    return float(value)


def require_positive(name: str, arr) -> None:
    """Raise ``ValueError`` unless every entry of ``arr`` is finite and > 0."""
    a = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(a)) or not np.all(a > 0):
        raise ValueError(f"{name} must be finite and > 0, got {a.tolist()}")


def require_shape(name: str, arr: np.ndarray, shape: tuple) -> None:
    """Raise ``ValueError`` unless ``arr.shape`` matches ``shape`` (``None`` = any size)."""
    ok = arr.ndim == len(shape) and all(
        s is None or s == a for s, a in zip(shape, arr.shape, strict=True)
    )
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")


def no_hash(self) -> int:
    """``__hash__`` of a model that holds arrays: a ``TypeError`` that says what to jit instead.

    ``jax.jit(model.predict)`` hashes the bound method, hence the model and its arrays; were it
    hashable, jit would bake the arrays into the program as constants (slow to compile, one
    program per model). The model belongs among the arguments."""
    name = type(self).__name__
    raise TypeError(
        f"a {name} holds arrays and has no hash, so jax.jit cannot take its bound methods "
        f"(jax.jit(model.predict)): pass the model as an argument, "
        f"jax.jit({name}.predict)(model, ...), or use equinox.filter_jit(model.predict)"
    )
