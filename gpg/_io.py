"""Atomic file writes: a temporary file in the target's directory, renamed into place.

A reader (or a crash) sees the old file or the new one, never half of one. ``mkstemp`` creates
its file readable by the owner only; the result gets the permissions a plain ``open`` would
give (``0o666`` less the umask), so results and datasets are as readable as any other file, or,
replacing a file, that file's own permissions (a private file stays private). A symbolic link
is followed: its target is replaced and the link kept, as writing through ``open`` would.
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
    """Write ``data`` to ``path`` atomically; returns the path.

    Raises:
        ValueError: an empty path, or a file name longer than the file system allows.
    """
    if not str(path).strip():
        raise ValueError(f"path must be a file path, got {str(path)!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    limit = _name_max(path.parent)
    if len(os.fsencode(path.name)) > limit:
        raise ValueError(
            f"{path}: the file name is {len(os.fsencode(path.name))} bytes long, more than "
            f"the {limit} its file system allows"
        )
    target = path
    if path.is_symlink():  # its target is replaced, in a folder that may not exist yet
        target = Path(os.path.realpath(path))
        target.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = os.stat(target).st_mode & 0o7777
    except FileNotFoundError:
        mode = 0o666 & ~umask()
    # The temporary name stays short: a name near the limit leaves no room for a prefix.
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name[:32]}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _name_max(directory: Path) -> int:
    """The longest file name (bytes) ``directory``'s file system takes (255 if not said)."""
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


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
