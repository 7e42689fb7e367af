"""Local GPs per bin, the far set dropped (the paper's GP-S and GP-G-S)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from gpg.config import ModelConfig
from gpg.gp import local
from gpg.gp.binned import pack
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Kind, Product, bin_devices, bins_and_near, near_set_bytes


@dataclass(frozen=True)
class Local(Kind):
    """``gps_1x``, ``gps_8x`` and ``gpgs``: :mod:`gpg.gp.local` packed into a
    :class:`gpg.gp.binned.BinnedGP`."""

    name = "local"
    reads = ("partition", "near", "variance_dtype", "solver.device")
    partitioned = True

    def build(self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices=None) -> Product:
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        X, dims, t0 = arrays.X, arrays.dims, time.perf_counter()
        width = max(nb.size for nb in near.near) * (1 + len(dims))
        devs = bin_devices(devices, cfg, width, f"the bins' near sets ({width} rows each)")
        factors = local.precompute(X, Ybar, hyper, dims, near, devices=devs)
        model = pack(X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype)
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, timings=timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        return near_set_bytes(cfg, n_points, n_grad)


KIND = Local()
