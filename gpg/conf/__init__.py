"""The library's own configuration files, shipped as package data so that an installed gpg
finds them: ``vehicle/`` (vehicle files, :func:`gpg.quadrotor.load_vehicle`), ``data/`` (the
dataset scales) and ``model/`` (each model's options over ``_base``). The Hydra entry points'
own configs live in the repository's ``conf/`` and reach these through Hydra's search path
(``pkg://gpg.conf``)."""

from __future__ import annotations

import re
from collections.abc import Callable
from importlib.resources import files
from importlib.resources.abc import Traversable
from typing import Any

__all__ = ["GROUPS", "compose", "deep_merge", "group", "load", "names", "read_text"]

GROUPS = ("data", "model", "vehicle")


def group(name: str) -> Traversable:
    """The folder of config group ``name`` inside the installed package.

    Args:
        name: one of :data:`GROUPS`.

    Returns:
        The group's folder (an importlib.resources Traversable).

    Raises:
        ValueError: if ``name`` is not a group the package ships.
    """
    if name not in GROUPS:
        raise ValueError(f"unknown config group {name!r}; the package ships {list(GROUPS)}")
    return files(__name__).joinpath(name)


def names(name: str) -> list[str]:
    """The config names of a group (file stems, private ``_`` files left out).

    Args:
        name: one of :data:`GROUPS`.

    Returns:
        The sorted names, e.g. ``["default", "large", "paper", "smoke"]`` for ``"data"``.
    """
    return sorted(
        p.name[:-5]
        for p in group(name).iterdir()
        if p.name.endswith(".yaml") and not p.name.startswith("_")
    )


def read_text(name: str, entry: str) -> str | None:
    """The text of ``<group>/<entry>.yaml`` inside the package.

    Args:
        name: one of :data:`GROUPS`.
        entry: the config's name within the group.

    Returns:
        The file's text, or None when the package has no such file.
    """
    f = group(name).joinpath(f"{entry}.yaml")
    return f.read_text(encoding="utf-8") if f.is_file() else None


def deep_merge(base: dict[str, Any], over: dict[str, Any] | None) -> dict[str, Any]:
    """``base`` with the (nested) keys of ``over`` replaced, as Hydra merges a defaults list.

    Args:
        base: the mapping merged into.
        over: the keys that win (None: nothing).

    Returns:
        A new mapping; neither argument is changed.
    """
    out = dict(base)
    for k, v in (over or {}).items():
        out[k] = deep_merge(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def compose(
    own: dict[str, Any],
    where: str,
    group: str | None,
    load: Callable[[str, str | None], dict[str, Any]],
) -> dict[str, Any]:
    """A config with its defaults list composed as Hydra does, without Hydra: an entry
    ``name`` is the config of the same group, merged in; ``group: name`` goes under the key
    ``group``; ``_self_`` places the file's own keys (last when absent). Hydra's own settings
    (``hydra:``) are left out.

    Args:
        own: the file's parsed YAML (changed: ``hydra`` and ``defaults`` are popped).
        where: the file, for messages.
        group: the file's group (None: the top level).
        load: ``load(name, group)`` reads another config of the same kind.

    Returns:
        The composed config as plain values.

    Raises:
        ValueError: if the defaults list has an entry that needs Hydra itself.
    """
    own.pop("hydra", None)
    defaults = own.pop("defaults", None)
    if defaults is None:
        return own
    out: dict[str, Any] = {}
    for entry in defaults if "_self_" in defaults else [*defaults, "_self_"]:
        if entry == "_self_":
            out = deep_merge(out, own)
        elif isinstance(entry, str):
            out = deep_merge(out, load(entry, group))
        elif isinstance(entry, dict) and len(entry) == 1 and re.fullmatch(r"\w+", *entry):
            ((sub, sub_name),) = entry.items()
            out = deep_merge(out, {sub: load(sub_name, sub)})
        else:
            raise ValueError(
                f"{where}: the defaults entry {entry!r} needs Hydra (only 'name' and"
                " 'group: name' entries are read without it)"
            )
    return out


def load(name: str, group: str) -> dict[str, Any]:
    """A config the package ships, as plain values, its defaults composed
    (``load("gpgs_hybrid", "model")`` is the model's options over ``_base``).

    Args:
        name: the config's name within its group.
        group: one of :data:`GROUPS`.

    Returns:
        The config as plain Python containers.

    Raises:
        ValueError: if the group or the config does not exist, or its defaults need Hydra.
    """
    import yaml

    text = read_text(group, name)
    where = f"gpg/conf/{group}/{name}.yaml"
    if text is None:
        raise ValueError(f"no config {where}; known: {names(group)}")
    return compose(yaml.safe_load(text) or {}, where, group, load)
