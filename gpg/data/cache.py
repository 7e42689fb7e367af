"""The dataset cache: train/test pairs generated from a ``data`` and a ``vehicle`` config,
stored under a key that hashes everything that determines them, and loaded from there.

Entry points and notebooks share one cache directory; a pair appears in it complete or not at
all (written into a private temporary directory, then renamed into place).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gpg._dtype import float64
from gpg._io import require_writable, umask
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.sampling import FDSteps, generate
from gpg.quadrotor import acoustics, bemt
from gpg.quadrotor.generator import GENERATOR_VERSION, Generator
from gpg.quadrotor.simple_model import SimpleModel, fit_to_generator
from gpg.quadrotor.vehicle import Vehicle

__all__ = ["build_generator", "dataset_key", "ensure", "ensure_datasets", "load_data", "load_train"]

# data.generator keys, with their types; those not given keep the configs' defaults.
_BEMT_KEYS = {"n_radial": int, "n_azimuth": int, "interference": bool, "wake_gain": float}
_ACOUSTICS_KEYS = {"n_harmonics": int}
_GEN_KEYS = {**_BEMT_KEYS, **_ACOUSTICS_KEYS}


def build_generator(data_cfg: Mapping[str, Any], vehicle_cfg: Mapping[str, Any]) -> Generator:
    """The generator described by a ``data`` config group and a ``vehicle`` config group.

    Args:
        data_cfg: the ``data`` group; its ``generator`` mapping sets the BEMT (``n_radial``,
            ``n_azimuth``, ``interference``, ``wake_gain``) and acoustics (``n_harmonics``)
            settings, the others keep the configs' defaults.
        vehicle_cfg: the ``vehicle`` group (:meth:`gpg.quadrotor.vehicle.Vehicle.from_config`).

    Returns:
        The :class:`~gpg.quadrotor.generator.Generator`.

    Raises:
        ValueError: if ``data.generator`` names an unknown key.
    """
    g = dict(data_cfg.get("generator", {}))
    unknown = sorted(set(g) - _GEN_KEYS.keys())
    if unknown:
        raise ValueError(f"unknown data.generator keys {unknown}; valid: {sorted(_GEN_KEYS)}")
    cfg = bemt.BEMTConfig(**{k: cast(g[k]) for k, cast in _BEMT_KEYS.items() if k in g})
    ac = acoustics.AcousticsConfig(
        **{k: cast(g[k]) for k, cast in _ACOUSTICS_KEYS.items() if k in g}
    )
    return Generator(Vehicle.from_config(vehicle_cfg), cfg, ac)


def dataset_key(data_cfg: Mapping[str, Any], vehicle_cfg: Mapping[str, Any]) -> str:
    """The cache key of a train/test pair: a hash of everything that determines the data.

    ``chunk`` and ``workers`` do not change the data and mirror images are made after the
    cache, so they are left out; the default frame (airflow) keeps the key it had before the
    frame existed. The generator's version is part of the key.

    Args:
        data_cfg: the ``data`` config group.
        vehicle_cfg: the ``vehicle`` config group.

    Returns:
        ``<data name>-<12 hex digits>``, the name of the pair's cache directory.
    """
    # chunk and workers do not change the data; mirror images are made after the cache
    relevant = {k: v for k, v in data_cfg.items() if k not in ("chunk", "workers", "mirror")}
    if relevant.get("frame") == "airflow":  # the default: the same key as before it existed
        del relevant["frame"]
    blob = json.dumps(
        {"data": relevant, "vehicle": vehicle_cfg, "generator_version": GENERATOR_VERSION},
        sort_keys=True,
        default=str,
    )
    return f"{data_cfg.get('name', 'data')}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}"


def check_numbers(data_cfg: Mapping[str, Any]) -> None:
    """The data config's counts, seeds and switches, each named when wrong."""
    for key, lo in (("n_train", 1), ("n_test", 1), ("train_seed", 0), ("test_seed", 0)):
        v = data_cfg.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ValueError(f"data.{key} must be an integer >= {lo}, got {v!r}")
    for key, default in (("chunk", 512), ("workers", 1)):
        v = data_cfg.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"data.{key} must be a positive integer, got {v!r}")
    for key in ("keep_raw", "noise"):
        if not isinstance(data_cfg.get(key, True), bool):
            raise ValueError(f"data.{key} must be true or false, got {data_cfg.get(key)!r}")
    if data_cfg.get("frame", "airflow") not in ("airflow", "body"):
        raise ValueError(f"data.frame must be 'airflow' or 'body', got {data_cfg.get('frame')!r}")
    mirror = data_cfg.get("mirror") or []
    if not isinstance(mirror, list | tuple) or not set(mirror) <= {"x", "y"}:
        raise ValueError(f"data.mirror must be a list of body axes 'x', 'y', got {mirror!r}")
    if mirror and data_cfg.get("frame", "airflow") != "body":
        raise ValueError("data.mirror takes body-frame data (data.frame: body)")


