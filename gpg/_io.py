"""Atomic file writes: a temporary file in the target's directory, renamed into place.

A reader (or a crash) sees the old file or the new one, never half of one. ``mkstemp`` creates
its file readable by the owner only; the result gets the permissions a plain ``open`` would
give (``0o666`` less the umask), so results and datasets are as readable as any other file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def umask() -> int:
    """The process umask (reading it means setting it: set it straight back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def require_writable(directory: str | Path, what: str) -> Path:
    """``directory`` (created if missing) when this process can write into it, else a
    ``ValueError`` naming ``what`` and the reason: checked before long work whose result would
    otherwise be lost at the end."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=directory, prefix=".write-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ValueError(f"{what} {directory} is not writable: {exc.strerror or exc}") from exc
    return directory
