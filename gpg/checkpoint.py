"""Save and load a :class:`~gpg.surrogate.Surrogate` (orbax for the arrays, JSON for the rest).

A checkpoint is a directory::

    <path>/metadata.json   format and version, model name and resolved config, output names,
                           normalisation, hyperparameters, partition, the module structure,
                           and shape, dtype and SHA-256 of every array
    <path>/arrays/         an orbax checkpoint of the arrays

Loading rebuilds the exact module tree from the recorded structure (only gpg classes are
accepted) and checks every array against its recorded shape, dtype and checksum, so a restored
surrogate predicts bit for bit what the saved one did, and a damaged checkpoint is reported as
such rather than loaded. Saving writes into a temporary sibling directory and renames it into
place at the end: a failed save leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import shutil
import uuid
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import gpg

FORMAT = "gpg-surrogate"
FORMAT_VERSION = 2  # 2: noise, output scales, hybrid and PIC models


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
        "gpg_version": gpg.__version__,
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
        with ocp.StandardCheckpointer() as ck:
            ck.save(tmp / "arrays", arrays)
            ck.wait_until_finished()
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
        meta = json.loads(meta_file.read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{meta_file} is damaged: {exc}") from exc
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{path} is not a gpg surrogate checkpoint (format {meta.get('format')!r})"
        )
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format version {meta.get('format_version')}; "
            f"this gpg ({gpg.__version__}) reads version {FORMAT_VERSION}"
        )
    return meta


def load(path: str | Path):
    """Read a :class:`~gpg.surrogate.Surrogate` written by :func:`save`."""
    import orbax.checkpoint as ocp  # here, not at module level: `import gpg` stays fast

    path = Path(path).absolute()
    meta = read_metadata(path)
    if not (path / "arrays").is_dir():
        raise CheckpointError(f"{path} is incomplete: the arrays directory is missing")
    try:
        with ocp.StandardCheckpointer() as ck:
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
