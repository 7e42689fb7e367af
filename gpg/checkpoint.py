"""Save and load a :class:`~gpg.surrogate.Surrogate` (orbax for the arrays, JSON for the rest).

A checkpoint is a directory holding complete versions of the surrogate and a pointer to the
current one::

    <path>/CURRENT                 the name of the current version directory
    <path>/v-<id>/metadata.json    format and version, model name and resolved config, output
                                   names, normalisation, hyperparameters, partition, the module
                                   structure, shape, dtype and SHA-256 of every array, SHA-256 of
                                   every file of arrays/, and a SHA-256 of the metadata itself
    <path>/v-<id>/arrays/          an orbax checkpoint of the arrays

Saving is atomic and exclusive. A new checkpoint is written completely into a temporary
sibling and renamed into place: the rename fails if the path exists, so of two processes
saving to one path with ``overwrite=False`` exactly one succeeds and the other gets a
:class:`CheckpointError` (nothing of the first is touched). ``overwrite=True`` writes a new
version beside the current one, switches ``CURRENT`` by an atomic replace, and only then
removes the old version; writers of one path take turns (a lock file, ``fcntl.flock``). A
reader resolves ``CURRENT`` and loads that version; if a writer removes it meanwhile, the
reader sees ``CURRENT`` changed and loads the new one: a reader never sees a half-replaced
checkpoint. Format version 4 (the arrays and metadata directly in ``<path>``) still loads, and
``overwrite=True`` replaces it by the new layout.

Every byte that changes a prediction is covered by a checksum: the metadata (which holds the
static fields, e.g. ``hover_speed``) by its own, the orbax files by theirs, and the arrays once
restored by theirs. Loading checks them all before orbax reads anything, so any corruption is
one :class:`CheckpointError` naming the damaged file, and a restored surrogate predicts bit for
bit what the saved one did. Loading rebuilds the exact module tree from the recorded structure
(only gpg classes are accepted). A failed save leaves nothing behind.

Dtypes: arrays load as they were saved (a float64 surrogate stays float64 in a float32 program,
as the fitted one is: JAX converts its arrays at each call), so a loaded surrogate predicts
exactly what the saved one did; ``load(path, dtype=jnp.float32)`` is the explicit conversion
(:meth:`gpg.Surrogate.astype`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import importlib
import json
import logging
import shutil
import threading
import uuid
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import equinox as eqx
import jax
import numpy as np
from jax.typing import DTypeLike

from gpg import _host, models
from gpg._io import atomic_write, require_writable
from gpg._version import __version__

if TYPE_CHECKING:
    from gpg.surrogate import Surrogate

__all__ = ["FORMAT_VERSION", "CheckpointError", "load", "read_metadata", "save", "version_dir"]

FORMAT = "gpg-surrogate"
FORMAT_VERSION = 12  # 2: noise, output scales, hybrid and PIC models; 3: M_noise;
# 4: M_noise with unsteady loading (a version-3 M_noise would now predict other levels);
# 5: versions under CURRENT (atomic overwrite); version 4's flat layout still loads;
# 6: fields renamed (ν² is ``noise``, M_noise ``noise_model``); 4 and 5 load through RENAMED;
# 7: ExactGP.order/observed and HybridGP.record (conditioning); older files load them as None
# 8: a conditioned ExactGP keeps its new rows factored (gpg.linalg.tri.BorderedTriangular)
# 9: an ExactGP factorises only the rows it observed (``order`` names them); the decoupled
#    factors of 7 and 8 still load and condition
# 10: Surrogate.frame (the body-frame formulation); older files load as the airflow frame
# 11: ``bases`` of ExactGP, BinnedGP and the hybrid's Record (directional gradient rows of
#     converted data); older files load them as None
# 12: Surrogate.half_turn (airflow from behind read at the half-turn image); older files load
#     it as False, and an older gpg refuses a file that has it rather than drop it
READABLE_VERSIONS = (4, 5, 6, 7, 8, 9, 10, 11, 12)
# Fields renamed since an older format: (module, class) -> {old field: new field}. Reading one
# warns (DeprecationWarning): save the surrogate again to write the current format.
RENAMED = {
    ("gpg.gp.hyper", "Hyper"): {"jitter": "noise"},
    ("gpg.gp.binned", "BinnedGP"): {"jitter": "noise"},
    ("gpg.surrogate", "Surrogate"): {"noise": "noise_model"},
}
CURRENT = "CURRENT"
LOAD_ATTEMPTS = 20  # reloads when a concurrent overwrite replaced the version being read
# Orbax's writers and readers in one process interfere when run from several threads at once
# (measured: a save failed with NOT_FOUND inside the other's temporary directory); threads of one
# process take turns for the orbax step. Processes need no such lock: they write apart.
_ORBAX = threading.Lock()


class CheckpointError(ValueError):
    """A checkpoint is missing, damaged, or of another format version."""


def _trusted(module: str, qualname: str) -> bool:
    """Whether a checkpoint may name this class: gpg's own, or the predictor of a kind
    registered with :func:`gpg.models.register` (loading imports the module it names)."""
    if module.startswith("gpg."):
        return True
    return any(
        (p.__module__, p.__qualname__) == (module, qualname)
        for p in (spec.kind.predictor for spec in models.SPECS.values())
        if p is not None
    )


def _describe(obj: Any, arrays: dict[str, np.ndarray], path: str) -> Any:
    if isinstance(obj, eqx.Module):
        cls = type(obj)
        if not _trusted(cls.__module__, cls.__qualname__):
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
        a = arrays[desc["__array__"]]
        # As saved: a float64 array stays float64 even where x64 is off (see module docstring).
        return _host.as_stored(a)
    if isinstance(desc, dict) and "__tuple__" in desc:
        return tuple(_rebuild(v, arrays) for v in desc["__tuple__"])
    if isinstance(desc, dict) and "__class__" in desc:
        module = desc["__module__"]
        if not _trusted(module, desc["__class__"]):
            raise CheckpointError(
                f"checkpoint names a class outside gpg and its registered kinds: "
                f"{module}.{desc['__class__']}"
            )
        cls = importlib.import_module(module)
        for part in desc["__class__"].split("."):
            cls = getattr(cls, part)
        fields = _renamed_fields(module, desc["__class__"], desc["fields"])
        known = {f.name: f for f in dataclasses.fields(cls)}
        # A field added since the file was written takes its default (format 7 added the
        # exact model's row order and the hybrid's training record, both None before; format
        # 10 the surrogate's frame, "airflow" before; format 11 the models' bases, None;
        # format 12 the surrogate's half turn, False).
        added = {
            n for n, f in known.items() if n not in fields and f.default is not dataclasses.MISSING
        }
        if set(known) - added != set(fields):
            raise CheckpointError(
                f"{desc['__class__']} fields differ from this gpg version: "
                f"{sorted((set(known) - added) ^ set(fields))}"
            )
        obj = object.__new__(cls)
        for name in added:
            object.__setattr__(obj, name, known[name].default)
        for name, value in fields.items():
            object.__setattr__(obj, name, _rebuild(value, arrays))
        return obj
    if isinstance(desc, list):
        return [_rebuild(v, arrays) for v in desc]
    return desc


def _renamed_fields(module: str, cls: str, fields: dict[str, Any]) -> dict[str, Any]:
    """``fields`` under this version's names (:data:`RENAMED`), with a warning per old name."""
    renames = RENAMED.get((module, cls), {})
    old = [k for k in fields if k in renames]
    for k in old:
        warnings.warn(
            f"checkpoint field {cls}.{k} was written by an earlier gpg and is read as "
            f"{renames[k]}; save the surrogate again to write format {FORMAT_VERSION}",
            DeprecationWarning,
            stacklevel=2,
        )
    return {renames.get(k, k): v for k, v in fields.items()}


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
    """Human-readable parts of the metadata: normalisation, and what the model says of itself
    (:meth:`gpg.gp.predictor.Predictor.describe`: hyperparameters, partition)."""
    out: dict[str, Any] = {
        "normalisation": {
            "x_lo": np.asarray(sur.normalizer.x_lo).tolist(),
            "x_hi": np.asarray(sur.normalizer.x_hi).tolist(),
            "y_mean": np.asarray(sur.normalizer.y_mean).tolist(),
            "y_std": np.asarray(sur.normalizer.y_std).tolist(),
        },
        **sur.model.describe(),
    }
    if sur.simple is not None:
        out["simple_model"] = {"P_F": float(sur.simple.P_F), "T_z": float(sur.simple.T_z)}
    return out


