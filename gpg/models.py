"""gpg's models under one ``predict``, built by name: the paper's six baselines and two more.

=========== ========= ====== =========== ================ ===================================
name        gradients points partitioned far set          what
=========== ========= ====== =========== ================ ===================================
gp          no        raw 8X no          —                exact GP on every raw sample
gpg         yes       1X     no          —                exact GP with gradients (GP-G)
gps_1x      no        1X     yes         dropped          local GP per bin (GP-S-1X)
gps_8x      no        raw 8X yes         dropped          local GP per bin (GP-S-8X)
gpgs        yes       1X     yes         dropped          local GP-G per bin (GP-G-S)
gpgs_schur  yes       1X     yes         Schur complement the paper's method (GP-G-S-Schur)
gpgs_hybrid yes       1X     yes         exact mean       GP-G mean, near-set variance
gpg_pic     yes       1X     yes         inducing points  PIC: exact block per bin + low rank
=========== ========= ====== =========== ================ ===================================

Options (not new names): partition ``scheme`` (slab, kdtree), bins, near ``budget``,
``points`` or ``epsilon``, ``mean`` form of ``gpgs_schur`` (exact, paper) and its precompute
``route`` (global, direct), the storage ``variance_dtype`` of the variance factors, and the
``inducing`` points of ``gpg_pic``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gpg._dtype import float64
from gpg.config import ModelConfig
from gpg.data.dataset import Dataset
from gpg.data.preprocess import Training, prepare
from gpg.gp import partition, pic, schur
from gpg.gp.binned import BinnedGP, pack, pack_points
from gpg.gp.exact import ExactGP
from gpg.gp.fit import HyperFitResult, fit_hyperparameters
from gpg.gp.gram import assemble_gram, stack_targets
from gpg.gp.hybrid import HybridGP
from gpg.gp.hyper import Hyper, gradient_noise
from gpg.gp.mean import GlobalMean, output_scale
from gpg.gp.predictor import Predictor
from gpg.linalg import dense, memory
from gpg.names import GRAD_DIMS
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise


@dataclass(frozen=True)
class Spec:
    """What a model name means: its training data, whether it is partitioned, and how its
    predictor is built (``kind``: exact, local, schur, hybrid or pic)."""

    gradients: bool
    raw: bool
    partitioned: bool
    kind: str
    title: str

    @property
    def schur(self) -> bool:
        return self.kind == "schur"


SPECS: dict[str, Spec] = {
    "gp": Spec(False, True, False, "exact", "GP"),
    "gpg": Spec(True, False, False, "exact", "GP-G"),
    "gps_1x": Spec(False, False, True, "local", "GP-S-1X"),
    "gps_8x": Spec(False, True, True, "local", "GP-S-8X"),
    "gpgs": Spec(True, False, True, "local", "GP-G-S"),
    "gpgs_schur": Spec(True, False, True, "schur", "GP-G-S-Schur"),
    "gpgs_hybrid": Spec(True, False, True, "hybrid", "GP-G-S-Hybrid"),
    "gpg_pic": Spec(True, False, True, "pic", "GP-G-PIC"),
}
NAMES = tuple(SPECS)
PAPER_NAMES = NAMES[:6]  # the paper's six baselines


def resolve_config(name: str, cfg: ModelConfig | ModelConfig | None = None) -> ModelConfig:
    """Model ``name``'s :class:`~gpg.config.ModelConfig`: the shared defaults, the model's own,
    then ``cfg``; unknown names, keys and values raise ``ValueError`` naming them (before any
    data is touched). A :class:`ModelConfig` is taken as it is."""
    if name not in SPECS:
        raise ValueError(f"unknown model {name!r}; valid: {list(NAMES)}")
    return ModelConfig.resolve(name, cfg)


def build_partition(
    X: np.ndarray, cfg: ModelConfig, Y: np.ndarray | None = None
) -> partition.Partition:
    """The partition a resolved config asks for, on training inputs ``X`` (the ``adaptive``
    scheme also reads the targets ``Y``: its bins follow their local variation)."""
    pc = cfg.partition
    opts: dict[str, Any] = {"dim": pc.dim} if pc.scheme in ("slab", "adaptive") else {}
    if pc.scheme == "adaptive":
        if Y is None:
            raise ValueError("partition.scheme=adaptive needs the training targets")
        opts["weights"] = partition.variation_weights(X, Y)
    return partition.build(X, pc.scheme, pc.n_bins(X.shape[0]), **opts)


@dataclass
class Built:
    """A built model and how it was built (timings in seconds, resolved config).

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
        return sum(self.timings.values())


