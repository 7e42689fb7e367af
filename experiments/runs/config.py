"""The entry points' configs read without Hydra (for notebooks, tests and scripts), and their
top-level options checked before any work."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gpg import conf as package_conf

# The entry points' own configs (compare.yaml, ...), beside this package in the repository
# (experiments/ and conf/ are both the repository's, neither is installed). The library's
# configs (data scales, models, vehicles) ship inside gpg (gpg.conf).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def conf(name: str, group: str | None = None) -> dict[str, Any]:
    """A config file as plain values, without Hydra (for notebooks and scripts):
    ``conf("smoke", "data")`` reads the data scale ``smoke`` shipped with gpg
    (:func:`gpg.conf.load`; likewise the groups ``model`` and ``vehicle``); other groups and
    the entry points' configs are read from the repository's ``conf/``, their defaults lists
    composed as Hydra does (:func:`gpg.conf.compose`)."""
    import yaml

    if group in package_conf.GROUPS:
        return package_conf.load(name, group)
    path = CONF_DIR / (group or "") / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml") if not p.stem.startswith("_"))
        raise ValueError(f"no config {path}; known: {known}")
    own = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    return package_conf.compose(own, str(path), group, conf)


def check_options(cfg: Mapping[str, Any], spec: Mapping[str, str]) -> None:
    """An entry point's top-level options checked before any work, each named when wrong.

    ``spec`` maps a key to its kind: ``count`` (integer >= 1), ``index`` (integer >= 0),
    ``bool``, ``mapping?`` (a mapping or null), ``devices`` (null or a device count >= 1),
    ``path`` (a non-empty string), ``path?`` (the same, or null).
    """
    for key, kind in spec.items():
        if key not in cfg:
            continue
        v = cfg[key]
        integer = isinstance(v, int) and not isinstance(v, bool)
        ok = {
            "count": integer and v >= 1,
            "index": integer and v >= 0,
            "bool": isinstance(v, bool),
            "mapping?": v is None or isinstance(v, Mapping),
            "devices": v is None or (integer and v >= 1),
            "path": isinstance(v, str) and v != "",
            "path?": v is None or (isinstance(v, str) and v != ""),
        }[kind]
        if not ok:
            want = {
                "count": "an integer >= 1",
                "index": "an integer >= 0",
                "bool": "true or false",
                "mapping?": "a mapping or null",
                "devices": "null or a number of devices >= 1",
                "path": "a path",
                "path?": "a path or null",
            }[kind]
            raise ValueError(f"{key} must be {want}, got {v!r}")
