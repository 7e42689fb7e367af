"""What every kind of model provides: the options it reads, the bytes it needs, and its build.

A *kind* is a way of building a predictor from prepared training arrays (exact, local, Schur,
hybrid, PIC); a *model name* (``gpgs``, ``gps_8x``, …) is a kind plus the data it trains on
(:mod:`gpg.models`). A kind is a frozen dataclass whose fields, if any, are fixed settings of
the kind itself; what a user may change per run is read from the
:class:`~gpg.config.ModelConfig`, and only the keys named in :attr:`Kind.reads` (a run that
sets any other key away from the model's defaults is refused by :func:`gpg.models.resolve_config`).
"""

from __future__ import annotations

import abc
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import jax
import numpy as np

from gpg.config import ModelConfig
from gpg.gp import partition
from gpg.gp.gram import mask_targets, observed_rows, stack_targets
from gpg.gp.hyper import Hyper
from gpg.gp.predictor import Predictor
from gpg.linalg import device as linalg_device
from gpg.parallel import Devices

if TYPE_CHECKING:
    from gpg.gp.exact import ExactGP

__all__ = ["Arrays", "Cases", "Kind", "Product", "build_partition"]


@dataclass(frozen=True)
class Arrays:
    """What a model trains on (normalised): inputs ``X`` (N, D), targets ``Y`` (N, M), their
    gradients ``dY`` (N, M, G) or None, and the gradient dimensions ``dims`` they cover."""

    X: np.ndarray
    Y: np.ndarray
    dY: np.ndarray | None
    dims: tuple[int, ...]
    # (N, G): which gradients each case has; None when all (cases without some perturbations)
    observed: np.ndarray | None = None
    # Bins to keep (a rebuild that must match a conditioned model); None: built from the config
    partition: partition.Partition | None = None
    # (N, G, G): the directions of each case's gradient rows (gpg.gp.gram.row_directions);
    # None for derivatives along the coordinates dims
    bases: np.ndarray | None = None

    @property
    def n_grad(self) -> int:
        return len(self.dims) if self.dY is not None else 0

    @property
    def rows(self) -> np.ndarray | None:
        """The observed stacked rows (:func:`gpg.gp.gram.observed_rows`)."""
        return observed_rows(self.observed, self.X.shape[0])

    def bins(self, cfg: ModelConfig) -> partition.Partition:
        """The partition to train with: the one given, else the one ``cfg`` asks for.

        Args:
            cfg: the resolved model config (its ``partition`` section).

        Returns:
            :attr:`partition` when set (a rebuild that must keep a model's bins), else
            :func:`build_partition` on ``X`` and ``Y``.
        """
        return (
            self.partition if self.partition is not None else build_partition(self.X, cfg, self.Y)
        )

    def targets(self) -> np.ndarray:
        """The stacked targets ``Ȳ`` the kinds solve against.

        Returns:
            ``Ȳ`` (R, M) in the layout of :mod:`gpg.gp.kernels` (values, then each gradient
            dim's rows), 0 on the rows not observed.
        """
        return mask_targets(stack_targets(self.Y, self.dY), self.rows)


class Cases(NamedTuple):
    """A conditionable model's training inputs ``X`` (normalised, N × D), hyperparameters and
    gradient dims (:meth:`Kind.cases`)."""

    X: np.ndarray
    hyper: Hyper
    grad_dims: tuple[int, ...]


@dataclass
class Product:
    """A kind's build: the predictor, the near sets it conditions on (if any), what was measured
    at build time (``diagnostics``) and the seconds of each step (``timings``)."""

    model: Predictor
    near: partition.NearSets | None = None
    diagnostics: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


class Kind(abc.ABC):
    """The interface of a kind (module docstring). Subclasses set the class attributes and
    implement :meth:`build` and :meth:`required_bytes`."""

    name: ClassVar[str]  # the kind's word in the registry and in messages
    reads: ClassVar[tuple[str, ...]]  # top-level ModelConfig keys read besides ``hyper``
    partitioned: ClassVar[bool]  # cuts the inputs into bins (``partition`` is read)
    needs_gram: ClassVar[bool] = False  # forms and factorises the whole K̄
    # The predictor class a kind defined outside gpg builds: checkpoints name classes, and load
    # only those of gpg and of registered kinds (gpg's own kinds leave it None).
    predictor: ClassVar[type[Predictor] | None] = None
    # Trains on cases that carry only some gradient dims (Arrays.observed)
    partial_gradients: ClassVar[bool] = False
    # Trains on gradient rows along other directions than the inputs' (Arrays.bases)
    directional_gradients: ClassVar[bool] = False

    def condition(self, model: Predictor, new: Arrays, cfg: ModelConfig) -> Predictor:
        """``model`` conditioned on the cases ``new``, without a refit.

        Kinds that can condition override this; the result equals a rebuild on all the cases
        with ``model``'s hyperparameters. The default refuses.

        Args:
            model: a predictor this kind built.
            new: the new cases, normalised as ``model``'s training arrays were.
            cfg: the model's resolved config.

        Returns:
            The conditioned predictor.

        Raises:
            ValueError: always, for a kind that cannot condition (naming the kind).
        """
        raise self._cannot_condition()

    def cases(self, model: Predictor) -> Cases:
        """What :mod:`gpg.design` reads of a model that conditions.

        Args:
            model: a predictor this kind built.

        Returns:
            Its normalised training inputs, hyperparameters and gradient dims.

        Raises:
            ValueError: always, for a kind that cannot condition.
        """
        raise self._cannot_condition()

    def posterior(self, model: Predictor) -> ExactGP:
        """The exact GP-G that the acquisition reads its variances from.

        Args:
            model: a predictor this kind built.

        Returns:
            The exact GP-G on ``model``'s training cases with its hyperparameters.

        Raises:
            ValueError: always, for a kind that cannot condition.
        """
        raise self._cannot_condition()

    def _cannot_condition(self) -> ValueError:
        return ValueError(
            f"a model of kind {self.name!r} cannot be conditioned on new cases: refit it "
            "(gpg and gpgs_hybrid can)"
        )

    @abc.abstractmethod
    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """The predictor on ``arrays`` with fixed hyperparameters.

        Args:
            arrays: the normalised training arrays.
            hyper: the hyperparameters (σ, l, ν², λ_i²), fitted beforehand.
            cfg: the resolved model config; only the keys in :attr:`reads` are used.
            devices: JAX devices to spread the kind's per-bin work over, where it has any
                (:mod:`gpg.parallel`); None for the single-device or host path.

        Returns:
            The predictor with the near sets, diagnostics and timings of the build.
        """

    @abc.abstractmethod
    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """Peak bytes of :meth:`build` beyond the data, estimated from sizes alone.

        Args:
            cfg: the resolved model config.
            n_points: training points ``N``.
            n_grad: gradient dims per point ``G`` (0 without gradients).

        Returns:
            The estimate in bytes, checked against the memory available before any work.
        """

    def check(self, model: str, cfg: ModelConfig, n_points: int) -> None:
        """Size checks of the options against the data, before any work.

        Args:
            model: the model name, for the message.
            cfg: the resolved model config.
            n_points: training points.

        Raises:
            ValueError: if a partitioned kind is asked for more bins than points, naming
                ``model``.
        """
        if self.partitioned and cfg.partition.n_bins(n_points) > n_points:
            raise ValueError(
                f"model {model!r}: partition.bins={cfg.partition.n_bins(n_points)} exceeds the "
                f"{n_points} training points"
            )


