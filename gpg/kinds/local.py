"""Local GPs per bin, the far set dropped (the paper's GP-S and GP-G-S)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from gpg.config import ModelConfig
from gpg.gp import local
from gpg.gp.binned import pack
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Kind, Product, bin_devices, bins_and_near, near_set_bytes
from gpg.parallel import Devices

__all__ = ["KIND", "Local"]


@dataclass(frozen=True)
class Local(Kind):
    """``gps_1x``, ``gps_8x`` and ``gpgs``: :mod:`gpg.gp.local` packed into a
    :class:`gpg.gp.binned.BinnedGP`."""

    name = "local"
    reads = ("partition", "near", "variance_dtype", "solver.device")
    partitioned = True

    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """A local GP per bin on its near set, the far set dropped.

        Args:
            arrays: the normalised training arrays (every gradient at every case).
            hyper: the fitted hyperparameters, shared by all bins.
            cfg: the resolved config: ``partition``, ``near``, ``variance_dtype`` and
                ``solver.device`` (where each bin's solve runs when ``devices`` is None).
            devices: JAX devices over which the bins' factorisations are spread; None lets
                ``solver.device`` choose between the host and the default device.

        Returns:
            The :class:`~gpg.gp.binned.BinnedGP`, the near sets, and the seconds of the
            partition and of the fit.
        """
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        X, dims, t0 = arrays.X, arrays.dims, time.perf_counter()
        width = max(nb.size for nb in near.near) * (1 + len(dims))
        devs = bin_devices(devices, cfg, width, f"the bins' near sets ({width} rows each)")
        factors = local.precompute(X, Ybar, hyper, dims, near, devices=devs)
        model = pack(X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype)
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, timings=timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """The per-bin precompute's peak: a few near-set blocks, then every bin's factor.

        Args:
            cfg: the resolved config (the bins and the near-set rule set the widths).
            n_points: training points.
            n_grad: gradient dims per point.

        Returns:
            The estimate in bytes (:func:`gpg.kinds.base.near_set_bytes`).
        """
        return near_set_bytes(cfg, n_points, n_grad)


KIND = Local()