def _generate_pair(
    gen: Generator,
    data_cfg: Mapping[str, Any],
    vehicle_cfg: Mapping[str, Any],
    simple: SimpleModel,
    progress,
):
    bounds = Bounds.from_config(data_cfg.get("bounds", {}))
    fd = FDSteps(**data_cfg.get("fd", {}))
    meta = {
        "name": data_cfg.get("name"),
        "vehicle": dict(vehicle_cfg),  # the dataset names its vehicle (Surrogate.fit reads it)
        "generator": {
            "name": "gpg BEMT + tonal acoustics",
            "version": GENERATOR_VERSION,
            "vehicle": gen.vehicle.name,
            "settings": dict(data_cfg.get("generator", {})),
        },
        "simple_model": {"P_F": float(simple.P_F), "T_z": float(simple.T_z)},
    }
    chunk = int(data_cfg.get("chunk", 512))
    workers = int(data_cfg.get("workers", 1))
    frame = data_cfg.get("frame", "airflow")
    train = generate(
        gen,
        int(data_cfg["n_train"]),
        bounds=bounds,
        seed=int(data_cfg["train_seed"]),
        gradients=data_cfg.get("gradients", "fd"),
        fd=fd,
        keep_raw=bool(data_cfg.get("keep_raw", True)),
        noise=bool(data_cfg.get("noise", True)),
        chunk=chunk,
        progress="train set" if progress else False,
        meta={**meta, "split": "train"},
        workers=workers,
        frame=frame,
    )
    test = generate(
        gen,
        int(data_cfg["n_test"]),
        bounds=bounds,
        seed=int(data_cfg["test_seed"]),
        gradients="none",
        keep_raw=False,
        noise=bool(data_cfg.get("noise", True)),
        chunk=chunk,
        progress="test set" if progress else False,
        meta={**meta, "split": "test"},
        workers=workers,
        frame=frame,
    )
    return train, test


def ensure_datasets(
    data_cfg: Mapping[str, Any],
    vehicle_cfg: Mapping[str, Any],
    cache_dir: str | Path,
    *,
    progress: bool = True,
) -> tuple[Dataset, Dataset, Path, dict[str, Any]]:
    """Load the train/test pair from the cache, generating (and caching) it when absent.

    Args:
        data_cfg: the ``data`` config group (counts, seeds, bounds, steps, generator).
        vehicle_cfg: the ``vehicle`` config group.
        cache_dir: the cache directory; the pair lives in its subdirectory
            :func:`dataset_key`.
        progress: show progress bars while generating.

    Returns:
        ``(train, test, cache_path, info)``; ``info`` has the key, the path, whether the pair
        was cached, and the seconds generation took (None when cached).
    """
    return ensure(data_cfg, vehicle_cfg, cache_dir, progress=progress)[1:]


@float64
def ensure(
    data_cfg: Mapping[str, Any],
    vehicle_cfg: Mapping[str, Any],
    cache_dir: str | Path,
    *,
    progress: bool = True,
) -> tuple[Generator, Dataset, Dataset, Path, dict[str, Any]]:
    """:func:`ensure_datasets`, also returning the generator it built.

    Every setting is checked before any work or any file (bad bounds fail at once); the
    cache directory must be writable before a generation whose result could not be kept.

    Args:
        data_cfg: the ``data`` config group.
        vehicle_cfg: the ``vehicle`` config group.
        cache_dir: the cache directory.
        progress: show progress bars while generating.

    Returns:
        ``(generator, train, test, cache_path, info)``, the rest as :func:`ensure_datasets`.

    Raises:
        ValueError: if the two seeds are equal (the test set must be held out), or a count,
            seed, switch, bound, step or generator setting is invalid, naming it; or if the
            pair must be generated and ``cache_dir`` is not writable.
    """
    check_numbers(data_cfg)
    if data_cfg["train_seed"] == data_cfg["test_seed"]:
        raise ValueError("data.train_seed and data.test_seed must differ (held-out test set)")
    # Validate everything before any work or any file: bad bounds fail in milliseconds.
    Bounds.from_config(data_cfg.get("bounds", {}))
    FDSteps(**data_cfg.get("fd", {}))
    gen = build_generator(data_cfg, vehicle_cfg)
    key = dataset_key(data_cfg, vehicle_cfg)
    where = Path(cache_dir) / key
    info: dict[str, Any] = {"key": key, "cache": str(where)}
    if (where / "train.npz").is_file() and (where / "test.npz").is_file():
        info.update(cached=True, generate_s=None)
        return gen, Dataset.load(where / "train"), Dataset.load(where / "test"), where, info
    # Before minutes of generation whose result could not be kept.
    require_writable(Path(cache_dir), "the dataset cache directory (cache_dir)")
    t0 = time.perf_counter()
    simple = fit_to_generator(gen)
    train, test = _generate_pair(gen, data_cfg, vehicle_cfg, simple, progress)
    info.update(cached=False, generate_s=time.perf_counter() - t0)
    publish(where, train, test)
    return gen, train, test, where, info