def save(path: str | Path, surrogate: Surrogate, *, overwrite: bool = False) -> Path:
    """Write ``surrogate`` to the directory ``path``, atomically (see the module docstring).

    A failed save leaves nothing behind, and a reader never sees a half-written checkpoint.

    Args:
        path: the checkpoint directory; its parent is created if needed.
        surrogate: the surrogate to save.
        overwrite: replace a checkpoint at ``path`` (a new version, then ``CURRENT`` switched);
            False fails if ``path`` exists, also when another process creates it while this
            one writes.

    Returns:
        The absolute path of the checkpoint.

    Raises:
        ValueError: if ``surrogate`` is not a :class:`gpg.Surrogate`.
        CheckpointError: if ``path`` exists and is not a directory, exists without
            ``overwrite``, or its directory is not writable.
    """
    from gpg.surrogate import Surrogate

    if not isinstance(surrogate, Surrogate):
        raise ValueError(f"save expects a gpg.Surrogate, got {type(surrogate).__name__}")
    path = Path(path).absolute()
    if path.exists() and not path.is_dir():
        raise CheckpointError(f"{path} exists and is not a checkpoint directory")
    if path.exists() and not overwrite:
        raise CheckpointError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        require_writable(path.parent, "the checkpoint's directory")
    except ValueError as exc:
        raise CheckpointError(str(exc)) from exc
    version = f"v-{uuid.uuid4().hex[:12]}"
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        _write_version(tmp / version, surrogate)
        atomic_write(tmp / CURRENT, (version + "\n").encode())
        try:
            tmp.rename(path)  # atomic; fails when path exists and is not empty
            return path
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
                raise
            if not overwrite:
                raise CheckpointError(
                    f"{path} exists (another process saved it meanwhile); pass overwrite=True "
                    "to replace it"
                ) from None
        with _writer_lock(path):
            (tmp / version).rename(path / version)
            _switch(path, version)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    return path


