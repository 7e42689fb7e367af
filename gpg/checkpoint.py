"""Save and load a :class:`~gpg.surrogate.Surrogate` (orbax for the arrays, JSON for the rest).

A checkpoint is a directory::

    <path>/metadata.json   format and version, model name and resolved config, output names,
                           normalisation, hyperparameters, partition, the module structure,
                           shape, dtype and SHA-256 of every array, SHA-256 of every file of
                           arrays/, and a SHA-256 of the metadata itself
    <path>/arrays/         an orbax checkpoint of the arrays

Every byte that changes a prediction is covered by a checksum: the metadata (which holds the
static fields, e.g. ``hover_speed``) by its own, the orbax files by theirs, and the arrays once
restored by theirs. Loading checks them all before orbax reads anything, so any corruption is
one :class:`CheckpointError` naming the damaged file, and a restored surrogate predicts bit for
bit what the saved one did. Loading rebuilds the exact module tree from the recorded structure
(only gpg classes are accepted). Saving writes into a temporary sibling directory and renames
it into place at the end: a failed save leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib
import json
import logging
import shutil
import uuid
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gpg._version import __version__

FORMAT = "gpg-surrogate"
FORMAT_VERSION = 4  # 2: noise, output scales, hybrid and PIC models; 3: M_noise;
# 4: M_noise with unsteady loading (a version-3 M_noise would now predict other levels)


class CheckpointError(ValueError):
    """A checkpoint is missing, damaged, or of another format version."""


def _describe(obj: Any, arrays: dict[str, np.ndarray], path: str) -> Any:
    if isinstance(obj, eqx.Module):
        cls = type(obj)
        if not cls.__module__.startswith("gpg."):
            raise TypeError(f"cannot checkpoint {cls.__module__}.{cls.__qualname__} at {path}")
        return {
            "__module__": cls.__module__,
            "__class__": cls.__qualname__,
            "fields": {
                f.name: _describe(getattr(obj, f.name), arrays, f"{path}.{f.name}")
                for f in dataclasses.fields(obj)
            },
        }
    if isinstance(obj, jax.Array | np.ndarray):
        key = f"a{len(arrays):04d}"
        arrays[key] = np.asarray(obj)
        return {"__array__": key, "path": path}
    if isinstance(obj, tuple):
        return {"__tuple__": [_describe(v, arrays, f"{path}[{i}]") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_describe(v, arrays, f"{path}[{i}]") for i, v in enumerate(obj)]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    raise TypeError(f"cannot checkpoint a {type(obj).__name__} at {path}")


def _rebuild(desc: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(desc, dict) and "__array__" in desc:
        return jnp.asarray(arrays[desc["__array__"]])
    if isinstance(desc, dict) and "__tuple__" in desc:
        return tuple(_rebuild(v, arrays) for v in desc["__tuple__"])
    if isinstance(desc, dict) and "__class__" in desc:
        module = desc["__module__"]
        if not module.startswith("gpg."):
            raise CheckpointError(f"checkpoint names a class outside gpg: {module}")
        cls = importlib.import_module(module)
        for part in desc["__class__"].split("."):
            cls = getattr(cls, part)
        names = {f.name for f in dataclasses.fields(cls)}
        if names != set(desc["fields"]):
            raise CheckpointError(
                f"{desc['__class__']} fields differ from this gpg version: "
                f"{sorted(names ^ set(desc['fields']))}"
            )
        obj = object.__new__(cls)
        for name, value in desc["fields"].items():
            object.__setattr__(obj, name, _rebuild(value, arrays))
        return obj
    if isinstance(desc, list):
        return [_rebuild(v, arrays) for v in desc]
    return desc


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def _file_digests(root: Path) -> dict[str, str]:
    """SHA-256 of every file under ``root``, by path relative to it."""
    out = {}
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        h = hashlib.sha256()
        with open(f, "rb") as fh:
            for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                h.update(block)
        out[f.relative_to(root).as_posix()] = h.hexdigest()
    return out


def _meta_digest(meta: dict[str, Any]) -> str:
    body = {k: v for k, v in meta.items() if k != "metadata_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


@contextlib.contextmanager
def _quiet_orbax():
    """Orbax and its asyncio machinery log a traceback per failed task; gpg reports one
    CheckpointError instead, so their loggers are muted while orbax runs."""
    names = ("absl", "asyncio", "orbax", "jax._src.distributed")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, lv in zip(loggers, levels, strict=True):
            lg.setLevel(lv)


def _summary(sur) -> dict[str, Any]:
    """Human-readable parts of the metadata (normalisation, hyperparameters, partition)."""
    model = sur.model
    out: dict[str, Any] = {
        "normalisation": {
            "x_lo": np.asarray(sur.normalizer.x_lo).tolist(),
            "x_hi": np.asarray(sur.normalizer.x_hi).tolist(),
            "y_mean": np.asarray(sur.normalizer.y_mean).tolist(),
            "y_std": np.asarray(sur.normalizer.y_std).tolist(),
        },
    }
    hyper = getattr(model, "hyper", None)
    if hyper is not None:
        out["hyperparameters"] = {k: np.asarray(v).tolist() for k, v in vars(hyper).items()}
    else:
        out["hyperparameters"] = {
            "variance": np.asarray(model.variance).tolist(),
            "lengthscale": np.asarray(model.lengthscale).tolist(),
        }
    part = getattr(model, "partition", None)
    if part is not None:
        out["partition"] = {
            "scheme": part.scheme,
            "n_bins": part.n_bins,
            "near_points": np.asarray(model.n_near).tolist(),
        }
    if sur.simple is not None:
        out["simple_model"] = {"P_F": float(sur.simple.P_F), "T_z": float(sur.simple.T_z)}
    return out


def save(path: str | Path, surrogate, *, overwrite: bool = False) -> Path:
    """Write ``surrogate`` to the directory ``path`` (atomically); returns the path."""
    import orbax.checkpoint as ocp  # here, not at module level: `import gpg` stays fast

    from gpg.surrogate import Surrogate

    if not isinstance(surrogate, Surrogate):
        raise ValueError(f"save expects a gpg.Surrogate, got {type(surrogate).__name__}")
    path = Path(path).absolute()
    if path.exists() and not overwrite:
        raise CheckpointError(f"{path} exists; pass overwrite=True to replace it")
    arrays: dict[str, np.ndarray] = {}
    skeleton = _describe(surrogate, arrays, "surrogate")
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "gpg_version": __version__,
        "model_name": surrogate.model_name,
        "config": surrogate.config,
        "output_names": list(surrogate.output_names),
        **_summary(surrogate),
        "skeleton": skeleton,
        "arrays": {
            k: {"shape": list(a.shape), "dtype": str(a.dtype), "sha256": _digest(a)}
            for k, a in arrays.items()
        },
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        with _quiet_orbax(), ocp.StandardCheckpointer() as ck:
            ck.save(tmp / "arrays", arrays)
            ck.wait_until_finished()
        meta["files"] = _file_digests(tmp / "arrays")
        meta["metadata_sha256"] = _meta_digest(meta)
        (tmp / "metadata.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
        if path.exists():
            old = path.with_name(f".{path.name}.old-{uuid.uuid4().hex[:8]}")
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The checkpoint's metadata, after checking format and version."""
    path = Path(path).absolute()
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint at {path}")
    meta_file = path / "metadata.json"
    if not meta_file.is_file():
        raise CheckpointError(f"{path} is not a gpg checkpoint: metadata.json is missing")
    try:
        meta = json.loads(meta_file.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{meta_file} is damaged: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("metadata_sha256") != _meta_digest(meta):
        raise CheckpointError(f"{meta_file} is damaged: it fails its checksum")
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{path} is not a gpg surrogate checkpoint (format {meta.get('format')!r})"
        )
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format version {meta.get('format_version')}; "
            f"this gpg ({__version__}) reads version {FORMAT_VERSION}"
        )
    return meta


