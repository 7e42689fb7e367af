"""gpg's models under one ``predict``, built by name: the paper's six baselines and two more.

=========== ========= ====== ====== ================ ===================================
name        gradients points kind   far set          what
=========== ========= ====== ====== ================ ===================================
gp          no        raw 8X exact  —                exact GP on every raw sample
gpg         yes       1X     exact  —                exact GP with gradients (GP-G)
gps_1x      no        1X     local  dropped          local GP per bin (GP-S-1X)
gps_8x      no        raw 8X local  dropped          local GP per bin (GP-S-8X)
gpgs        yes       1X     local  dropped          local GP-G per bin (GP-G-S)
gpgs_schur  yes       1X     schur  Schur complement the paper's method (GP-G-S-Schur)
gpgs_hybrid yes       1X     hybrid exact mean       GP-G mean, near-set variance
gpg_pic     yes       1X     pic    inducing points  PIC: exact block per bin + low rank
=========== ========= ====== ====== ================ ===================================

A name is a kind (:mod:`gpg.kinds`: how the predictor is built, and which options it reads)
plus the data it trains on; :data:`SPECS` is the registry, one line per name, and
``gpg/conf/model/<name>.yaml`` holds each name's own defaults. Options (not new names):
partition ``scheme``, bins, near ``budget``, ``points`` or ``epsilon``, the ``mean`` form of
``gpgs_schur`` (exact, paper) and its precompute ``route`` (global, direct), the storage
``variance_dtype`` of the variance factors, and the ``inducing`` points of ``gpg_pic``; an
option a name's kind does not read is refused (:func:`resolve_config`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gpg._dtype import float64
from gpg.config import ModelConfig, package_defaults
from gpg.data.dataset import Dataset
from gpg.data.preprocess import Training, prepare
from gpg.gp import partition
from gpg.gp.fit import HyperFitResult, fit_hyperparameters
from gpg.gp.hyper import Hyper, gradient_noise
from gpg.gp.predictor import Predictor
from gpg.kinds import KINDS, Arrays, Kind, base
from gpg.linalg import memory
from gpg.names import GRAD_DIMS
from gpg.parallel import Devices
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise

__all__ = [
    "NAMES",
    "SPECS",
    "Built",
    "Spec",
    "build",
    "build_partition",
    "check_feasible",
    "check_finite_model",
    "fit_hyper",
    "gradient_arrays",
    "model_defaults",
    "reads",
    "register",
    "required_bytes",
    "resolve_config",
    "restrict",
    "train",
    "training_arrays",
    "unregister",
]

DATA = ("values", "gradients", "raw")  # what a model trains on (see Spec.data)


@dataclass(frozen=True)
class Spec:
    """What a model name means: the ``data`` it trains on (``values`` the base points without
    their gradients, ``gradients`` the base points with them, ``raw`` every raw 8X sample), the
    ``kind`` that builds it (:mod:`gpg.kinds`) and its ``title`` in tables and figures."""

    data: str
    kind: Kind
    title: str

    def __post_init__(self):
        if self.data not in DATA:
            raise ValueError(f"Spec.data must be one of {list(DATA)}, got {self.data!r}")
        if not isinstance(self.kind, Kind):
            raise ValueError(f"Spec.kind must be a gpg.kinds.Kind, got {self.kind!r}")

    @property
    def gradients(self) -> bool:
        """Whether the model trains on the base points with their gradients."""
        return self.data == "gradients"

    @property
    def raw(self) -> bool:
        """Whether the model trains on every raw 8X sample."""
        return self.data == "raw"

    @property
    def partitioned(self) -> bool:
        """Whether the model's kind cuts the inputs into bins."""
        return self.kind.partitioned

    @property
    def schur(self) -> bool:
        """Whether the model is built by the paper's Schur complement (``gpgs_schur``)."""
        return self.kind.name == "schur"