def _write_version(where: Path, surrogate) -> None:
    """One complete version (metadata.json and arrays/) into the new directory ``where``."""
    import orbax.checkpoint as ocp  # here, not at module level: `import gpg` stays fast

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
    where.mkdir()
    with _ORBAX, _quiet_orbax(), ocp.StandardCheckpointer() as ck:
        ck.save(where / "arrays", arrays)
        ck.wait_until_finished()
    meta["files"] = _file_digests(where / "arrays")
    meta["metadata_sha256"] = _meta_digest(meta)
    atomic_write(
        where / "metadata.json", (json.dumps(meta, indent=1, sort_keys=True) + "\n").encode()
    )


@contextlib.contextmanager
def _writer_lock(path: Path):
    """Writers of one checkpoint take turns (advisory ``flock`` on ``<path>/.lock``; readers
    never wait). Without ``fcntl`` (Windows) concurrent overwrites are not serialised."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX
        yield
        return
    with open(path / ".lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _switch(path: Path, version: str) -> None:
    """Make ``version`` current, then remove every other version and a version-4 layout (under
    the writer lock: no other writer is between its own steps)."""
    atomic_write(path / CURRENT, (version + "\n").encode())
    for p in path.iterdir():
        old_version = p.is_dir() and p.name.startswith("v-") and p.name != version
        if old_version or p.name in ("metadata.json", "arrays"):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


def _current(path: Path) -> str | None:
    """The name in ``<path>/CURRENT``, or None (a version-4 checkpoint, or none at all)."""
    try:
        name = (path / CURRENT).read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        versions = sorted(p.name for p in path.glob("v-*") if p.is_dir())
        if versions:  # a writer never leaves a version without CURRENT (atomic replace)
            raise CheckpointError(
                f"{path / CURRENT} is missing, but the checkpoint holds version(s) {versions}: "
                "the file naming the current version was deleted; save the surrogate again "
                "(or write the version's name into CURRENT if you know which one is whole)"
            ) from None
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path / CURRENT} is damaged: {exc}") from exc
    if not name.startswith("v-") or "/" in name or name != Path(name).name:
        raise CheckpointError(f"{path / CURRENT} is damaged: it names {name!r}")
    return name


def version_dir(path: str | Path) -> Path:
    """The directory of the checkpoint's current version.

    Args:
        path: the checkpoint directory.

    Returns:
        ``<path>/v-<id>`` as ``CURRENT`` names it; ``path`` itself for format version 4.

    Raises:
        CheckpointError: if ``CURRENT`` is missing beside versions, damaged, or names a
            version the checkpoint does not hold.
    """
    path = Path(path).absolute()
    return _version_path(path, _current(path))


def _version_path(path: Path, name: str | None) -> Path:
    if name is None:
        return path
    if not (path / name).is_dir():
        versions = sorted(p.name for p in path.glob("v-*") if p.is_dir())
        raise CheckpointError(
            f"{path / CURRENT} names version {name!r}, which the checkpoint does not hold (it "
            f"holds {versions}): CURRENT is damaged (truncated?) or that version was deleted"
        )
    return path / name


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The metadata of the checkpoint's current version, without loading its arrays.

    Args:
        path: the checkpoint directory.

    Returns:
        The contents of ``metadata.json``: format and version, model name and config, output
            names, normalisation, hyperparameters, partition, and the arrays' shapes and checksums.

    Raises:
        CheckpointError: if there is no checkpoint at ``path``, the metadata are missing or
            fail their checksum, or the format or its version is not one this gpg reads.
    """
    path = Path(path).absolute()
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint at {path}")
    return _read_metadata(version_dir(path))


