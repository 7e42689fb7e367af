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

import copy
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from gpg import kernels, linalg, memory, partition, pic, schur
from gpg.data.preprocess import GRAD_DIMS, Training
from gpg.gp import (
    ExactGP,
    Hyper,
    HyperFitResult,
    assemble_gram,
    fit_hyperparameters,
    gradient_noise,
    stack_targets,
)
from gpg.mean import GlobalMean, output_scale
from gpg.predictor import Predictor
from gpg.tri import BlockTriangular


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

DEFAULTS: dict[str, Any] = {
    "hyper": {
        "fit": True,  # maximise the marginal likelihood (else use the values below)
        "subset": 300,  # points in the likelihood fit
        "seed": 0,  # subset draw
        "max_steps": 200,  # BFGS steps
        "variance": 1.0,  # σ (initial value, or fixed)
        "lengthscale": 1.0,  # l on inputs in [-1, 1] (initial value, or fixed)
        "ard": True,  # one lengthscale per input
        "jitter": 1e-8,  # ν² on value rows when it is not fitted
        "fit_jitter": True,  # fit ν² jointly with σ and l (needs fit)
        "jitter_init": 1e-2,  # initial ν²/σ of that fit
        "jitter_floor": 1e-6,  # lower bound of the fitted ν²/σ
        "grad_noise_scale": 0.3,  # s in λ_i² = s·Var(∂_i Ỹ)
        "fit_grad_noise": False,  # also fit s
        "lengthscale_scale": 1.0,  # multiplies the fitted (or given) lengthscales
        "output_scales": True,  # per-output ML variance scale (closed form, from α)
    },
    "partition": {"scheme": "slab", "bins": 10, "points_per_bin": None, "dim": 7},
    "near": {"budget": 0.125, "epsilon": None, "points": None},
    "variance_dtype": "float64",  # dtype of the stored variance factors (float32 halves bytes)
    "mean": "exact",
    "route": "global",
    "inducing": {"points": 250, "seed": 0, "jitter": 1e-6},
}

# Where a model's own defaults differ from DEFAULTS (conf/model/<name>.yaml says the same).
# The hybrid's partition serves its variance only: bins of about 150 points and near sets of
# 160 points, whatever N, keep the per-query bytes fixed (0.7 ms at data=paper, README); the
# factors of both are stored in float32, which changed no NLPD or coverage digit at
# data=default and data=paper (README Measurements).
MODEL_DEFAULTS: dict[str, dict[str, Any]] = {
    "gpgs_hybrid": {
        "partition": {"scheme": "kdtree", "points_per_bin": 150},
        "near": {"budget": None, "points": 160},
        "variance_dtype": "float32",
    },
    "gpg_pic": {"variance_dtype": "float32"},
}

FAR = 1e3  # padding position: its kernel with any query in [-1, 1]^D underflows to 0
FACTOR_BANDS = 8  # row bands per variance factor (gpg.tri): 56 % of the dense bytes
DTYPES = ("float64", "float32")


def _merge(base: dict, over: Mapping | None, where: str) -> dict:
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if k not in base:
            raise ValueError(f"unknown key {where}{k!r}; valid: {sorted(base)}")
        if isinstance(base[k], dict):
            if not isinstance(v, Mapping):
                raise ValueError(f"{where}{k} must be a mapping, got {v!r}")
            out[k] = _merge(base[k], v, f"{where}{k}.")
        else:
            out[k] = v
    return out