def training_arrays(name: str, training: Training):
    """``(X, Y, dY, grad_dims)`` a model trains on, or a ``ValueError`` saying what is missing."""
    spec = SPECS[name]
    if spec.raw:
        if training.X_raw is None:
            raise ValueError(
                f"model {name!r} trains on the raw 8X samples, which the dataset lacks"
            )
        return training.X_raw, training.Y_raw, None, ()
    if spec.gradients:
        if training.dY is None:
            raise ValueError(f"model {name!r} needs gradients, which the dataset lacks")
        return training.X, training.Y, training.dY, GRAD_DIMS
    return training.X, training.Y, None, ()


def initial_hyper(cfg: ModelConfig, n_inputs: int, dY: np.ndarray | None) -> Hyper:
    h = cfg.hyper
    ls = np.broadcast_to(np.asarray(h.lengthscale, float), (n_inputs,)) if h.ard else h.lengthscale
    lam = gradient_noise(dY, h.grad_noise_scale) if dY is not None else 1e-6
    return Hyper(variance=h.variance, lengthscale=ls, jitter=h.jitter, grad_noise=lam)


@float64
def fit_hyper(
    name: str, training: Training, cfg: Mapping[str, Any] | ModelConfig | None = None
) -> tuple[Hyper, HyperFitResult | None, float]:
    """Hyperparameters for ``name``: fitted by marginal likelihood or the configured values,
    then the lengthscales multiplied by ``hyper.lengthscale_scale``."""
    cfg = resolve_config(name, cfg)
    X, Y, dY, dims = training_arrays(name, training)
    init = initial_hyper(cfg, X.shape[1], dY)
    h = cfg.hyper
    res, seconds = None, 0.0
    if not h.fit:
        hyper = init.validate(X.shape[1], len(dims))
    else:
        t0 = time.perf_counter()
        res = fit_hyperparameters(
            X,
            Y,
            dY,
            grad_dims=dims if dY is not None else None,
            init=init,
            ard=h.ard,
            fit_grad_noise=h.fit_grad_noise,
            fit_jitter=h.fit_jitter,
            jitter_floor=h.jitter_floor,
            jitter_init=h.jitter_init,
            subset_size=h.subset,
            seed=h.seed,
            max_steps=h.max_steps,
        )
        hyper, seconds = res.hyper, time.perf_counter() - t0
    if h.lengthscale_scale != 1.0:
        scaled = hyper.lengthscale * h.lengthscale_scale
        hyper = eqx.tree_at(lambda t: t.lengthscale, hyper, scaled)
    check_scaled_inputs(X, hyper)
    return hyper, res, seconds


def check_scaled_inputs(X: np.ndarray, hyper: Hyper) -> None:
    """The kernel divides the inputs by the lengthscales: a lengthscale so small that ``x/l``
    overflows (1e-300 on inputs in [−1, 1]) would give a model that answers NaN everywhere."""
    ls = np.asarray(hyper.lengthscale, dtype=float)
    with np.errstate(all="ignore"):
        r2 = np.sum((np.asarray(X) / ls) ** 2, axis=1)
    if not np.all(np.isfinite(r2)):
        raise ValueError(
            f"lengthscale {ls.min():.3g} is too small for inputs in [-1, 1]: the scaled "
            "distances overflow and every prediction would be NaN"
        )