def _read_metadata(where: Path) -> dict[str, Any]:
    meta_file = where / "metadata.json"
    if not meta_file.is_file():
        raise CheckpointError(f"{where} is not a gpg checkpoint: metadata.json is missing")
    try:
        meta = json.loads(meta_file.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{meta_file} is damaged: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("metadata_sha256") != _meta_digest(meta):
        raise CheckpointError(f"{meta_file} is damaged: it fails its checksum")
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{where} is not a gpg surrogate checkpoint (format {meta.get('format')!r})"
        )
    if meta.get("format_version") not in READABLE_VERSIONS:
        raise CheckpointError(
            f"{where} has checkpoint format version {meta.get('format_version')}; "
            f"this gpg ({__version__}) reads versions {list(READABLE_VERSIONS)}"
        )
    return meta


def load(path: str | Path, *, dtype: DTypeLike | None = None) -> Surrogate:
    """Read a :class:`~gpg.surrogate.Surrogate` written by :func:`save`.

    Every checksum is checked before orbax reads anything. Safe against a concurrent
    ``save(..., overwrite=True)`` of the same path: the reader then loads the new version.

    Args:
        path: the checkpoint directory.
        dtype: convert every float array to it (e.g. ``jnp.float32``,
            :meth:`Surrogate.astype`); None loads them bit for bit as saved.

    Returns:
        The surrogate, which predicts exactly what the saved one did (without ``dtype``).

    Raises:
        CheckpointError: if there is no checkpoint at ``path``, or it is damaged,
            incomplete or of a format version this gpg does not read, naming the file.
    """
    path = Path(path).absolute()
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint at {path}")
    for attempt in range(LOAD_ATTEMPTS):
        name = _current(path)
        try:
            sur = _load_version(_version_path(path, name))
            break
        except (CheckpointError, OSError) as exc:
            # Replaced by a writer while we read it: read the new version instead.
            if _current(path) != name and attempt + 1 < LOAD_ATTEMPTS:
                continue
            if isinstance(exc, CheckpointError):
                raise
            raise CheckpointError(f"checkpoint at {path} is damaged or incomplete: {exc}") from exc
    return sur if dtype is None else sur.astype(dtype)


def _load_version(where: Path):
    import orbax.checkpoint as ocp  # here, not at module level: `import gpg` stays fast

    meta = _read_metadata(where)
    if not (where / "arrays").is_dir():
        raise CheckpointError(f"{where} is incomplete: the arrays directory is missing")
    want_files, have_files = meta.get("files", {}), _file_digests(where / "arrays")
    for name in sorted(set(want_files) | set(have_files)):
        if name not in have_files:
            raise CheckpointError(f"{where / 'arrays' / name} is missing: incomplete checkpoint")
        if name not in want_files:
            raise CheckpointError(f"{where / 'arrays' / name} is not part of the checkpoint")
        if want_files[name] != have_files[name]:
            raise CheckpointError(f"{where / 'arrays' / name} is damaged: it fails its checksum")
    try:
        # x64 on while restoring: a float64 array must not come back as float32.
        with _ORBAX, _quiet_orbax(), jax.enable_x64(True), ocp.StandardCheckpointer() as ck:
            restored = ck.restore(where / "arrays")
    except Exception as exc:  # orbax/tensorstore raise many types for damaged files
        raise CheckpointError(
            f"checkpoint data at {where} is damaged or incomplete: {exc}"
        ) from exc
    arrays = {k: np.asarray(v) for k, v in restored.items()}
    want = meta["arrays"]
    if set(arrays) != set(want):
        raise CheckpointError(f"{where} holds arrays {sorted(arrays)} but records {sorted(want)}")
    for k, spec in want.items():
        a = arrays[k]
        if (
            list(a.shape) != spec["shape"]
            or str(a.dtype) != spec["dtype"]
            or _digest(a) != spec["sha256"]
        ):
            raise CheckpointError(
                f"array {k} of {where} fails its shape/dtype/checksum check: damaged"
            )
    return _rebuild(meta["skeleton"], arrays)