def resolve_config(name: str, cfg: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Defaults overlaid with ``cfg``, checked; unknown names, keys and values raise
    ``ValueError`` naming them (before any data is touched)."""
    if name not in SPECS:
        raise ValueError(f"unknown model {name!r}; valid: {list(NAMES)}")
    cfg = dict(cfg or {})
    cfg.pop("name", None)
    base = _merge(DEFAULTS, MODEL_DEFAULTS.get(name), "")
    out = _merge(base, cfg, "")
    _check_values(name, out)
    return out


def n_bins(cfg: Mapping[str, Any], n_points: int) -> int:
    """The number of bins of a resolved config for ``n_points`` training points:
    ``partition.points_per_bin`` when set (about that many points per bin), else ``bins``."""
    pc = cfg["partition"]
    if pc["points_per_bin"] is not None:
        return int(min(max(1, round(n_points / pc["points_per_bin"])), n_points))
    return int(pc["bins"])


def build_partition(X: np.ndarray, cfg: Mapping[str, Any]) -> partition.Partition:
    """The partition a resolved config asks for, on training inputs ``X``."""
    pc = cfg["partition"]
    opts = {"dim": pc["dim"]} if pc["scheme"] == "slab" else {}
    return partition.build(X, pc["scheme"], n_bins(cfg, X.shape[0]), **opts)


def _check_values(name: str, cfg: dict[str, Any]) -> None:
    near, ind = cfg["near"], cfg["inducing"]
    if SPECS[name].partitioned and all(near[k] is None for k in ("epsilon", "budget", "points")):
        raise ValueError(f"model {name!r} needs one of near.epsilon, near.points, near.budget")
    pts = near["points"]
    if pts is not None and (isinstance(pts, bool) or not isinstance(pts, int) or pts < 1):
        raise ValueError(f"near.points must be a positive integer, got {pts!r}")
    for key in ("bins", "points_per_bin"):
        v = cfg["partition"][key]
        if v is None and key == "points_per_bin":
            continue
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"partition.{key} must be a positive integer, got {v!r}")
    if cfg["variance_dtype"] not in DTYPES:
        raise ValueError(
            f"variance_dtype must be one of {list(DTYPES)}, got {cfg['variance_dtype']!r}"
        )
    u = ind["points"]
    if SPECS[name].kind == "pic" and (isinstance(u, bool) or not isinstance(u, int) or u < 1):
        raise ValueError(f"inducing.points must be a positive integer, got {u!r}")
    if not cfg["hyper"]["lengthscale_scale"] > 0:
        raise ValueError(
            f"hyper.lengthscale_scale must be > 0, got {cfg['hyper']['lengthscale_scale']!r}"
        )
    schur.check_options(cfg["mean"], cfg["route"])


class BinnedGP(Predictor):
    """Partitioned predictor: each query is answered from its bin's near set only.

    ``Xn`` (B, P, D) near points per bin, padded to P with far-away points; ``coef`` (B, M, Rp)
    mean coefficients and ``factor`` one triangular variance factor per bin (row bands, see
    :mod:`gpg.tri`) over the bin's rows (``Rp = P(1+G)``, value rows then gradient rows),
    zero on padding; ``jitter`` the value-noise variance ``ν²`` of an observation. The mean
    computes the query's kernel row against its own bin only, then multiplies it by every bin's
    small coefficient block and keeps its own: under ``vmap`` that is one dense product instead
    of a per-query gather of coefficients, which the CPU serves several times faster.

    The "near set" of a bin is whatever the bin's predictor conditions on: the near training
    points (``gps_*``, ``gpgs``, ``gpgs_schur``, the hybrid's variance), or, for ``gpg_pic``,
    the ``shared`` inducing inputs (U, D), whose rows come first in every bin, followed by the
    bin's own points.
    """

    partition: partition.Partition
    shared: Float[Array, "U D"] | None
    Xn: Float[Array, "B P D"]
    coef: Float[Array, "B M Rp"]
    factor: tuple[BlockTriangular, ...]
    variance: Float[Array, ""]
    lengthscale: Float[Array, "*L"]
    jitter: Float[Array, ""]
    output_scale: Float[Array, " M"]
    n_near: Int[Array, " B"]
    grad_dims: tuple[int, ...] = eqx.field(static=True)

    @property
    def n_inputs(self) -> int:
        return self.Xn.shape[2]

    @property
    def n_outputs(self) -> int:
        return self.coef.shape[1]

    @property
    def noise(self) -> Float[Array, ""]:
        return self.jitter

    def kernel_row(self, x: Float[Array, " D"], b: Int[Array, ""]) -> Float[Array, " Rp"]:
        """``k̄(x, X_n)`` against bin ``b``'s near set: values, then gradient rows."""
        Xb = jax.lax.dynamic_index_in_dim(self.Xn, b, keepdims=False)
        row = kernels.query_rows(x[None], Xb, self.variance, self.lengthscale, self.grad_dims)[0]
        if self.shared is None:
            return row
        k_u = kernels.query_rows(
            x[None], self.shared, self.variance, self.lengthscale, self.grad_dims
        )[0]
        return jnp.concatenate([k_u, row])

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        b = self.partition.lookup(x)
        return binned_contract(self.coef, b, self.kernel_row(x, b))

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        b = self.partition.lookup(x)
        k = self.kernel_row(x, b)
        quad = binned_quadratic_form(self.factor, b, k)
        return binned_contract(self.coef, b, k), self.variance - quad

    def mean_view(self) -> BinnedGP:
        """Without the variance factors (the mean reads the coefficients only)."""
        return eqx.tree_at(lambda m: m.factor, self, ())

    def variance_one(self, x: Float[Array, " D"]) -> Float[Array, ""]:
        """Latent variance alone (unclamped): ``σ − ‖F_b k̄_qn‖²``."""
        b = self.partition.lookup(x)
        return self.variance - binned_quadratic_form(self.factor, b, self.kernel_row(x, b))


# One query reads one bin's arrays; a batch reads every bin's arrays once. JAX would turn the
# one-query code into a per-query gather (coefficients) or a select with every bin's factor
# broadcast to the batch (variance), so both get a batch rule of their own (custom_vmap):
# one dense product per bin for all queries, each query keeping its own bin's result.
# Forward-mode differentiation works through them; reverse mode does not (custom_vmap).


def _batched_args(axis_size, in_batched, b, k):
    bins = b if in_batched[1] else jnp.broadcast_to(b, (axis_size,))
    K = k if in_batched[2] else jnp.broadcast_to(k, (axis_size,) + k.shape)
    return bins, K


@jax.custom_batching.custom_vmap
def binned_contract(
    coef: Float[Array, "B M R"], b: Int[Array, ""], k: Float[Array, " R"]
) -> Float[Array, " M"]:
    """``C_b k``: one bin's mean coefficients applied to a kernel row."""
    return jax.lax.dynamic_index_in_dim(coef, b, keepdims=False) @ k


@binned_contract.def_vmap
def _binned_contract_batched(axis_size, in_batched, coef, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if in_batched[0]:  # a batch of models: one pair at a time
        return jax.lax.map(lambda a: binned_contract(*a), (coef, bins, K)), True
    every = jnp.einsum("qr,bmr->qbm", K, coef)  # all bins for all queries: one product
    return jnp.take_along_axis(every, bins[:, None, None], axis=1)[:, 0], True


@jax.custom_batching.custom_vmap
def binned_quadratic_form(
    factor: tuple[BlockTriangular, ...], b: Int[Array, ""], k: Float[Array, " R"]
) -> Float[Array, ""]:
    """``‖F_b k‖²`` with bin ``b``'s factor: a ``lax.switch`` reads that bin's bands only."""
    branches = [lambda kk, f=f: f.matvec(kk) for f in factor]
    v = jax.lax.switch(b, branches, k)
    return (v @ v).astype(k.dtype)


@binned_quadratic_form.def_vmap
def _binned_quadratic_form_batched(axis_size, in_batched, factor, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if any(jax.tree.leaves(in_batched[0])):
        return jax.lax.map(lambda a: binned_quadratic_form(*a), (factor, bins, K)), True
    out = jnp.zeros(axis_size, dtype=K.dtype)
    for i, f in enumerate(factor):
        V = f.rmatmul(K)
        out = jnp.where(bins == i, jnp.sum(V * V, axis=1).astype(K.dtype), out)
    return out, True


def pack_points(
    points: Sequence[np.ndarray],
    factors: Iterable[schur.BinFactors],
    part: partition.Partition,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    dtype: str = "float64",
    shared: np.ndarray | None = None,
    scale: np.ndarray | None = None,
) -> BinnedGP:
    """Padded, stacked per-bin arrays of a :class:`BinnedGP`: bin ``b`` conditions on the
    points ``points[b]`` (p_b, D) through ``factors[b]`` (rows dimension-major over them),
    after the rows of the ``shared`` points if any (PIC's inducing inputs). ``dtype`` is the
    storage type of the variance factors. ``scale`` is the per-output variance scale; by
    default it is pooled from the bins' own fits (ones where a route does not report them).
    ``factors`` may be a generator: each bin's factor is stored in bands before the next one
    is drawn, so the dense factors are never all held at once."""
    B, D = len(points), points[0].shape[1]
    g = len(grad_dims)
    P = max(p.shape[0] for p in points)
    up = 0 if shared is None else shared.shape[0] * (1 + g)
    Rp = up + P * (1 + g)
    Xn = np.full((B, P, D), FAR)
    coefs, bands, ytys, n_rows = [], [], [], 0
    for b, (pts, f) in enumerate(zip(points, factors, strict=True)):
        p = pts.shape[0]
        Xn[b, :p] = pts
        # Local row -> padded row is increasing, so a triangular factor stays triangular.
        pos = np.concatenate([np.arange(up), up + schur.near_rows(np.arange(p), P, g)])
        coef = np.zeros((f.coef.shape[1], Rp))
        coef[:, pos] = f.coef.T
        coefs.append(coef)
        if p == P:  # no padding: the factor as it is
            dense = np.asarray(f.factor, dtype=dtype)
        else:
            dense = np.zeros((Rp, Rp), dtype=dtype)
            dense[np.ix_(pos, pos)] = f.factor
        bands.append(
            BlockTriangular.from_dense(
                dense, lower=f.lower, n_blocks=FACTOR_BANDS, dense_rows=f.dense_rows
            )
        )
        ytys.append(f.yty)
        n_rows += f.n_rows
        del dense, f
    if scale is None:
        if all(y is not None for y in ytys):
            scale = output_scale(np.sum(ytys, axis=0), n_rows)
        else:
            scale = np.ones(coefs[0].shape[0])
    return BinnedGP(
        partition=part,
        shared=None if shared is None else jnp.asarray(shared),
        Xn=jnp.asarray(Xn),
        coef=jnp.asarray(np.stack(coefs)),
        factor=tuple(bands),
        variance=hyper.variance,
        lengthscale=hyper.lengthscale,
        jitter=hyper.jitter,
        output_scale=jnp.asarray(scale, dtype=float),
        n_near=jnp.asarray([p.shape[0] for p in points]),
        grad_dims=grad_dims,
    )


def pack(
    X: np.ndarray,
    factors: list[schur.BinFactors],
    near: partition.NearSets,
    part: partition.Partition,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    dtype: str = "float64",
    scale: np.ndarray | None = None,
) -> BinnedGP:
    """:func:`pack_points` for near sets of training points ``X[near.near[b]]``."""
    points = [X[nb] for nb in near.near]
    return pack_points(points, factors, part, hyper, grad_dims, dtype=dtype, scale=scale)


class HybridGP(Predictor):
    """GP-G-S-Hybrid: the exact GP-G mean from the global ``α`` (:mod:`gpg.mean`), and the
    variance of the query's bin's near set, ``σ − k_qnᵀ K̄_nn⁻¹ k_qn``.

    Conditioning on a subset of the observations never lowers the posterior variance, so the
    near-set variance is an upper bound on the exact GP-G variance at every query: the
    hybrid has exactly GP-G's accuracy, is continuous in its mean, and is conservative, never
    overconfident, in its uncertainty relative to GP-G.
    """

    mean: GlobalMean
    local: BinnedGP

    @property
    def n_inputs(self) -> int:
        return self.local.n_inputs

    @property
    def n_outputs(self) -> int:
        return self.mean.n_outputs

    @property
    def noise(self) -> Float[Array, ""]:
        return self.local.jitter

    @property
    def output_scale(self) -> Float[Array, " M"]:
        return self.local.output_scale

    @property
    def partition(self) -> partition.Partition:
        return self.local.partition

    @property
    def n_near(self) -> Int[Array, " B"]:
        return self.local.n_near

    @property
    def variance(self) -> Float[Array, ""]:
        return self.local.variance

    @property
    def lengthscale(self) -> Float[Array, "*L"]:
        return self.local.lengthscale

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        return self.mean(x)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        return self.mean(x), self.local.variance_one(x)

    def mean_view(self) -> HybridGP:
        """The global mean with the near sets' arrays dropped (the mean does not read them)."""
        return HybridGP(mean=self.mean, local=self.local.mean_view())


@dataclass
class Built:
    """A built model and how it was built (timings in seconds, resolved config).

    ``diagnostics`` holds what was measured at build time: for ``gpgs_schur`` the far-set
    correlations that its ``k_qf ≈ 0`` assumption needs small (:func:`schur.far_correlation`),
    for ``gpg_pic`` the inducing-point count.
    """

    name: str
    model: Predictor
    config: dict[str, Any]
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


def initial_hyper(cfg: Mapping[str, Any], n_inputs: int, dY: np.ndarray | None) -> Hyper:
    h = cfg["hyper"]
    ls = (
        np.broadcast_to(np.asarray(h["lengthscale"], float), (n_inputs,))
        if h["ard"]
        else h["lengthscale"]
    )
    lam = gradient_noise(dY, h["grad_noise_scale"]) if dY is not None else 1e-6
    return Hyper(variance=h["variance"], lengthscale=ls, jitter=h["jitter"], grad_noise=lam)


def fit_hyper(
    name: str, training: Training, cfg: Mapping[str, Any]
) -> tuple[Hyper, HyperFitResult | None, float]:
    """Hyperparameters for ``name``: fitted by marginal likelihood or the configured values,
    then the lengthscales multiplied by ``hyper.lengthscale_scale``."""
    cfg = resolve_config(name, cfg)
    X, Y, dY, dims = training_arrays(name, training)
    init = initial_hyper(cfg, X.shape[1], dY)
    h = cfg["hyper"]
    res, seconds = None, 0.0
    if not h["fit"]:
        hyper = init.validate(X.shape[1], len(dims))
    else:
        t0 = time.perf_counter()
        res = fit_hyperparameters(
            X,
            Y,
            dY,
            grad_dims=dims if dY is not None else None,
            init=init,
            ard=h["ard"],
            fit_grad_noise=h["fit_grad_noise"],
            fit_jitter=h["fit_jitter"],
            jitter_floor=h["jitter_floor"],
            jitter_init=h["jitter_init"],
            subset_size=h["subset"],
            seed=h["seed"],
            max_steps=h["max_steps"],
        )
        hyper, seconds = res.hyper, time.perf_counter() - t0
    if h["lengthscale_scale"] != 1.0:
        scaled = hyper.lengthscale * h["lengthscale_scale"]
        hyper = eqx.tree_at(lambda t: t.lengthscale, hyper, scaled)
    return hyper, res, seconds


def required_bytes(name: str, cfg: Mapping[str, Any], n_points: int, n_grad: int) -> int:
    """Peak bytes the build of ``name`` needs beyond the data, estimated from sizes alone."""
    spec = SPECS[name]
    rows = n_points * (1 + n_grad)
    if spec.kind in ("exact", "hybrid"):
        return int(rows * rows * 8 * 1.2)  # one K̄, factorised in place
    if spec.kind == "schur":
        return int(rows * rows * 8 * (3 if cfg["route"] == "direct" else 1.5))
    bins = n_bins(cfg, n_points)
    per_bin = math.ceil(n_points / bins) * (1 + n_grad)
    if spec.kind == "pic":
        u = cfg["inducing"]["points"] * (1 + n_grad)
        width = per_bin + u
        # per-bin blocks and cross-covariances while training; every bin's stored factor after
        return int(8 * (3 * width * width + rows * u // bins + bins * 0.6 * width * width))
    near = cfg["near"]
    if near["points"] is not None:
        width = max(near["points"], math.ceil(n_points / bins)) * (1 + n_grad)
    elif near["budget"] is not None and near["epsilon"] is None:
        width = max(math.ceil(near["budget"] * n_points), math.ceil(n_points / bins)) * (1 + n_grad)
    else:
        width = rows  # an ε near set can hold every point
    return int(8 * width * width * (3 + 0.6 * bins))


def check_feasible(name: str, cfg: Mapping[str, Any], training: Training) -> None:
    """Everything that can be checked before any heavy work: the data the model needs, sizes
    against the data (bins, inducing points), and memory. Raises ``ValueError`` or
    :class:`gpg.memory.InsufficientMemory` with one clear message."""
    cfg = resolve_config(name, cfg)
    X, _, _, dims = training_arrays(name, training)
    n = X.shape[0]
    spec = SPECS[name]
    if spec.partitioned and n_bins(cfg, n) > n:
        raise ValueError(
            f"model {name!r}: partition.bins={n_bins(cfg, n)} exceeds the {n} training points"
        )
    if spec.kind == "pic" and cfg["inducing"]["points"] > n:
        raise ValueError(
            f"model {name!r}: inducing.points={cfg['inducing']['points']} is more inducing "
            f"points than the {n} training points"
        )
    need = required_bytes(name, cfg, n, len(dims))
    hint = "" if spec.kind in ("local", "pic") else " (gpgs and gpg_pic train without K̄)"
    memory.require(f"model {name!r} on {n} points{hint}", need)


def build(
    name: str,
    training: Training,
    cfg: Mapping[str, Any] | None = None,
    *,
    hyper: Hyper | None = None,
) -> Built:
    """Build model ``name`` on ``training`` (see the module table). ``hyper`` skips the fit."""
    cfg = resolve_config(name, cfg)
    check_feasible(name, cfg, training)
    spec = SPECS[name]
    X, Y, dY, dims = training_arrays(name, training)
    timings: dict[str, float] = {}
    fit_res = None
    if hyper is None:
        hyper, fit_res, timings["hyper_s"] = fit_hyper(name, training, cfg)
    if spec.kind == "exact":
        t0 = time.perf_counter()
        model = ExactGP.fit(X, Y, dY, grad_dims=dims if dY is not None else None, hyper=hyper)
        timings["fit_s"] = time.perf_counter() - t0
        return Built(name, _scales(model, cfg), cfg, hyper, fit_res, timings)

    dims = tuple(dims)
    t0 = time.perf_counter()
    nc = cfg["near"]
    part = build_partition(X, cfg)
    near = None
    if spec.kind != "pic":
        near = partition.near_sets(X, part, hyper.lengthscale, **_near_rule(nc))
    timings["partition_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    Ybar = stack_targets(Y, dY)
    diagnostics: dict[str, Any] = {}
    dtype = cfg["variance_dtype"]
    if spec.kind == "pic":
        model, diagnostics = _build_pic(X, Ybar, hyper, dims, part, cfg)
    elif spec.kind == "hybrid":
        alpha = exact_alpha(X, Ybar, hyper, dims)
        factors = schur.precompute(X, Ybar, hyper, dims, near, route="local")
        scale = output_scale(np.sum(Ybar * alpha, axis=0), Ybar.shape[0])
        model = HybridGP(
            mean=GlobalMean.from_alpha(X, alpha, hyper.variance, hyper.lengthscale, dims),
            local=pack(X, factors, near, part, hyper, dims, dtype=dtype, scale=scale),
        )
    else:
        route = cfg["route"] if spec.schur else "local"
        factors = schur.precompute(X, Ybar, hyper, dims, near, route=route, mean=cfg["mean"])
        model = pack(X, factors, near, part, hyper, dims, dtype=dtype)
        if spec.schur:
            diagnostics = schur.diagnose(X, part, near, hyper.lengthscale, name=name)
    timings["fit_s"] = time.perf_counter() - t0
    return Built(name, _scales(model, cfg), cfg, hyper, fit_res, timings, near, diagnostics)


def _scales(model: Predictor, cfg: Mapping[str, Any]) -> Predictor:
    """Per-output variance scales as built, or ones when ``hyper.output_scales`` is off."""
    if cfg["hyper"]["output_scales"]:
        return model
    ones = jnp.ones_like(model.output_scale)
    if isinstance(model, HybridGP):
        return eqx.tree_at(lambda m: m.local.output_scale, model, ones)
    return eqx.tree_at(lambda m: m.output_scale, model, ones)


def _near_rule(nc: Mapping[str, Any]) -> dict[str, Any]:
    """The near-set rule of a config: ``epsilon`` if given, else ``points``, else ``budget``."""
    if nc["epsilon"] is not None:
        return {"epsilon": nc["epsilon"]}
    if nc["points"] is not None:
        return {"points": nc["points"]}
    return {"budget": nc["budget"]}


def exact_alpha(X: np.ndarray, Ybar: np.ndarray, hyper: Hyper, dims: tuple[int, ...]) -> np.ndarray:
    """``α = K̄⁻¹ Ȳ`` by one in-place Cholesky factorisation of ``K̄`` (no inverse kept)."""
    r = Ybar.shape[0]
    memory.require(f"the global α over {r} rows", int(r * r * 8 * 1.1))
    buf = memory.square_buffer(r)
    chol = linalg.cholesky_inplace(assemble_gram(jnp.asarray(X), hyper, dims, out=buf.array))
    alpha = linalg.cho_solve(chol, Ybar)
    del chol, buf
    return alpha


def _build_pic(X, Ybar, hyper, dims, part, cfg) -> tuple[BinnedGP, dict[str, Any]]:
    ic = cfg["inducing"]
    Z = pic.inducing_inputs(X, ic["points"], seed=ic["seed"])
    bins = np.asarray(part.lookup_batch(jnp.asarray(X)))
    blocks = [np.flatnonzero(bins == b) for b in range(part.n_bins)]
    if any(b.size == 0 for b in blocks):
        raise ValueError("a PIC bin holds no training point; use fewer bins")
    factors = pic.iter_precompute(X, Ybar, hyper, dims, blocks, Z, jitter=ic["jitter"])
    points = [X[b] for b in blocks]
    model = pack_points(points, factors, part, hyper, dims, dtype=cfg["variance_dtype"], shared=Z)
    info = {"inducing_points": int(Z.shape[0]), "block_points": [int(b.size) for b in blocks]}
    return model, info
