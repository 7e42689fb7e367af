"""What a long-running script built on gpg needs besides the models: the float64 policy for
a whole function, files written atomically (a crash leaves the old file or the new one), and
Ctrl-C taken at safe points. gpg's own loops use the same functions; the experiment runs in
the repository's ``experiments/`` use only these (docs/design.md, "Layout")."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import jax
import numpy as np

from gpg import _dtype, _interrupt, _io

__all__ = ["atomic_write", "check_interrupt", "deferred_interrupt", "float64", "write_json"]

P = ParamSpec("P")
R = TypeVar("R")


def float64(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` run with 64-bit JAX whatever the program's setting (docs/design.md, "Dtype
    policy"): its JAX float arguments widened, every matrix product at full precision.

    Args:
        fn: the function to wrap.

    Returns:
        The wrapped function, with ``fn``'s signature.
    """
    return _dtype.float64(fn)


def atomic_write(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same directory, renamed
    into place, with the permissions a plain ``open`` would give.

    Args:
        path: the file to write (its directory must exist).
        data: the bytes.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    return _io.atomic_write(path, data)


def _default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray | jax.Array):
        return np.asarray(o).tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically (:func:`atomic_write`).

    Args:
        path: the file to write.
        obj: plain containers; NumPy and JAX arrays and scalars become lists and numbers,
            paths strings.

    Raises:
        TypeError: if ``obj`` holds anything else.
    """
    text = json.dumps(obj, indent=2, sort_keys=False, default=_default) + "\n"
    _io.atomic_write(path, text.encode())


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """While the block runs (main thread only), a first Ctrl-C sets a flag that gpg's long
    loops check between steps (:func:`check_interrupt`), where they raise KeyboardInterrupt in
    ordinary Python code; a second Ctrl-C aborts at once. An interpreter torn down around
    XLA's live threads can crash; this is what avoids it.

    Yields:
        Nothing: the block runs with the handler installed, and the previous one is restored.
    """
    with _interrupt.deferred():
        yield


def check_interrupt() -> None:
    """A safe point: raise KeyboardInterrupt if a Ctrl-C arrived inside
    :func:`deferred_interrupt` (nothing otherwise)."""
    _interrupt.check()
