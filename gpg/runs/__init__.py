"""Deprecated: the experiment runs left the installed package.

``gpg.runs.<name>`` is now ``experiments.runs.<name>`` in a checkout of the repository (it is
not installed with gpg), and the comparison's records ``gpg.runs.results`` are
:mod:`gpg.results`. Importing ``gpg.runs.<name>`` warns and hands over the module at its new
place, for one release; outside a checkout it raises ImportError saying where the code went.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from types import ModuleType

__all__: list[str] = []

_MOVED = {"results": "gpg.results"}
# gpg.runs.common was split by concern: its names are found in these, in this order.
_SPLIT = {
    "common": (
        "experiments.runs.common",
        "experiments.runs.config",
        "experiments.runs.timing",
        "experiments.runs.output",
    )
}


def _new_name(fullname: str) -> str:
    sub = fullname.removeprefix(__name__ + ".")
    return _MOVED.get(sub, f"experiments.runs.{sub}")


class _Forward(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``gpg.runs.<name>`` and loads it as the module at its new place."""

    def __init__(self) -> None:
        self._specs: dict[str, object] = {}  # old name -> the module's own spec

    def find_spec(self, fullname, path, target=None):
        if fullname.startswith(__name__ + ".") and fullname.count(".") == 2:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec) -> ModuleType:
        new = _new_name(spec.name)
        warnings.warn(
            f"{spec.name} moved to {new} (experiment code is not part of the installed "
            "package); the old name goes away in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        try:
            parts = [importlib.import_module(m) for m in _SPLIT.get(spec.name.split(".")[-1], ())]
            module = _merged(spec.name, parts) if parts else importlib.import_module(new)
        except ModuleNotFoundError as exc:
            if not (exc.name or "").startswith("experiments"):
                raise
            raise ImportError(
                f"{spec.name} moved to {new}, in the gpg repository's experiments/ (not "
                "installed with gpg): run from a checkout of the repository"
            ) from exc
        # The import system records this spec on the module it gets back; the module keeps
        # its own, so that it stays what it is at its new place.
        self._specs[spec.name] = module.__spec__ or spec
        return module

    def exec_module(self, module: ModuleType) -> None:
        module.__spec__ = self._specs.pop(module.__spec__.name)


def _merged(name: str, parts: list[ModuleType]) -> ModuleType:
    """A module whose names are those of ``parts`` (the first that has one wins)."""
    module = ModuleType(
        name, f"Deprecated: {name}'s names, now in " + ", ".join(p.__name__ for p in parts)
    )

    def __getattr__(attr: str):
        for p in parts:
            if hasattr(p, attr):
                return getattr(p, attr)
        raise AttributeError(f"module {name!r} has no attribute {attr!r}")

    module.__getattr__ = __getattr__
    return module


if not any(isinstance(f, _Forward) for f in sys.meta_path):
    sys.meta_path.insert(0, _Forward())


def __getattr__(name: str) -> ModuleType:
    if name.startswith("__"):
        raise AttributeError(name)
    return importlib.import_module(f"{__name__}.{name}")