def publish(where: Path, train: Dataset, test: Dataset) -> None:
    """Write the pair into a temporary directory of this writer's own and rename it into place:
    the cache entry appears complete or not at all, and concurrent writers of one entry do not
    touch each other's files (the first rename wins; the others' data are identical)."""
    where.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=where.parent, prefix=f".{where.name}.partial-"))
    try:
        train.save(tmp / "train")
        test.save(tmp / "test")
        os.chmod(tmp, 0o777 & ~umask())  # mkdtemp makes it private; the cache is shared
        if where.exists() and not (where / "test.npz").is_file():
            shutil.rmtree(where, ignore_errors=True)  # left by a crash of an older gpg
        try:
            os.rename(tmp, where)
        except OSError:
            if not ((where / "train.npz").is_file() and (where / "test.npz").is_file()):
                raise  # not another writer's finished entry: a real failure
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def load_data(cfg: dict[str, Any]) -> tuple[Dataset, Dataset, dict[str, Any]]:
    """Train and test sets of a run's config: user files or the generated pair.

    The training set gets its mirror images when ``data.mirror`` asks for them; the test set
    is never mirrored.

    Args:
        cfg: the run's config: ``dataset.train`` and ``dataset.test`` (paths of dataset files,
            both or neither), else ``data``, ``vehicle`` and ``cache_dir`` to generate from.

    Returns:
        ``(train, test, info)``; ``info`` has the cache key (None for user files) and where
        the sets come from.

    Raises:
        ValueError: if only one of ``dataset.train`` and ``dataset.test`` is given.
    """
    paths = cfg.get("dataset") or {}
    if paths.get("train") or paths.get("test"):
        if not (paths.get("train") and paths.get("test")):
            raise ValueError("give both dataset.train and dataset.test (held-out test set)")
        train, test = Dataset.load(paths["train"]), Dataset.load(paths["test"])
        info = {"key": None, "train": str(paths["train"]), "test": str(paths["test"])}
        return with_mirrors(train, cfg), test, info
    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    return with_mirrors(train, cfg), test, info


def with_mirrors(train: Dataset, cfg: dict[str, Any]) -> Dataset:
    """The training set with its mirror images (``data.mirror``, body frame only: see
    :mod:`gpg.data.symmetry`; none by default). Made after the cache, so the cached files and
    their key do not depend on it; the test set is never mirrored."""
    axes = tuple((cfg.get("data") or {}).get("mirror") or ())
    if not axes:
        return train
    from gpg.data.symmetry import augment
    from gpg.quadrotor.vehicle import Vehicle

    return augment(train, Vehicle.from_config(cfg["vehicle"]), axes)


def load_train(cfg: dict[str, Any]) -> Dataset:
    """The training set alone: ``dataset.train``, else the generated one.

    A generated set comes through :func:`load_data`, which also generates and caches its test
    set; a user's file is read as it is (no mirror images).

    Args:
        cfg: the run's config, as for :func:`load_data`.

    Returns:
        The training :class:`~gpg.data.Dataset`.

    Raises:
        ValueError: if ``dataset.test`` is given without ``dataset.train``.
    """
    paths = cfg.get("dataset") or {}
    if paths.get("train"):
        return Dataset.load(paths["train"])
    if paths.get("test"):
        raise ValueError("dataset.test given without dataset.train (only the training set is used)")
    return load_data(cfg)[0]
