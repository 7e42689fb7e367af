"""Exact GP (with or without gradient rows): one factorisation of the whole ``K̄``."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from gpg.config import ModelConfig
from gpg.gp.exact import ExactGP
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Cases, Kind, Product, gram_bytes


@dataclass(frozen=True)
class Exact(Kind):
    """``gp`` and ``gpg``: :class:`gpg.gp.exact.ExactGP`."""

    name = "exact"
    reads = ("solver.device",)
    partitioned = False
    needs_gram = True
    partial_gradients = True
    directional_gradients = True

    def build(self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices=None) -> Product:
        t0 = time.perf_counter()
        dims = arrays.dims if arrays.dY is not None else None
        model = ExactGP.fit(
            arrays.X, arrays.Y, arrays.dY, grad_dims=dims, hyper=hyper, observed=arrays.observed,
            bases=arrays.bases, device=cfg.solver.device,
        )  # fmt: skip
        return Product(model, timings={"fit_s": time.perf_counter() - t0})

    def condition(self, model: ExactGP, new: Arrays, cfg: ModelConfig) -> ExactGP:
        """The bordered Cholesky update (:meth:`gpg.gp.exact.ExactGP.condition`)."""
        return model.condition(new.X, new.Y, new.dY, observed=new.observed, bases=new.bases)

    def cases(self, model: ExactGP) -> Cases:
        return Cases(np.asarray(model.X), model.hyper, model.grad_dims)

    def posterior(self, model: ExactGP) -> ExactGP:
        return model

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        return gram_bytes(n_points, n_grad)  # one K̄, factorised in place


KIND = Exact()