def build_partition(
    X: np.ndarray, cfg: ModelConfig, Y: np.ndarray | None = None
) -> partition.Partition:
    """The partition a resolved config asks for.

    Args:
        X: (N, D) normalised training inputs.
        cfg: the resolved model config (its ``partition`` section: scheme, bins, dim).
        Y: (N, M) training targets, read by the ``adaptive`` scheme only (its bins follow
            their local variation).

    Returns:
        The partition of ``X`` into the configured number of bins.

    Raises:
        ValueError: if ``partition.dim`` is not an input of ``X``, or the ``adaptive``
            scheme is given no targets.
    """
    pc = cfg.partition
    opts: dict[str, Any] = {"dim": pc.dim} if pc.scheme in ("slab", "adaptive") else {}
    if opts and not 0 <= pc.dim < X.shape[1]:
        raise ValueError(
            f"partition.dim={pc.dim} is not an input of the {X.shape[1]}-input data (0 to "
            f"{X.shape[1] - 1}; body-frame data has 7 inputs r1..r4, u, v, w: e.g. "
            "partition.dim=4 cuts along u, or partition.scheme=kdtree)"
        )
    if pc.scheme == "adaptive":
        if Y is None:
            raise ValueError("partition.scheme=adaptive needs the training targets")
        opts["weights"] = partition.variation_weights(X, Y)
    return partition.build(X, pc.scheme, pc.n_bins(X.shape[0]), **opts)


def bins_and_near(
    arrays: Arrays, hyper: Hyper, cfg: ModelConfig
) -> tuple[partition.Partition, partition.NearSets, np.ndarray, dict[str, float]]:
    """The partition, every bin's near set (``near`` options), the stacked targets ``Ȳ``
    (:func:`gpg.gp.gram.stack_targets`) and the build's timings so far (``partition_s``)."""
    t0 = time.perf_counter()
    part = arrays.bins(cfg)
    near = partition.near_sets(arrays.X, part, hyper.lengthscale, **cfg.near.rule())
    return part, near, arrays.targets(), {"partition_s": time.perf_counter() - t0}


def near_set_bytes(cfg: ModelConfig, n_points: int, n_grad: int) -> int:
    """Peak bytes of a per-bin near-set precompute: a few dense near blocks while one bin is
    factorised, and every bin's stored factor after."""
    bins = cfg.partition.n_bins(n_points)
    near = cfg.near
    per_bin = math.ceil(n_points / bins)
    if near.points is not None:
        width = max(near.points, per_bin) * (1 + n_grad)
    elif near.budget is not None and near.epsilon is None:
        width = max(math.ceil(near.budget * n_points), per_bin) * (1 + n_grad)
    else:
        width = n_points * (1 + n_grad)  # an ε near set can hold every point
    return int(8 * width * width * (3 + 0.6 * bins))


def gram_bytes(n_points: int, n_grad: int, copies: float = 1.2) -> int:
    """Bytes of ``copies`` dense ``K̄`` over ``n_points`` points with ``n_grad`` gradient rows."""
    rows = n_points * (1 + n_grad)
    return int(rows * rows * 8 * copies)


def bin_devices(devices, cfg: ModelConfig, rows: int, what: str, *, host_only: bool = False):
    """The devices of a per-bin precompute (:mod:`gpg.parallel`): the caller's, else JAX's
    default device where ``solver.device`` places a bin's solve of ``rows`` rows there
    (:func:`gpg.linalg.device.place`), else None, the host path. ``host_only``: the data need
    the host path (cases without some gradients, directional rows), which ``auto`` then takes;
    ``device`` passes the device on, and the precompute refuses with its reason."""
    if devices is not None:
        return devices
    mode = cfg.solver.device
    if host_only and mode == "auto":
        return None
    if linalg_device.place(mode, linalg_device.solve_bytes(rows, True), what) == "device":
        return jax.devices()[:1]
    return None