def load(path: str | Path):
    """Read a :class:`~gpg.surrogate.Surrogate` written by :func:`save`."""
    import orbax.checkpoint as ocp  # here, not at module level: `import gpg` stays fast

    path = Path(path).absolute()
    meta = read_metadata(path)
    if not (path / "arrays").is_dir():
        raise CheckpointError(f"{path} is incomplete: the arrays directory is missing")
    want_files, have_files = meta.get("files", {}), _file_digests(path / "arrays")
    for name in sorted(set(want_files) | set(have_files)):
        if name not in have_files:
            raise CheckpointError(f"{path / 'arrays' / name} is missing: incomplete checkpoint")
        if name not in want_files:
            raise CheckpointError(f"{path / 'arrays' / name} is not part of the checkpoint")
        if want_files[name] != have_files[name]:
            raise CheckpointError(f"{path / 'arrays' / name} is damaged: it fails its checksum")
    try:
        with _quiet_orbax(), ocp.StandardCheckpointer() as ck:
            restored = ck.restore(path / "arrays")
    except Exception as exc:  # orbax/tensorstore raise many types for damaged files
        raise CheckpointError(f"checkpoint data at {path} is damaged or incomplete: {exc}") from exc
    arrays = {k: np.asarray(v) for k, v in restored.items()}
    want = meta["arrays"]
    if set(arrays) != set(want):
        raise CheckpointError(f"{path} holds arrays {sorted(arrays)} but records {sorted(want)}")
    for k, spec in want.items():
        a = arrays[k]
        if (
            list(a.shape) != spec["shape"]
            or str(a.dtype) != spec["dtype"]
            or _digest(a) != spec["sha256"]
        ):
            raise CheckpointError(
                f"array {k} of {path} fails its shape/dtype/checksum check: damaged"
            )
    return _rebuild(meta["skeleton"], arrays)