def check_finite_model(name: str, model: Predictor) -> None:
    """Every array a built model holds is finite (else ``ValueError`` naming where): a fit
    never returns a model that answers NaN for finite queries."""
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
    """Peak bytes the build of ``name`` needs beyond the data, estimated from sizes alone."""
    cfg = resolve_config(name, cfg)
    spec = SPECS[name]
    rows = n_points * (1 + n_grad)
    if spec.kind in ("exact", "hybrid"):
        return int(rows * rows * 8 * 1.2)  # one K̄, factorised in place
    if spec.kind == "schur":
        return int(rows * rows * 8 * (3 if cfg.route == "direct" else 1.5))
    bins = cfg.partition.n_bins(n_points)
    per_bin = math.ceil(n_points / bins) * (1 + n_grad)
    if spec.kind == "pic":
        u = cfg.inducing.points * (1 + n_grad)
        width = per_bin + u
        # per-bin blocks and cross-covariances while training; every bin's stored factor after
        return int(8 * (3 * width * width + rows * u // bins + bins * 0.6 * width * width))
    near = cfg.near
    if near.points is not None:
        width = max(near.points, math.ceil(n_points / bins)) * (1 + n_grad)
    elif near.budget is not None and near.epsilon is None:
        width = max(math.ceil(near.budget * n_points), math.ceil(n_points / bins)) * (1 + n_grad)
    else:
        width = rows  # an ε near set can hold every point
    return int(8 * width * width * (3 + 0.6 * bins))


def check_feasible(
    name: str, cfg: Mapping[str, Any] | ModelConfig | None, training: Training
) -> None:
    """Everything that can be checked before any heavy work: the data the model needs, sizes
    against the data (bins, inducing points), and memory. Raises ``ValueError`` or
    :class:`gpg.linalg.memory.InsufficientMemory` with one clear message."""
    cfg = resolve_config(name, cfg)
    X, _, _, dims = training_arrays(name, training)
    n = X.shape[0]
    spec = SPECS[name]
    if spec.partitioned and cfg.partition.n_bins(n) > n:
        raise ValueError(
            f"model {name!r}: partition.bins={cfg.partition.n_bins(n)} exceeds the {n} "
            "training points"
        )
    if spec.kind == "pic" and cfg.inducing.points > n:
        raise ValueError(
            f"model {name!r}: inducing.points={cfg.inducing.points} is more inducing "
            f"points than the {n} training points"
        )
    need = required_bytes(name, cfg, n, len(dims))
    hint = "" if spec.kind in ("local", "pic") else " (gpgs and gpg_pic train without K̄)"
    memory.require(f"model {name!r} on {n} points{hint}", need)


@float64
def build(
    name: str,
    training: Training,
    cfg: Mapping[str, Any] | ModelConfig | None = None,
    *,
    hyper: Hyper | None = None,
    devices=None,
) -> Built:
    """Build model ``name`` on ``training`` (see the module table). ``hyper`` skips the fit.
    ``devices`` spreads the per-bin precompute of the local models (``gps_*``, ``gpgs``, the
    hybrid's variance) and of ``gpg_pic`` over JAX devices (:mod:`gpg.parallel`; None: one
    process, LAPACK)."""
    cfg = resolve_config(name, cfg)
    check_feasible(name, cfg, training)
    spec = SPECS[name]
    X, Y, dY, dims = training_arrays(name, training)
    timings: dict[str, float] = {}
    fit_res = None
    if hyper is None:
        hyper, fit_res, timings["hyper_s"] = fit_hyper(name, training, cfg)
    else:
        check_scaled_inputs(X, hyper)
    if spec.kind == "exact":
        t0 = time.perf_counter()
        model = ExactGP.fit(X, Y, dY, grad_dims=dims if dY is not None else None, hyper=hyper)
        timings["fit_s"] = time.perf_counter() - t0
        check_finite_model(name, model)
        return Built(name, _scales(model, cfg), cfg, hyper, fit_res, timings)

    dims = tuple(dims)
    t0 = time.perf_counter()
    nc = cfg.near
    part = build_partition(X, cfg, Y)
    near = None
    if spec.kind != "pic":
        near = partition.near_sets(X, part, hyper.lengthscale, **nc.rule())
    timings["partition_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    Ybar = stack_targets(Y, dY)
    diagnostics: dict[str, Any] = {}
    dtype = cfg.variance_dtype
    if spec.kind == "pic":
        model, diagnostics = _build_pic(X, Ybar, hyper, dims, part, cfg, devices)
    elif spec.kind == "hybrid":
        alpha = exact_alpha(X, Ybar, hyper, dims)
        factors = schur.precompute(X, Ybar, hyper, dims, near, route="local", devices=devices)
        scale = output_scale(np.sum(Ybar * alpha, axis=0), Ybar.shape[0])
        model = HybridGP(
            mean=GlobalMean.from_alpha(X, alpha, hyper.variance, hyper.lengthscale, dims),
            local=pack(X, factors, near, part, hyper, dims, dtype=dtype, scale=scale),
        )
    else:
        route = cfg.route if spec.schur else "local"
        factors = schur.precompute(
            X,
            Ybar,
            hyper,
            dims,
            near,
            route=route,
            mean=cfg.mean,
            devices=devices if route == "local" else None,
        )
        model = pack(X, factors, near, part, hyper, dims, dtype=dtype)
        if spec.schur:
            diagnostics = schur.diagnose(X, part, near, hyper.lengthscale, name=name)
    timings["fit_s"] = time.perf_counter() - t0
    check_finite_model(name, model)
    return Built(name, _scales(model, cfg), cfg, hyper, fit_res, timings, near, diagnostics)


@float64
def train(
    name: str,
    dataset: Dataset,
    simple: SimpleModel | None,
    cfg: Mapping[str, Any] | ModelConfig | None = None,
    *,
    noise: SimpleNoise | None = None,
    hyper_cache: dict | None = None,
    devices=None,
) -> tuple[Training, Built]:
    """The one path from a dataset to a built model: :func:`gpg.data.prepare` (residuals
    against ``simple`` and, if given, ``noise`` = ``M_noise``; normalisation), then
    :func:`build`. With ``hyper_cache`` (a dict kept
    by the caller) the hyperparameters are fitted once per training arrays (raw samples or
    not, gradients or not) and hyperparameter config, and shared by every model that matches:
    the paper's comparison fits them once for all models on the same points. ``devices`` as
    for :func:`build`."""
    cfg = resolve_config(name, cfg)
    training = prepare(dataset, simple, noise)
    hyper = fit_res = None
    hyper_s = 0.0
    if hyper_cache is not None:
        spec = SPECS[name]
        key = (spec.raw, spec.gradients, json.dumps(cfg.to_dict()["hyper"], sort_keys=True))
        if key not in hyper_cache:
            check_feasible(name, cfg, training)  # before a fit that would be wasted
            hyper_cache[key] = fit_hyper(name, training, cfg)
        hyper, fit_res, hyper_s = hyper_cache[key]
    built = build(name, training, cfg, hyper=hyper, devices=devices)
    if hyper_cache is not None:
        built.hyper_fit = fit_res
        built.timings = {"hyper_s": hyper_s, **built.timings}
    return training, built


def _scales(model: Predictor, cfg: ModelConfig) -> Predictor:
    """Per-output variance scales as built, or ones when ``hyper.output_scales`` is off."""
    if cfg.hyper.output_scales:
        return model
    ones = jnp.ones_like(model.output_scale)
    if isinstance(model, HybridGP):
        return eqx.tree_at(lambda m: m.local.output_scale, model, ones)
    return eqx.tree_at(lambda m: m.output_scale, model, ones)


def exact_alpha(X: np.ndarray, Ybar: np.ndarray, hyper: Hyper, dims: tuple[int, ...]) -> np.ndarray:
    """``α = K̄⁻¹ Ȳ`` by one in-place Cholesky factorisation of ``K̄`` (no inverse kept)."""
    r = Ybar.shape[0]
    memory.require(f"the global α over {r} rows", int(r * r * 8 * 1.1))
    buf = memory.square_buffer(r)
    chol = dense.cholesky_inplace(assemble_gram(jnp.asarray(X), hyper, dims, out=buf.array))
    alpha = dense.cho_solve(chol, Ybar)
    del chol, buf
    return alpha


def _build_pic(X, Ybar, hyper, dims, part, cfg, devices=None) -> tuple[BinnedGP, dict[str, Any]]:
    ic = cfg.inducing
    Z = pic.inducing_inputs(X, ic.points, seed=ic.seed)
    bins = np.asarray(part.lookup_batch(jnp.asarray(X)))
    blocks = [np.flatnonzero(bins == b) for b in range(part.n_bins)]
    if any(b.size == 0 for b in blocks):
        raise ValueError("a PIC bin holds no training point; use fewer bins")
    if devices is None:
        factors = pic.iter_precompute(X, Ybar, hyper, dims, blocks, Z, jitter=ic.jitter)
    else:
        factors = pic.iter_precompute_devices(
            X, Ybar, hyper, dims, blocks, Z, jitter=ic.jitter, devices=devices
        )
    points = [X[b] for b in blocks]
    model = pack_points(points, factors, part, hyper, dims, dtype=cfg.variance_dtype, shared=Z)
    info = {"inducing_points": int(Z.shape[0]), "block_points": [int(b.size) for b in blocks]}
    return model, info
