"""Small helpers shared by the experiment runners: timing, model building, JSON output, tables."""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import numpy as np

from gpg import conf as package_conf

if TYPE_CHECKING:
    from gpg.config import ModelConfig
    from gpg.data.dataset import Dataset
    from gpg.data.preprocess import Training
    from gpg.models import Built
    from gpg.quadrotor.simple_model import SimpleModel
    from gpg.quadrotor.simple_noise import SimpleNoise

# The entry points' own configs (compare.yaml, ...), beside this package in the repository
# (experiments/ and conf/ are both the repository's, neither is installed). The library's
# configs (data scales, models, vehicles) ship inside gpg (gpg.conf).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"

_log = logging.getLogger("experiments.runs")


def report(text: str) -> None:
    """A result for the console and, under Hydra, the run's log file (``<job>.log``): logged
    at INFO when logging is configured, printed otherwise."""
    if logging.getLogger().hasHandlers():
        _log.info(text)
    else:
        print(text)


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


def set_dispatch(cfg: Mapping[str, Any]) -> None:
    """Apply ``cfg['sync_dispatch']`` (default true): run JAX CPU computations on the calling
    thread. JAX otherwise runs them on a worker thread, and waking the caller afterwards adds a
    noisy latency per call comparable to a mean prediction (the README's real-time quick start
    says how much)."""
    jax.config.update("jax_cpu_enable_async_dispatch", not cfg.get("sync_dispatch", True))


def block(x):
    """Wait for every array in ``x`` (JAX dispatch is asynchronous)."""
    return jax.block_until_ready(x)


def time_calls(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> np.ndarray:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        block(fn())
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        block(fn())
        out[i] = time.perf_counter() - t0
    return out


def stats(seconds: np.ndarray) -> dict[str, float]:
    """Median, 5th and 95th percentile and mean, in seconds."""
    return {
        "median_s": float(np.median(seconds)),
        "p05_s": float(np.percentile(seconds, 5)),
        "p95_s": float(np.percentile(seconds, 95)),
        "mean_s": float(np.mean(seconds)),
        "n": int(seconds.size),
    }


def latency(fn: Callable[..., Any], args_list: Sequence[tuple], n: int) -> dict[str, float]:
    """:func:`stats` of ``n`` calls ``fn(*args)`` cycling through ``args_list``, after 3
    untimed warm-up calls."""
    calls = itertools.cycle(args_list)
    return stats(time_calls(lambda: fn(*next(calls)), n, warmup=3))


def world_arrays(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dataset inputs ``x`` as world-frame states ``(rpm, euler, v_air)`` (N, 4), (N, 3),
    (N, 3) whose world frame is the dataset's: airflow-frame inputs (rpm, Euler angles,
    airspeed; 8 columns) fly the air ``V e_x`` at that attitude, body-frame inputs
    ``(rpm, u, v, w)`` (7 columns) the identity attitude with that air."""
    if x.shape[1] == 7:
        return x[:, :4], np.zeros((x.shape[0], 3)), x[:, 4:7]
    v = np.zeros((x.shape[0], 3))
    v[:, 0] = x[:, 7]
    return x[:, :4], x[:, 4:7], v


def world_states(x: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The first ``n`` (at least one) of :func:`world_arrays`, one state at a time: NumPy
    arrays, as a simulator written in Python passes them."""
    rpm, euler, v = world_arrays(x[: max(n, 1)])
    return [(np.array(r), np.array(e), np.array(a)) for r, e, a in zip(rpm, euler, v, strict=True)]


class Fitted(NamedTuple):
    """A model built by :func:`fit_model`, with what went into it."""

    training: Training
    built: Built
    hyper_fit: Any  # HyperFitResult, or None when the hyperparameters were not fitted
    timings: dict[str, float]  # hyper_s (of the fit, also when shared), then build's own
    peak_memory_bytes: int | None  # peak RSS growth of fit + build (if measured)


def fit_model(
    name: str,
    mcfg: ModelConfig,
    train: Dataset,
    simple: SimpleModel | None,
    hyper_cache: dict,
    *,
    noise_model: SimpleNoise | None = None,
    measure_memory: bool = False,
    devices=None,
) -> Fitted:
    """Preprocess ``train`` and build model ``name`` with its resolved config ``mcfg``.

    Hyperparameters are fitted once per training arrays (raw samples or not, gradients or not)
    and hyperparameter config, and shared through ``hyper_cache`` by the models that match.
    ``measure_memory`` samples the peak RSS of the fit and build.
    """
    from gpg import models
    from gpg.linalg import memory

    with memory.PeakRSS() if measure_memory else contextlib.nullcontext() as mem:
        training, built = models.train(
            name,
            train,
            simple,
            mcfg,
            noise_model=noise_model,
            hyper_cache=hyper_cache,
            devices=devices,
        )
    return Fitted(
        training,
        built,
        built.hyper_fit,
        built.timings,
        mem.peak_delta if measure_memory else None,
    )


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


def surrogate_from_config(cfg: Mapping[str, Any], vehicle) -> Any:
    """The surrogate a flight experiment uses: ``cfg["surrogate_checkpoint"]`` loaded, or
    ``cfg["model"]`` (its ``name`` and overrides) fitted on the configured training data."""
    from gpg import checkpoint
    from gpg.data.cache import load_train
    from gpg.surrogate import Surrogate

    if cfg.get("surrogate_checkpoint"):
        return checkpoint.load(cfg["surrogate_checkpoint"])
    model = dict(cfg["model"])
    name = model.pop("name")
    return Surrogate.fit(load_train(cfg), name, model, vehicle=vehicle)


def flight_setup(cfg: Mapping[str, Any], options: Mapping[str, str]):
    """What every flight experiment starts with: its ``options`` checked, the dispatch set,
    the vehicle and the surrogate (:func:`surrogate_from_config`), which must carry the
    simplified model ``M`` the controller is designed on."""
    from gpg.quadrotor.vehicle import Vehicle

    check_options(cfg, options)
    set_dispatch(cfg)
    vehicle = Vehicle.from_config(cfg["vehicle"])
    sur = surrogate_from_config(cfg, vehicle)
    if sur.simple is None:
        raise ValueError("the surrogate has no simplified model; the controller needs one")
    return vehicle, sur


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }


def table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    """A Markdown table: ``columns`` are (key, header, format spec)."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    lines = [head, sep]
    for r in rows:
        cells = []
        for key, _, spec in columns:
            v = r.get(key)
            cells.append("—" if v is None else format(v, spec) if spec else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
