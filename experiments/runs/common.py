"""What several experiments build the same way: world-frame query arrays, a model fitted and
timed, the surrogate and vehicle of a flight experiment. The configs are read by
:mod:`experiments.runs.config`, times measured by :mod:`experiments.runs.timing`, results
printed by :mod:`experiments.runs.output`."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from experiments.runs.config import check_options
from experiments.runs.timing import set_dispatch

if TYPE_CHECKING:
    from gpg.config import ModelConfig
    from gpg.data.dataset import Dataset
    from gpg.data.preprocess import Training
    from gpg.models import Built
    from gpg.quadrotor.simple_model import SimpleModel
    from gpg.quadrotor.simple_noise import SimpleNoise


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
