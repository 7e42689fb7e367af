"""GP-G's exact mean from the global ``α`` with a near-set variance (GP-G-S-Hybrid)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import jax.numpy as jnp
import numpy as np

from gpg.config import ModelConfig
from gpg.gp import cg, local, pic
from gpg.gp.binned import pack
from gpg.gp.gram import assemble_gram
from gpg.gp.hybrid import HybridGP
from gpg.gp.hyper import Hyper
from gpg.gp.matfree import gram_matvec, gram_matvec_devices
from gpg.gp.mean import GlobalMean, output_scale
from gpg.kinds.base import Arrays, Kind, Product, bins_and_near, gram_bytes, near_set_bytes
from gpg.linalg import dense, memory


@dataclass(frozen=True)
class Hybrid(Kind):
    """``gpgs_hybrid``: :class:`gpg.gp.hybrid.HybridGP`, the mean from one factorisation of
    ``K̄``, the variance from :mod:`gpg.gp.local` on the bins' near sets."""

    name = "hybrid"
    reads = ("partition", "near", "variance_dtype", "solver")
    partitioned = True
    needs_gram = True  # by default; solver.method cg trains without K̄

    def build(self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices=None) -> Product:
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        X, dims, t0 = arrays.X, arrays.dims, time.perf_counter()
        diagnostics: dict = {}
        if solver_method(cfg, arrays.X.shape[0], len(dims)) == "cg":
            alpha, diagnostics = cg_alpha(X, Ybar, hyper, dims, cfg.solver, devices)
        else:
            alpha = exact_alpha(X, Ybar, hyper, dims)
        factors = local.precompute(X, Ybar, hyper, dims, near, devices=devices)
        scale = output_scale(np.sum(Ybar * alpha, axis=0), Ybar.shape[0])
        model = HybridGP(
            mean=GlobalMean.from_alpha(X, alpha, hyper.variance, hyper.lengthscale, dims),
            local=pack(X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype, scale=scale),
        )
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, diagnostics, timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        if solver_method(cfg, n_points, n_grad) == "cg":
            mean = cg_bytes(cfg, n_points, n_grad, 9)  # the nine outputs of gpg's data
        else:
            mean = gram_bytes(n_points, n_grad)
        return max(mean, near_set_bytes(cfg, n_points, n_grad))


def solver_method(cfg: ModelConfig, n_points: int, n_grad: int) -> str:
    """``cholesky`` or ``cg``: ``solver.method``, with ``auto`` resolved by whether a dense
    ``K̄`` fits in the memory available now."""
    method = cfg.solver.method
    if method == "auto":
        fits = gram_bytes(n_points, n_grad) <= 0.9 * memory.available_bytes()
        method = "cholesky" if fits else "cg"
    return method


def cg_bytes(cfg: ModelConfig, n_points: int, n_grad: int, n_outputs: int) -> int:
    """Peak bytes of :func:`cg_alpha`: the Nyström factor ``V`` and ``K̄_xu`` while it is
    made, the product's columns and one tile of ``K``, and a few CG vectors."""
    rows = n_points * (1 + n_grad)
    u = min(cfg.solver.points, n_points) * (1 + n_grad)
    columns = n_points * (n_grad + 1) * (n_grad + 2) * n_outputs
    return int(
        8
        * (
            2.2 * rows * u
            + u * u * 3
            + columns * 2
            + cfg.solver.tile * n_points * 3
            + 8 * rows * n_outputs
        )
    )


def cg_alpha(
    X, Ybar, hyper: Hyper, dims: tuple[int, ...], sc, devices=None
) -> tuple[np.ndarray, dict]:
    """``α = K̄⁻¹ Ȳ`` by preconditioned CG (:mod:`gpg.gp.cg`), and how the solve went;
    ``devices`` spreads each product's row tiles over JAX devices (:mod:`gpg.parallel`)."""
    t0 = time.perf_counter()
    Xj = jnp.asarray(X)
    Z = pic.inducing_inputs(X, min(sc.points, X.shape[0]), seed=sc.seed)
    precond = cg.Nystrom.create(Xj, hyper, dims, jnp.asarray(Z))
    setup = time.perf_counter() - t0
    if devices is None:
        matvec = partial(gram_matvec, Xj, hyper, dims, tile=sc.tile)
    else:
        matvec = partial(gram_matvec_devices, Xj, hyper, dims, devices=devices, tile=sc.tile)
    alpha, info = cg.solve(matvec, jnp.asarray(Ybar), precond, tol=sc.tol, max_iter=sc.max_iter)
    return np.asarray(alpha), {
        "solver": "cg",
        "cg_iterations": info.iterations,
        "cg_residual": info.residual.tolist(),
        "cg_setup_s": setup,
        "cg_solve_s": info.solve_s,
    }


def exact_alpha(X: np.ndarray, Ybar: np.ndarray, hyper: Hyper, dims: tuple[int, ...]) -> np.ndarray:
    """``α = K̄⁻¹ Ȳ`` by one in-place Cholesky factorisation of ``K̄`` (no inverse kept)."""
    r = Ybar.shape[0]
    memory.require(f"the global α over {r} rows", int(r * r * 8 * 1.1))
    buf = memory.square_buffer(r)
    chol = dense.cholesky_inplace(assemble_gram(jnp.asarray(X), hyper, dims, out=buf.array))
    alpha = dense.cho_solve(chol, Ybar)
    del chol, buf
    return alpha


KIND = Hybrid()