SPECS: dict[str, Spec] = {
    "gp": Spec("raw", KINDS["exact"], "GP"),
    "gpg": Spec("gradients", KINDS["exact"], "GP-G"),
    "gps_1x": Spec("values", KINDS["local"], "GP-S-1X"),
    "gps_8x": Spec("raw", KINDS["local"], "GP-S-8X"),
    "gpgs": Spec("gradients", KINDS["local"], "GP-G-S"),
    "gpgs_schur": Spec("gradients", KINDS["schur"], "GP-G-S-Schur"),
    "gpgs_hybrid": Spec("gradients", KINDS["hybrid"], "GP-G-S-Hybrid"),
    "gpg_pic": Spec("gradients", KINDS["pic"], "GP-G-PIC"),
}
NAMES = tuple(SPECS)
PAPER_NAMES = NAMES[:6]  # the paper's six baselines
_DEFAULTS: dict[str, dict[str, Any]] = {}  # defaults of models registered in code


def register(
    name: str, kind: Kind, data: str, title: str, defaults: Mapping[str, Any] | None = None
) -> None:
    """Add model ``name``, which then builds, checkpoints and compares like the built-in ones.

    See docs/design.md, "Kinds of model, and adding one".

    Args:
        name: the new model's name, a Python identifier not yet in :data:`SPECS`.
        kind: the :class:`~gpg.kinds.Kind` that builds it.
        data: what it trains on, ``"values"``, ``"gradients"`` or ``"raw"`` (:class:`Spec`).
        title: its name in tables and figures.
        defaults: its own defaults over the shared ones, as a built-in model keeps them in
            ``gpg/conf/model/<name>.yaml``; None for none.

    Raises:
        ValueError: if ``name`` is not an identifier or is already registered, or ``data``,
            ``kind`` or ``defaults`` are not valid (checked before anything is registered).
    """
    global NAMES
    if not name.isidentifier():
        raise ValueError(f"model name must be an identifier, got {name!r}")
    if name in SPECS:
        raise ValueError(f"model {name!r} is already registered")
    spec = Spec(data, kind, title)
    ModelConfig.resolve(name, None, dict(defaults or {}))  # bad defaults fail here
    SPECS[name] = spec
    _DEFAULTS[name] = dict(defaults or {})
    NAMES = tuple(SPECS)


def unregister(name: str) -> None:
    """Remove a model added by :func:`register`.

    Args:
        name: the model's name.

    Raises:
        ValueError: if ``name`` was not added by :func:`register` (a built-in model stays).
    """
    global NAMES
    if name not in _DEFAULTS:
        raise ValueError(f"model {name!r} was not added by register()")
    del SPECS[name], _DEFAULTS[name]
    NAMES = tuple(SPECS)


def reads(name: str) -> tuple[str, ...]:
    """The top-level config keys model ``name`` reads.

    Args:
        name: a model name of :data:`NAMES`.

    Returns:
        ``"hyper"`` and the options of the model's kind (:attr:`gpg.kinds.Kind.reads`).

    Raises:
        ValueError: if ``name`` is not a known model.
    """
    return ("hyper", *SPECS[_known(name)].kind.reads)


