"""GP-G's exact mean from the global ``α`` with a near-set variance (GP-G-S-Hybrid)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from gpg.config import ModelConfig
from gpg.gp import local
from gpg.gp.binned import pack
from gpg.gp.gram import assemble_gram
from gpg.gp.hybrid import HybridGP
from gpg.gp.hyper import Hyper
from gpg.gp.mean import GlobalMean, output_scale
from gpg.kinds.base import Arrays, Kind, Product, bins_and_near, gram_bytes, near_set_bytes
from gpg.linalg import dense, memory


@dataclass(frozen=True)
class Hybrid(Kind):
    """``gpgs_hybrid``: :class:`gpg.gp.hybrid.HybridGP`, the mean from one factorisation of
    ``K̄``, the variance from :mod:`gpg.gp.local` on the bins' near sets."""

    name = "hybrid"
    reads = ("partition", "near", "variance_dtype")
    partitioned = True
    needs_gram = True

    def build(self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices=None) -> Product:
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        X, dims, t0 = arrays.X, arrays.dims, time.perf_counter()
        alpha = exact_alpha(X, Ybar, hyper, dims)
        factors = local.precompute(X, Ybar, hyper, dims, near, devices=devices)
        scale = output_scale(np.sum(Ybar * alpha, axis=0), Ybar.shape[0])
        model = HybridGP(
            mean=GlobalMean.from_alpha(X, alpha, hyper.variance, hyper.lengthscale, dims),
            local=pack(X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype, scale=scale),
        )
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, timings=timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        return max(gram_bytes(n_points, n_grad), near_set_bytes(cfg, n_points, n_grad))


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
