"""Exact GP (with or without gradient rows): one factorisation of the whole ``K̄``."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from gpg.config import ModelConfig
from gpg.gp.exact import ExactGP
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Cases, Kind, Product, gram_bytes
from gpg.parallel import Devices

__all__ = ["KIND", "Exact"]


@dataclass(frozen=True)
class Exact(Kind):
    """``gp`` and ``gpg``: :class:`gpg.gp.exact.ExactGP`."""

    name = "exact"
    reads = ("solver.device",)
    partitioned = False
    needs_gram = True
    partial_gradients = True
    directional_gradients = True

    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """One factorisation of the whole ``K̄`` (:meth:`gpg.gp.exact.ExactGP.fit`).

        Args:
            arrays: the normalised training arrays; cases with some gradients missing
                (``observed``) and directional gradient rows (``bases``) are taken.
            hyper: the fitted hyperparameters (σ, l, ν², λ_i²).
            cfg: the resolved config; ``solver.device`` places the factorisation.
            devices: unused: the exact GP has no per-bin work to spread.

        Returns:
            The :class:`~gpg.gp.exact.ExactGP` and the seconds of its fit (``fit_s``).
        """
        t0 = time.perf_counter()
        dims = arrays.dims if arrays.dY is not None else None
        model = ExactGP.fit(
            arrays.X, arrays.Y, arrays.dY, grad_dims=dims, hyper=hyper, observed=arrays.observed,
            bases=arrays.bases, device=cfg.solver.device,
        )  # fmt: skip
        return Product(model, timings={"fit_s": time.perf_counter() - t0})

    def condition(self, model: ExactGP, new: Arrays, cfg: ModelConfig) -> ExactGP:
        """The bordered Cholesky update (:meth:`gpg.gp.exact.ExactGP.condition`).

        Args:
            model: the exact GP to condition.
            new: the new cases (normalised), with their gradients if ``model`` has them.
            cfg: unused: the exact GP keeps its own settings.

        Returns:
            ``model`` conditioned on ``new``, equal to a refit with its hyperparameters.
        """
        return model.condition(new.X, new.Y, new.dY, observed=new.observed, bases=new.bases)

    def cases(self, model: ExactGP) -> Cases:
        """The exact GP's training inputs, hyperparameters and gradient dims.

        Args:
            model: an exact GP.

        Returns:
            ``model``'s normalised ``X`` (as NumPy), ``hyper`` and ``grad_dims``.
        """
        return Cases(np.asarray(model.X), model.hyper, model.grad_dims)

    def posterior(self, model: ExactGP) -> ExactGP:
        """The exact GP-G the acquisition reads: the model itself.

        Args:
            model: an exact GP.

        Returns:
            ``model``, unchanged.
        """
        return model

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """One dense ``K̄``, factorised in place, with a margin.

        Args:
            cfg: unused: the size depends on the data alone.
            n_points: training points ``N``.
            n_grad: gradient dims ``G``; ``K̄`` has ``N(1 + G)`` rows.

        Returns:
            ``1.2 · 8 (N(1 + G))²`` bytes.
        """
        return gram_bytes(n_points, n_grad)


KIND = Exact()
