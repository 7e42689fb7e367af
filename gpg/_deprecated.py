"""Old names kept for one release: each use warns with the new name (``DeprecationWarning``)."""

from __future__ import annotations

import warnings


def deprecated(old: str, new: str, *, stacklevel: int = 3) -> None:
    """Warn that ``old`` is now ``new``; ``stacklevel`` 3 points at the caller's caller (the
    user's line that used the old name through a property or keyword)."""
    warnings.warn(f"{old} is deprecated; use {new}", DeprecationWarning, stacklevel=stacklevel)