def restrict(name: str, overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """The top-level keys of ``overrides`` that model ``name`` reads (:func:`reads`).

    One mapping of options serves several models, each given what applies to it (the
    comparison's ``model_overrides``).

    Args:
        name: a model name of :data:`NAMES`.
        overrides: options for several models; None for none.

    Returns:
        The entries of ``overrides`` whose key the model reads.

    Raises:
        ValueError: if ``name`` is not a known model.
    """
    read = reads(name)
    return {k: v for k, v in (overrides or {}).items() if k in read}


def model_defaults(name: str) -> dict[str, Any]:
    """Model ``name``'s own defaults over the shared ones.

    Args:
        name: a model name.

    Returns:
        The defaults given to :func:`register` for the model, else its
            ``gpg/conf/model/<name>.yaml`` (:func:`gpg.config.package_defaults`; empty without
            a file).
    """
    if name in _DEFAULTS:
        return dict(_DEFAULTS[name])
    return package_defaults(name)


def _known(name: str) -> str:
    if name not in SPECS:
        raise ValueError(f"unknown model {name!r}; valid: {list(NAMES)}")
    return name


def resolve_config(name: str, cfg: Mapping[str, Any] | ModelConfig | None = None) -> ModelConfig:
    """Model ``name``'s :class:`~gpg.config.ModelConfig`, checked before any data is touched.

    The shared defaults, then the model's own (:func:`model_defaults`), then ``cfg``. A key the
    model's kind does not read may not be set away from the model's default: ``gpg`` with a
    partition, or ``gpgs_schur`` with another route than its own, is refused rather than
    silently ignored.

    Args:
        name: a model name of :data:`NAMES`.
        cfg: overrides such as ``{"hyper": {"subset": 60}}``, or a :class:`ModelConfig`,
            taken as it is and checked the same way; None for the model's defaults.

    Returns:
        The resolved config.

    Raises:
        ValueError: for an unknown name, key or value, or a key the model's kind does not
            read set away from its default, naming it.
    """
    _known(name)
    defaults = model_defaults(name)
    own = ModelConfig.resolve(name, None, defaults)
    out = cfg if isinstance(cfg, ModelConfig) else ModelConfig.resolve(name, cfg, defaults)
    read = reads(name)
    base, got = own.to_dict(), out.to_dict()
    for key in got:
        if key in read:
            continue
        # A kind may read single keys of a section ("solver.device"): the rest must stay.
        sub = {r.split(".", 1)[1] for r in read if r.startswith(f"{key}.")}
        a, b = base[key], got[key]
        if sub and isinstance(a, dict):
            a = {k: v for k, v in a.items() if k not in sub}
            b = {k: v for k, v in b.items() if k not in sub}
        if a != b:
            where = _first_difference(key, a, b)
            raise ValueError(
                f"model {name!r} does not read option {where!r} (its kind "
                f"{SPECS[name].kind.name!r} reads: {', '.join(read)})"
            )
    return out


def _first_difference(where: str, a: Any, b: Any) -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in a:
            if a[k] != b.get(k):
                return _first_difference(f"{where}.{k}", a[k], b.get(k))
    return where


def build_partition(
    X: np.ndarray, cfg: ModelConfig, Y: np.ndarray | None = None
) -> partition.Partition:
    """The partition a resolved config asks for (:func:`gpg.kinds.base.build_partition`).

    Args:
        X: (N, D) normalised training inputs.
        cfg: the resolved config; its ``partition`` section (scheme, bins, dim) is read.
        Y: (N, M) normalised targets, which the ``adaptive`` scheme needs; None otherwise.

    Returns:
        The bins of the training points.
    """
    return base.build_partition(X, cfg, Y)


@dataclass
class Built:
    """A built model and how it was built (timings in seconds, resolved config).

    ``timings`` holds the seconds of each build step (``hyper_s`` for the fit, then the
    kind's); ``near`` the near sets of a partitioned kind (None otherwise).

    ``diagnostics`` holds what was measured at build time: for ``gpgs_schur`` the far-set
    correlations that its ``k_qf ≈ 0`` assumption needs small (:func:`schur.far_correlation`),
    for ``gpg_pic`` the inducing-point count.
    """

    name: str
    model: Predictor
    config: ModelConfig
    hyper: Hyper
    hyper_fit: HyperFitResult | None
    timings: dict[str, float] = field(default_factory=dict)
    near: partition.NearSets | None = None
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def train_s(self) -> float:
        """The build's seconds, all steps together."""
        return sum(self.timings.values())


def training_arrays(name: str, training: Training) -> Arrays:
    """The :class:`~gpg.kinds.Arrays` model ``name`` trains on.

    Args:
        name: a model name of :data:`NAMES`.
        training: the prepared data (:func:`gpg.data.prepare`).

    Returns:
        The raw 8X samples, the base points with their gradients, or the base points alone,
            as the model's :class:`Spec` says.

    Raises:
        ValueError: if ``name`` is unknown, or the data lack what the model trains on (the raw
            samples, or the gradients), saying which.
    """
    spec = SPECS[_known(name)]
    if spec.raw:
        if training.X_raw is None:
            raise ValueError(
                f"model {name!r} trains on the raw 8X samples, which the dataset lacks"
            )
        return Arrays(training.X_raw, training.Y_raw, None, ())
    if spec.gradients:
        if training.dY is None:
            raise ValueError(f"model {name!r} needs gradients, which the dataset lacks")
        return gradient_arrays(training.X, training.Y, training.dY, training.bases)
    return Arrays(training.X, training.Y, None, ())


def gradient_arrays(
    X: np.ndarray, Y: np.ndarray, dY: np.ndarray, bases: np.ndarray | None = None
) -> Arrays:
    """Training arrays with gradients along :data:`gpg.names.GRAD_DIMS`.

    Args:
        X: (N, D) normalised inputs.
        Y: (N, M) normalised targets.
        dY: (N, M, G) their gradients; NaN marks a gradient dim a case was not run for (all
            outputs alike, :attr:`gpg.data.Dataset.gradient_mask`).
        bases: (N, G, G) the directions of the gradient columns
            (:attr:`gpg.data.Dataset.grad_dirs`); None for the coordinate directions.

    Returns:
        The training arrays (:class:`~gpg.kinds.Arrays`); where ``dY`` has NaN, those
            entries are zeroed and ``observed`` marks the gradients each case has.
    """
    missing = np.isnan(dY)
    if not missing.any():
        return Arrays(X, Y, dY, GRAD_DIMS, bases=bases)
    return Arrays(X, Y, np.where(missing, 0.0, dY), GRAD_DIMS, ~missing[:, 0, :], bases=bases)


def initial_hyper(cfg: ModelConfig, n_inputs: int, dY: np.ndarray | None) -> Hyper:
    """The configured hyperparameters: the fit's start, or the values used without a fit."""
    h = cfg.hyper
    ls = np.asarray(h.lengthscale, float)
    if ls.shape not in ((), (n_inputs,)):
        raise ValueError(
            f"hyper.lengthscale has {ls.size} values; the model has {n_inputs} inputs: give one "
            f"value (every input) or {n_inputs} (one per input, with hyper.ard)"
        )
    if h.ard:
        ls = np.broadcast_to(ls, (n_inputs,))
    elif ls.ndim:
        raise ValueError("hyper.lengthscale has one value per input but hyper.ard is false")
    lam = gradient_noise(dY, h.grad_noise_scale) if dY is not None else 1e-6
    return Hyper(variance=h.variance, lengthscale=ls, noise=h.noise, grad_noise=lam)


@float64
def fit_hyper(
    name: str, training: Training, cfg: Mapping[str, Any] | ModelConfig | None = None
) -> tuple[Hyper, HyperFitResult | None, float]:
    """Hyperparameters for model ``name``: fitted, or the configured values.

    The fit maximises the marginal likelihood on a subset (``hyper.subset``), then, with
    ``hyper.full``, refits on every point by the stochastic likelihood from the subset's
    optimum. Either way the lengthscales are then multiplied by ``hyper.lengthscale_scale``.

    Args:
        name: a model name of :data:`NAMES`; it decides the training arrays.
        training: the prepared data (:func:`gpg.data.prepare`).
        cfg: the model's options (:func:`resolve_config`).

    Returns:
        The hyperparameters (σ², l, ν², λ_i²), the fit's result (None without a fit), and
            the fit's seconds (0 without one).
    """
    cfg = resolve_config(name, cfg)
    arrays = training_arrays(name, training)
    X, Y, dY, dims = arrays.X, arrays.Y, arrays.dY, arrays.dims
    seen = dY if arrays.observed is None else np.where(arrays.observed[:, None], dY, np.nan)
    init = initial_hyper(cfg, X.shape[1], seen)
    h = cfg.hyper
    res, seconds = None, 0.0
    if not h.fit:
        hyper = init.validate(X.shape[1], len(dims))
    else:
        t0 = time.perf_counter()
        data = {
            "grad_dims": dims if dY is not None else None,
            "observed": arrays.observed,
            "bases": arrays.bases,
        }
        res = fit_hyperparameters(X, Y, dY, init=init, options=h.fit_options(), **data)
        if h.full:
            # From the subset's optimum: the refit on all points then needs few of its steps.
            opts = h.full_options(_noise_ratio(res, h))
            res = fit_hyperparameters(X, Y, dY, init=res.hyper, options=opts, **data)
        hyper, seconds = res.hyper, time.perf_counter() - t0
    if h.lengthscale_scale != 1.0:
        scaled = hyper.lengthscale * h.lengthscale_scale
        hyper = eqx.tree_at(lambda t: t.lengthscale, hyper, scaled)
    check_scaled_inputs(X, hyper)
    return hyper, res, seconds


def _noise_ratio(res: HyperFitResult, h) -> float:
    """Where the refit on all points starts ``ν²/σ``: the subset fit's, kept above the floor."""
    return max(res.noise_ratio, h.noise_floor * (1 + 1e-6)) if h.fit_noise else h.noise_init


def check_scaled_inputs(X: np.ndarray, hyper: Hyper) -> None:
    """Refuse a lengthscale so small that ``x/l`` overflows (1e-300 on inputs in [−1, 1]).

    The kernel divides the inputs by the lengthscales: such a model would answer NaN
    everywhere."""
    ls = np.asarray(hyper.lengthscale, dtype=float)
    with np.errstate(all="ignore"):
        r2 = np.sum((np.asarray(X) / ls) ** 2, axis=1)
    if not np.all(np.isfinite(r2)):
        raise ValueError(
            f"lengthscale {ls.min():.3g} is too small for inputs in [-1, 1]: the scaled "
            "distances overflow and every prediction would be NaN"
        )


def check_finite_model(name: str, model: Predictor) -> None:
    """Check that every array a built model holds is finite.

    A fit never returns a model that answers NaN for finite queries.

    Args:
        name: the model's name, for the message.
        model: the built predictor.

    Raises:
        ValueError: naming the first array that holds NaN or inf.
    """
    leaves = jax.tree_util.tree_leaves_with_path(eqx.filter(model, eqx.is_inexact_array))
    for path, leaf in leaves:
        if not np.all(np.isfinite(np.asarray(leaf))):
            where = jax.tree_util.keystr(path)
            raise ValueError(
                f"model {name!r}: the fit produced NaN or inf in {where}; the data or the "
                "hyperparameters are degenerate (e.g. too few points, duplicated inputs with "
                "different outputs, or extreme values)"
            )


def required_bytes(
    name: str, cfg: Mapping[str, Any] | ModelConfig | None, n_points: int, n_grad: int
) -> int:
    """The peak bytes the build of model ``name`` needs beyond the data.

    Estimated from the sizes alone, before any data exist (:meth:`gpg.kinds.Kind.required_bytes`).

    Args:
        name: a model name of :data:`NAMES`.
        cfg: the model's options (:func:`resolve_config`).
        n_points: the training points N.
        n_grad: the gradient dims G per point.

    Returns:
        The estimate, in bytes.
    """
    cfg = resolve_config(name, cfg)
    return SPECS[name].kind.required_bytes(cfg, n_points, n_grad)


def check_feasible(
    name: str, cfg: Mapping[str, Any] | ModelConfig | None, training: Training
) -> None:
    """Check everything that can be checked before any heavy work, with one clear message.

    The data the model needs, its sizes against the data (bins, inducing points), and memory.

    Args:
        name: a model name of :data:`NAMES`.
        cfg: the model's options (:func:`resolve_config`).
        training: the prepared data (:func:`gpg.data.prepare`).

    Raises:
        ValueError: if the data lack what the model trains on, its sizes do not fit the data,
            or it cannot train on directional or partial gradients the data have.
        gpg.linalg.memory.InsufficientMemory: if the build would not fit in the memory
            available.
    """
    cfg = resolve_config(name, cfg)
    arrays = training_arrays(name, training)
    n = arrays.X.shape[0]
    kind = SPECS[name].kind
    kind.check(name, cfg, n)
    if arrays.bases is not None and not kind.directional_gradients:
        raise ValueError(
            f"model {name!r} takes gradients along the inputs only, and this dataset's are "
            "along other directions (grad_dirs: data converted by gpg.data.convert.to_body); "
            "gpg and gpgs_hybrid train on such data"
        )
    if arrays.observed is not None and not kind.partial_gradients:
        raise ValueError(
            f"model {name!r} needs every gradient at every case, and some cases lack some "
            "(NaN gradients in the dataset); gpg and gpgs_hybrid train on such data"
        )
    need = kind.required_bytes(cfg, n, len(arrays.dims))
    hint = " (gpgs and gpg_pic train without K̄, gpgs_hybrid too with solver.method=cg)"
    hint = hint if kind.needs_gram else ""
    memory.require(f"model {name!r} on {n} points{hint}", need)


@float64
def build(
    name: str,
    training: Training,
    cfg: Mapping[str, Any] | ModelConfig | None = None,
    *,
    hyper: Hyper | None = None,
    devices: Devices = None,
) -> Built:
    """Build model ``name`` on ``training`` (see the module table).

    Checks first (:func:`check_feasible`), then fits the hyperparameters (:func:`fit_hyper`),
    then the kind's build (:mod:`gpg.kinds`); the built model is refused if any of its arrays
    is not finite.

    Args:
        name: a model name of :data:`NAMES`.
        training: the prepared data (:func:`gpg.data.prepare`).
        cfg: the model's options (:func:`resolve_config`).
        hyper: hyperparameters to use instead of fitting them.
        devices: a count or a list of JAX devices over which the kinds' per-bin precompute
            (``gps_*``, ``gpgs``, the hybrid's variance, ``gpg_pic``) is spread
            (:mod:`gpg.parallel`); None for one process, LAPACK.

    Returns:
        The model with its config, hyperparameters, fit result and timings.

    Raises:
        ValueError: as :func:`resolve_config`, :func:`check_feasible` and
            :func:`check_finite_model` raise it.
        gpg.linalg.memory.InsufficientMemory: if the build would not fit in memory.
    """
    cfg = resolve_config(name, cfg)
    check_feasible(name, cfg, training)
    arrays = training_arrays(name, training)
    timings: dict[str, float] = {}
    fit_res = None
    if hyper is None:
        hyper, fit_res, timings["hyper_s"] = fit_hyper(name, training, cfg)
    else:
        check_scaled_inputs(arrays.X, hyper)
    product = SPECS[name].kind.build(arrays, hyper, cfg, devices=devices)
    check_finite_model(name, product.model)
    model = product.model
    if not cfg.hyper.output_scales:  # one shared scale: the kernel's own amplitude
        model = model.with_output_scale(jnp.ones_like(model.output_scale))
    timings.update(product.timings)
    return Built(name, model, cfg, hyper, fit_res, timings, product.near, product.diagnostics)


@float64
def train(
    name: str,
    dataset: Dataset,
    simple: SimpleModel | None,
    cfg: Mapping[str, Any] | ModelConfig | None = None,
    *,
    noise_model: SimpleNoise | None = None,
    hyper_cache: dict | None = None,
    devices: Devices = None,
) -> tuple[Training, Built]:
    """The one path from a dataset to a built model: :func:`gpg.data.prepare`, then :func:`build`.

    The paper's comparison fits the hyperparameters once for all models on the same points:
    that is what ``hyper_cache`` is for.

    Args:
        name: a model name of :data:`NAMES`.
        dataset: the training data.
        simple: the simplified model ``M`` the residuals are taken against; None fits the raw
            outputs.
        cfg: the model's options (:func:`resolve_config`).
        noise_model: ``M_noise``, subtracted from the levels too; None for none.
        hyper_cache: a dict kept by the caller; the hyperparameters are then fitted once per
            kind of training arrays (raw samples or not, gradients or not) and hyperparameter
            config, and shared by every model that matches.
        devices: as for :func:`build`.

    Returns:
        The prepared data and the built model.
    """
    cfg = resolve_config(name, cfg)
    training = prepare(dataset, simple, noise_model)
    hyper = fit_res = None
    hyper_s = 0.0
    if hyper_cache is not None:
        spec = SPECS[name]
        key = (spec.data, json.dumps(cfg.to_dict()["hyper"], sort_keys=True))
        if key not in hyper_cache:
            check_feasible(name, cfg, training)  # before a fit that would be wasted
            hyper_cache[key] = fit_hyper(name, training, cfg)
        hyper, fit_res, hyper_s = hyper_cache[key]
    built = build(name, training, cfg, hyper=hyper, devices=devices)
    if hyper_cache is not None:
        built.hyper_fit = fit_res
        built.timings = {"hyper_s": hyper_s, **built.timings}
    return training, built
