"""The paper's models under one ``predict``, built by name (DESIGN "Baselines").

========== ========== ========= =========== ====== ===========================================
name       gradients  points    partitioned Schur  what
========== ========== ========= =========== ====== ===========================================
gp         no         raw 8X    no          —      exact GP on every raw sample
gpg        yes        1X        no          —      exact GP with gradients (GP-G)
gps_1x     no         1X        yes         no     local GP per bin (GP-S-1X)
gps_8x     no         raw 8X    yes         no     local GP per bin (GP-S-8X)
gpgs       yes        1X        yes         no     local GP-G per bin (GP-G-S, no Schur)
gpgs_schur yes        1X        yes         yes    the method (GP-G-S-Schur)
========== ========== ========= =========== ====== ===========================================

Options (not new names): partition ``scheme`` (slab, kdtree), bins, near ``budget`` or
``epsilon``, ``mean`` form of ``gpgs_schur`` (exact, paper) and its precompute ``route``
(global, direct).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from gpg import kernels, partition, schur
from gpg.data.preprocess import GRAD_DIMS, Training
from gpg.gp import (
    ExactGP,
    Hyper,
    HyperFitResult,
    fit_hyperparameters,
    gradient_noise,
    stack_targets,
)
from gpg.predictor import Predictor
from gpg.tri import BlockTriangular


@dataclass(frozen=True)
class Spec:
    gradients: bool
    raw: bool
    partitioned: bool
    schur: bool
    title: str


SPECS: dict[str, Spec] = {
    "gp": Spec(False, True, False, False, "GP"),
    "gpg": Spec(True, False, False, False, "GP-G"),
    "gps_1x": Spec(False, False, True, False, "GP-S-1X"),
    "gps_8x": Spec(False, True, True, False, "GP-S-8X"),
    "gpgs": Spec(True, False, True, False, "GP-G-S"),
    "gpgs_schur": Spec(True, False, True, True, "GP-G-S-Schur"),
}
NAMES = tuple(SPECS)

DEFAULTS: dict[str, Any] = {
    "hyper": {
        "fit": True,  # maximise the marginal likelihood (else use the values below)
        "subset": 300,  # points in the likelihood fit
        "seed": 0,  # subset draw
        "max_steps": 200,  # BFGS steps
        "variance": 1.0,  # σ (initial value, or fixed)
        "lengthscale": 1.0,  # l on inputs in [-1, 1] (initial value, or fixed)
        "ard": True,  # one lengthscale per input
        "jitter": 1e-8,  # ν² on value rows
        "grad_noise_scale": 0.3,  # s in λ_i² = s·Var(∂_i Ỹ)
        "fit_grad_noise": False,  # also fit s
    },
    "partition": {"scheme": "slab", "bins": 10, "dim": 7},
    "near": {"budget": 0.125, "epsilon": None},
    "mean": "exact",
    "route": "global",
}

FAR = 1e3  # padding position: its kernel with any query in [-1, 1]^D underflows to 0
FACTOR_BANDS = 8  # row bands per variance factor (gpg.tri): 56 % of the dense bytes


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
    """Defaults overlaid with ``cfg``; unknown names and keys raise ``ValueError``."""
    if name not in SPECS:
        raise ValueError(f"unknown model {name!r}; valid: {list(NAMES)}")
    cfg = dict(cfg or {})
    cfg.pop("name", None)
    return _merge(DEFAULTS, cfg, "")


class BinnedGP(Predictor):
    """Partitioned predictor: each query is answered from its bin's near set only.

    ``Xn`` (B, P, D) near points per bin, padded to P with far-away points; ``coef`` (B, M, Rp)
    mean coefficients and ``factor`` one triangular variance factor per bin (row bands, see
    :mod:`gpg.tri`) over the bin's rows (``Rp = P(1+G)``, value rows then gradient rows),
    zero on padding. The mean computes the
    query's kernel row against its own bin only, then multiplies it by every bin's small
    coefficient block and keeps its own: under ``vmap`` that is one dense product instead of a
    per-query gather of coefficients, which the CPU serves several times faster.
    """

    partition: partition.Partition
    Xn: Float[Array, "B P D"]
    coef: Float[Array, "B M Rp"]
    factor: tuple[BlockTriangular, ...]
    variance: Float[Array, ""]
    lengthscale: Float[Array, "*L"]
    n_near: Int[Array, " B"]
    grad_dims: tuple[int, ...] = eqx.field(static=True)

    @property
    def n_inputs(self) -> int:
        return self.Xn.shape[2]

    @property
    def n_outputs(self) -> int:
        return self.coef.shape[1]

    def kernel_row(self, x: Float[Array, " D"], b: Int[Array, ""]) -> Float[Array, " Rp"]:
        """``k̄(x, X_n)`` against bin ``b``'s near set: values, then gradient rows."""
        Xb = jax.lax.dynamic_index_in_dim(self.Xn, b, keepdims=False)
        return kernels.gram(x[None], Xb, self.variance, self.lengthscale, (), self.grad_dims)[0]

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        b = self.partition.lookup(x)
        return binned_contract(self.coef, b, self.kernel_row(x, b))

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        b = self.partition.lookup(x)
        k = self.kernel_row(x, b)
        quad = binned_quadratic_form(self.factor, b, k)
        return binned_contract(self.coef, b, k), jnp.maximum(self.variance - quad, 0.0)


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
    return v @ v


