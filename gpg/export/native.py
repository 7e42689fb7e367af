"""A surrogate's C (:func:`gpg.export.to_c`) built by the system's C compiler into a shared
library and called from Python through ctypes: the same arithmetic as the C a flight
computer runs, at its cost plus a foreign call's, with no JAX dispatch in between. What the
online filters' updates need from Python where a compiled JAX step pays per operation (a bank
of online terms scores its members under the offline band at every label), and what checks a
C export against the library in the user's own process."""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import weakref
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from gpg.export.c_source import to_c

__all__ = ["FLAGS", "Native", "NativePrediction", "to_native"]

# What the project's own timing and tests build with (one core, the C99 the source is in).
FLAGS = ("-O2", "-std=c99")


def _packed(*args: tuple[str, int]) -> tuple[tuple[str, int, int], ...]:
    """Arguments laid one after another in one buffer: name, length and first index."""
    starts = np.cumsum([0] + [n for _, n in args])
    return tuple((key, n, int(at)) for (key, n), at in zip(args, starts, strict=False))


# A state's arguments, and the online update's after t, in the order of their C declarations
# (and of gpg.flight.Labels.columns).
_STATE = _packed(("rpm", 4), ("euler", 3), ("v_air", 3))
_UPDATE = _packed(*((key, n) for key, n, _ in _STATE), ("force", 3), ("torque", 3),
                  ("force_var", 3), ("torque_var", 3))  # fmt: skip


class NativePrediction(NamedTuple):
    """One state's prediction from the C: as :class:`gpg.surrogate.Prediction`, in NumPy
    (float64; ``variance`` None where the export has none)."""

    force: np.ndarray
    torque: np.ndarray
    levels: np.ndarray
    variance: np.ndarray | None
    in_domain: bool


class Native:
    """A compiled export, loaded (made by :func:`to_native`). It holds the online state, if
    the model has one, in :attr:`state`, starting at the exported state; :meth:`update` moves
    it one label and :meth:`predict` reads it. Not thread-safe: one state, updated in place.

    Attributes:
        lib: the loaded library (``ctypes.CDLL``): the header's functions, ``<name>_*``.
        name: the C identifier the export was written under.
        directory: where the source, the header and the library are.
        n_levels: ``K``, the tonal noise levels predicted.
        has_variance: whether ``predict`` gives the variance.
        online: whether the model has an online term (adapted, tracked or a bank).
        state: the online state's bytes, laid out as the header's ``<name>_online`` (None
            without an online term).
    """

    def __init__(self, lib, name: str, directory: Path, n_levels: int, has_variance: bool):
        self.lib, self.name, self.directory = lib, name, directory
        self.n_levels, self.has_variance = int(n_levels), bool(has_variance)
        vp = ctypes.c_void_p
        self._in = np.zeros(sum(n for _, n, _ in _STATE))
        self._row = np.zeros(sum(n for _, n, _ in _UPDATE))
        self._out = np.zeros(12 + 2 * self.n_levels + 1)  # force, torque, levels, variance
        self._in_p = tuple(self._in.ctypes.data + 8 * at for _, _, at in _STATE)
        self._row_p = tuple(self._row.ctypes.data + 8 * at for _, _, at in _UPDATE)
        k = self.n_levels
        self._out_p = tuple(self._out.ctypes.data + 8 * at for at in (0, 3, 6, 6 + max(k, 1)))
        call = getattr(lib, f"{name}_predict" if has_variance else f"{name}_mean")
        call.argtypes, call.restype = [vp] * (7 if has_variance else 6), ctypes.c_int
        self._predict = call
        self.online = hasattr(lib, f"{name}_online_init")
        self.state = None
        if self.online:
            size = getattr(lib, f"{name}_online_size")
            size.restype = ctypes.c_size_t
            self.state = ctypes.create_string_buffer(size())
            self._state_p = ctypes.addressof(self.state)
            upd, pre = getattr(lib, f"{name}_online_update"), getattr(lib, f"{name}_online_predict")
            upd.argtypes, upd.restype = [vp, ctypes.c_double] + [vp] * 7, ctypes.c_int
            pre.argtypes, pre.restype = [vp] * 8, ctypes.c_int
            self._update, self._online_predict = upd, pre
            self.reset()

    def reset(self) -> None:
        """The online state back to the exported one (``<name>_online_init``).

        Raises:
            ValueError: for a model without an online term.
        """
        self._need_online("reset")
        getattr(self.lib, f"{self.name}_online_init")(ctypes.c_void_p(self._state_p))

    def predict(self, rpm: ArrayLike, euler: ArrayLike, v_air: ArrayLike) -> NativePrediction:
        """One state's prediction (``<name>_online_predict`` with an online term, at its
        current state; else ``<name>_predict``, or ``<name>_mean`` without the variance).

        Args:
            rpm: (4,) rotor speeds, rpm.
            euler: (3,) yaw, pitch, roll, rad.
            v_air: (3,) air velocity, m/s, world frame.

        Returns:
            The loads (N, N·m, world), the levels (dB), the variance and ``in_domain``; zeros
            and ``in_domain`` False for a non-finite input, as the C gives them.

        Raises:
            ValueError: an input of another length.
        """
        for (key, n, at), a in zip(_STATE, (rpm, euler, v_air), strict=True):
            self._in[at : at + n] = _vector(a, n, key)
        out, k = self._out, self.n_levels
        out[:] = 0.0
        if self.online:
            ok = self._online_predict(self._state_p, *self._in_p, *self._out_p)
        else:
            ok = self._predict(*self._in_p, *self._out_p[: 4 if self.has_variance else 3])
        var = out[6 + max(k, 1) : 12 + max(k, 1) + k].copy() if self.has_variance else None
        return NativePrediction(out[:3].copy(), out[3:6].copy(), out[6 : 6 + k].copy(), var,
                                bool(ok))  # fmt: skip

    def update(
        self,
        t: float,
        rpm: ArrayLike,
        euler: ArrayLike,
        v_air: ArrayLike,
        force: ArrayLike,
        torque: ArrayLike,
        force_var: ArrayLike,
        torque_var: ArrayLike,
    ) -> bool:
        """One label into the online state (``<name>_online_update``; the arguments as
        :func:`gpg.flight.update`'s and :meth:`gpg.flight.Labels.columns`).

        Args:
            t: the label's time, s (the state relaxes from its own time to it).
            rpm: (4,) rotor speeds, rpm.
            euler: (3,) yaw, pitch, roll, rad.
            v_air: (3,) air velocity, m/s, world frame.
            force: (3,) the measured aerodynamic force, N, world frame.
            torque: (3,) the measured aerodynamic torque, N·m.
            force_var: (3,) the force's noise variance, N².
            torque_var: (3,) the torque's, (N·m)².

        Returns:
            True, or False where the C left the state untouched (a non-finite value or a
            negative variance in the label).

        Raises:
            ValueError: for a model without an online term, or an argument of another length.
        """
        self._need_online("update")
        args = (rpm, euler, v_air, force, torque, force_var, torque_var)
        for (key, n, at), a in zip(_UPDATE, args, strict=True):
            self._row[at : at + n] = _vector(a, n, key)
        return bool(self._update(self._state_p, float(t), *self._row_p))

    def _need_online(self, what: str) -> None:
        if not self.online:
            raise ValueError(
                f"{what}: the model has no online term (gpg.flight.adapt, track or adapt_bank "
                "give one)"
            )


