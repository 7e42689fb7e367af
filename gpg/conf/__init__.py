"""The library's own configuration files, shipped as package data so that an installed gpg
finds them: ``vehicle/`` (vehicle files, :func:`gpg.quadrotor.load_vehicle`), ``data/`` (the
dataset scales) and ``model/`` (each model's options over ``_base``). The Hydra entry points'
own configs live in the repository's ``conf/`` and reach these through Hydra's search path
(``pkg://gpg.conf``)."""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

GROUPS = ("data", "model", "vehicle")


def group(name: str) -> Traversable:
    """The folder of config group ``name`` inside the installed package."""
    if name not in GROUPS:
        raise ValueError(f"unknown config group {name!r}; the package ships {list(GROUPS)}")
    return files(__name__).joinpath(name)


def names(name: str) -> list[str]:
    """The config names of group ``name`` (file stems, private ``_`` files left out)."""
    return sorted(
        p.name[:-5]
        for p in group(name).iterdir()
        if p.name.endswith(".yaml") and not p.name.startswith("_")
    )


def read_text(name: str, entry: str) -> str | None:
    """The text of ``<group>/<entry>.yaml``, or None when the package has no such file."""
    f = group(name).joinpath(f"{entry}.yaml")
    return f.read_text(encoding="utf-8") if f.is_file() else None