@binned_quadratic_form.def_vmap
def _binned_quadratic_form_batched(axis_size, in_batched, factor, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if any(jax.tree.leaves(in_batched[0])):
        return jax.lax.map(lambda a: binned_quadratic_form(*a), (factor, bins, K)), True
    out = jnp.zeros(axis_size, dtype=K.dtype)
    for i, f in enumerate(factor):
        V = f.rmatmul(K)
        out = jnp.where(bins == i, jnp.sum(V * V, axis=1), out)
    return out, True


def pack(
    X: np.ndarray,
    factors: list[schur.BinFactors],
    near: partition.NearSets,
    part: partition.Partition,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
) -> BinnedGP:
    """Padded, stacked per-bin arrays of a :class:`BinnedGP`."""
    B, D = len(factors), X.shape[1]
    g = len(grad_dims)
    P = max(nb.size for nb in near.near)
    Rp = P * (1 + g)
    M = factors[0].coef.shape[1]
    Xn = np.full((B, P, D), FAR)
    coef = np.zeros((B, M, Rp))
    bands = []
    for b, (nb, f) in enumerate(zip(near.near, factors, strict=True)):
        p = nb.size
        Xn[b, :p] = X[nb]
        # Local row -> padded row is increasing, so a triangular factor stays triangular.
        pos = schur.near_rows(np.arange(p), P, g)
        coef[b][:, pos] = f.coef.T
        dense = np.zeros((Rp, Rp))
        dense[np.ix_(pos, pos)] = f.factor
        bands.append(BlockTriangular.from_dense(dense, lower=f.lower, n_blocks=FACTOR_BANDS))
    return BinnedGP(
        partition=part,
        Xn=jnp.asarray(Xn),
        coef=jnp.asarray(coef),
        factor=tuple(bands),
        variance=hyper.variance,
        lengthscale=hyper.lengthscale,
        n_near=jnp.asarray([nb.size for nb in near.near]),
        grad_dims=grad_dims,
    )


@dataclass
class Built:
    """A built model and how it was built (timings in seconds, resolved config)."""

    name: str
    model: Predictor
    config: dict[str, Any]
    hyper: Hyper
    hyper_fit: HyperFitResult | None
    timings: dict[str, float] = field(default_factory=dict)
    near: partition.NearSets | None = None

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
    """Hyperparameters for ``name``: fitted by marginal likelihood or the configured values."""
    cfg = resolve_config(name, cfg)
    X, Y, dY, dims = training_arrays(name, training)
    init = initial_hyper(cfg, X.shape[1], dY)
    h = cfg["hyper"]
    if not h["fit"]:
        return init.validate(X.shape[1], len(dims)), None, 0.0
    t0 = time.perf_counter()
    res = fit_hyperparameters(
        X,
        Y,
        dY,
        grad_dims=dims if dY is not None else None,
        init=init,
        ard=h["ard"],
        fit_grad_noise=h["fit_grad_noise"],
        subset_size=h["subset"],
        seed=h["seed"],
        max_steps=h["max_steps"],
    )
    return res.hyper, res, time.perf_counter() - t0


def build(
    name: str,
    training: Training,
    cfg: Mapping[str, Any] | None = None,
    *,
    hyper: Hyper | None = None,
) -> Built:
    """Build model ``name`` on ``training`` (see the module table). ``hyper`` skips the fit."""
    cfg = resolve_config(name, cfg)
    spec = SPECS[name]
    X, Y, dY, dims = training_arrays(name, training)
    timings: dict[str, float] = {}
    fit_res = None
    if hyper is None:
        hyper, fit_res, timings["hyper_s"] = fit_hyper(name, training, cfg)
    if not spec.partitioned:
        t0 = time.perf_counter()
        model = ExactGP.fit(X, Y, dY, grad_dims=dims if dY is not None else None, hyper=hyper)
        timings["fit_s"] = time.perf_counter() - t0
        return Built(name, model, cfg, hyper, fit_res, timings)

    t0 = time.perf_counter()
    pc, nc = cfg["partition"], cfg["near"]
    opts = {"dim": pc["dim"]} if pc["scheme"] == "slab" else {}
    part = partition.build(X, pc["scheme"], int(pc["bins"]), **opts)
    near = partition.near_sets(
        X,
        part,
        hyper.lengthscale,
        epsilon=nc["epsilon"],
        budget=None if nc["epsilon"] is not None else nc["budget"],
    )
    timings["partition_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    Ybar = stack_targets(Y, dY)
    route = cfg["route"] if spec.schur else "local"
    factors = schur.precompute(X, Ybar, hyper, dims, near, route=route, mean=cfg["mean"])
    model = pack(X, factors, near, part, hyper, tuple(dims))
    timings["fit_s"] = time.perf_counter() - t0
    return Built(name, model, cfg, hyper, fit_res, timings, near)
