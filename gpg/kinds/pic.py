"""PIC with gradient inducing inputs: an exact block per bin plus a shared low-rank far field."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from gpg.config import ModelConfig
from gpg.gp import pic
from gpg.gp.binned import pack_points
from gpg.gp.gram import stack_targets
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Kind, Product, bin_devices
from gpg.parallel import Devices

__all__ = ["KIND", "Pic"]


@dataclass(frozen=True)
class Pic(Kind):
    """``gpg_pic``: :mod:`gpg.gp.pic`, trained bin by bin without ever forming ``K̄``."""

    name = "pic"
    reads = ("partition", "inducing", "variance_dtype", "solver.device")
    partitioned = True

    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """PIC bin by bin: each bin's exact block plus the shared inducing rows.

        Args:
            arrays: the normalised training arrays (every gradient at every case).
            hyper: the fitted hyperparameters.
            cfg: the resolved config: ``partition``, ``inducing`` (points, seed, jitter),
                ``variance_dtype`` and ``solver.device``.
            devices: JAX devices over which the bins' blocks are spread; None lets
                ``solver.device`` choose.

        Returns:
            The :class:`~gpg.gp.binned.BinnedGP`, the inducing and block sizes, and the
            timings (no near sets).

        Raises:
            ValueError: if a bin holds no training point.
        """
        t0 = time.perf_counter()
        X, dims = arrays.X, arrays.dims
        part = arrays.bins(cfg)
        timings = {"partition_s": time.perf_counter() - t0}
        t0 = time.perf_counter()
        ic = cfg.inducing
        Z = pic.inducing_inputs(X, ic.points, seed=ic.seed)
        bins = np.asarray(part.lookup_batch(X))
        blocks = [np.flatnonzero(bins == b) for b in range(part.n_bins)]
        if any(b.size == 0 for b in blocks):
            raise ValueError("a PIC bin holds no training point; use fewer bins")
        Ybar = stack_targets(arrays.Y, arrays.dY)
        width = (max(b.size for b in blocks) + Z.shape[0]) * (1 + len(dims))
        devices = bin_devices(devices, cfg, width, f"PIC's blocks ({width} rows each)")
        if devices is None:
            factors = pic.iter_precompute(X, Ybar, hyper, dims, blocks, Z, jitter=ic.jitter)
        else:
            factors = pic.iter_precompute_devices(
                X, Ybar, hyper, dims, blocks, Z, jitter=ic.jitter, devices=devices
            )
        points = [X[b] for b in blocks]
        model = pack_points(points, factors, part, hyper, dims, dtype=cfg.variance_dtype, shared=Z)
        info = {"inducing_points": int(Z.shape[0]), "block_points": [int(b.size) for b in blocks]}
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, None, info, timings)

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """Peak bytes of PIC's training: a bin's blocks and cross-covariances, then the factors.

        Args:
            cfg: the resolved config (bins and inducing points set the block width).
            n_points: training points.
            n_grad: gradient dims per point.

        Returns:
            The estimate in bytes.
        """
        bins = cfg.partition.n_bins(n_points)
        per_bin = -(-n_points // bins) * (1 + n_grad)
        u = cfg.inducing.points * (1 + n_grad)
        width = per_bin + u
        rows = n_points * (1 + n_grad)
        # per-bin blocks and cross-covariances while training; every bin's stored factor after
        return int(8 * (3 * width * width + rows * u // bins + bins * 0.6 * width * width))

    def check(self, model: str, cfg: ModelConfig, n_points: int) -> None:
        """The partitioned kinds' check, and no more inducing points than training points.

        Args:
            model: the model name, for the message.
            cfg: the resolved config.
            n_points: training points.

        Raises:
            ValueError: if there are more bins or more inducing points than training points,
                naming ``model``.
        """
        super().check(model, cfg, n_points)
        if cfg.inducing.points > n_points:
            raise ValueError(
                f"model {model!r}: inducing.points={cfg.inducing.points} is more inducing "
                f"points than the {n_points} training points"
            )


KIND = Pic()