def _vector(a, n: int, key: str) -> np.ndarray:
    v = np.asarray(a, dtype=float)
    if v.shape != (n,):
        raise ValueError(f"{key} must have shape ({n},), got {v.shape}")
    return v


def to_native(
    sur: Any,
    directory: str | Path | None = None,
    *,
    name: str = "gpg_model",
    dtype: str = "double",
    variance: bool = True,
    cc: str = "cc",
    flags: tuple[str, ...] = FLAGS,
) -> Native:
    """``sur`` exported to C (:func:`to_c`), compiled into a shared library by ``cc`` and
    loaded: its prediction, and an adapted, tracked or bank model's online update, called from
    Python at the C's cost.

    Args:
        sur: the fitted surrogate (any model :func:`to_c` exports).
        directory: where to write the source and the library (``<name>-<digest>.so``, one
            per content: a library already built from the same source is loaded again, not
            rebuilt); None: a temporary directory, removed with the returned object, or at
            once where the build fails.
        name: the C identifier of the export.
        dtype: ``"double"`` or ``"float"``, as :func:`to_c`.
        variance: whether to export the variance (a bank needs it).
        cc: the C compiler, a name on ``PATH`` or a path.
        flags: its flags, before ``-shared -fPIC``.

    Returns:
        The loaded :class:`Native`.

    Raises:
        ValueError: what :func:`to_c` refuses, or no compiler ``cc``.
        RuntimeError: the compiler failed (its message included).
    """
    exe = shutil.which(cc)
    if exe is None:
        raise ValueError(f"cc: no C compiler {cc!r} on PATH")
    owned = directory is None
    where = Path(tempfile.mkdtemp(prefix="gpg_native_") if owned else directory)
    try:
        out = _build(sur, where, exe, name, dtype, variance, cc, flags)
    except BaseException:
        # a temporary directory is the caller's only if the build hands back its library
        if owned:
            shutil.rmtree(where, ignore_errors=True)
        raise
    if owned:
        weakref.finalize(out, shutil.rmtree, where, ignore_errors=True)
    return out


def _build(sur, where: Path, exe: str, name, dtype, variance, cc, flags) -> Native:
    """:func:`to_native`'s source, library and load, in ``where``."""
    info = to_c(sur, where, name=name, dtype=dtype, variance=variance)
    # the state's size from the compiler, not from Python's idea of the struct's padding
    shim = where / f"{name}_native.c"
    shim.write_text(
        f'#include <stddef.h>\n#include "{name}.h"\n'
        f"size_t {name}_online_size(void) {{ return sizeof({name}_online); }}\n"
        if "_online_init" in info["h"].read_text()
        else "typedef int gpg_native_empty;\n"
    )
    # dlopen hands back a library already loaded from the same path, whatever the file holds
    # now: one file per content, so that another model written under this name loads its own
    # (and the same content is not built twice)
    digest = hashlib.sha256("\0".join((exe, *flags)).encode())
    for path in (info["c"], info["h"], shim):
        digest.update(path.read_bytes())
    so = where / f"{name}-{digest.hexdigest()[:16]}.so"
    if not so.exists():
        part = so.with_suffix(f".{os.getpid()}.part")
        built = subprocess.run(
            [exe, *flags, "-shared", "-fPIC", "-I", str(where), "-o", str(part), str(info["c"]),
             str(shim), "-lm"],
            capture_output=True, text=True,
        )  # fmt: skip
        if built.returncode != 0:
            part.unlink(missing_ok=True)
            raise RuntimeError(f"{cc} failed on {info['c']}: {built.stderr[-3000:]}")
        os.replace(part, so)  # whole or not at all
    n_levels = len(sur.output_names) - 6
    return Native(ctypes.CDLL(str(so)), name, where, n_levels, info["variance"])
