"""The paper's method: near sets per bin with the Schur-corrected far set (GP-G-S-Schur)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from gpg.config import ModelConfig
from gpg.gp import schur
from gpg.gp.binned import pack
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Kind, Product, bins_and_near, gram_bytes
from gpg.parallel import Devices

__all__ = ["KIND", "Schur"]


@dataclass(frozen=True)
class Schur(Kind):
    """``gpgs_schur``: :func:`gpg.gp.schur.precompute` by ``route`` with the ``mean`` form, and
    the build-time check of its ``k_qf ≈ 0`` assumption (:func:`gpg.gp.schur.diagnose`)."""

    name = "schur"
    reads = ("partition", "near", "variance_dtype", "mean", "route")
    partitioned = True
    needs_gram = True

    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """Near sets per bin with the Schur-corrected far set, and the check of ``k_qf ≈ 0``.

        Args:
            arrays: the normalised training cases, all gradients observed (the Schur route
                needs the whole ``K̄``).
            hyper: the fitted hyperparameters (σ², l, ν², λ²).
            cfg: the resolved config: ``partition``, ``near``, ``variance_dtype``, ``route``
                (how the far set's Schur complement is formed) and ``mean``.
            devices: unused: the Schur precompute runs on the host.

        Returns:
            The :class:`~gpg.gp.binned.BinnedGP`, the near sets, the far-correlation
            diagnostics (:func:`gpg.gp.schur.diagnose`) and the timings.
        """
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        X, dims, t0 = arrays.X, arrays.dims, time.perf_counter()
        factors = schur.precompute(X, Ybar, hyper, dims, near, route=cfg.route, mean=cfg.mean)
        model = pack(X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype)
        diagnostics = schur.diagnose(X, part, near, hyper.lengthscale, name="gpgs_schur")
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, diagnostics, timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """Dense ``K̄``-sized buffers: three for the ``direct`` route, one and a half otherwise.

        Args:
            cfg: the resolved config (its ``route``).
            n_points: training points ``N``.
            n_grad: gradient dims ``G``.

        Returns:
            The estimate in bytes, in multiples of ``8 (N(1 + G))²``.
        """
        return gram_bytes(n_points, n_grad, 3 if cfg.route == "direct" else 1.5)


KIND = Schur()
