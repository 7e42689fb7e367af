"""Typed, frozen model configuration: what a model is built with, resolved once.

:class:`ModelConfig` holds the hyperparameter choices (:class:`HyperConfig`), the partition
(:class:`PartitionConfig`), the near sets (:class:`NearConfig`), the inducing points of
``gpg_pic`` (:class:`InducingConfig`) and the few model switches. Every field is checked when
the object is made, and the error names the key (``hyper.subset must be ...``), so a bad
value fails before any data are touched.

:meth:`ModelConfig.resolve` is the one place where defaults meet overrides: the shared
defaults are the field defaults below, a model's own differences are in its
``gpg/conf/model/<name>.yaml`` (read by :func:`package_defaults`, the same file Hydra
composes), and the caller's overrides (a mapping, e.g. from Hydra, or a :class:`ModelConfig`)
come last. ``gpg/conf/model/_base.yaml`` mirrors the shared defaults for Hydra (a test keeps
the two equal).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import yaml

from gpg import conf
from gpg.gp.fit import FitOptions, Stochastic
from gpg.gp.partition import SCHEMES
from gpg.gp.schur import check_options
from gpg.linalg.device import PLACEMENTS

__all__ = [
    "HyperConfig",
    "InducingConfig",
    "ModelConfig",
    "NearConfig",
    "PartitionConfig",
    "SolverConfig",
    "package_defaults",
]

DTYPES = ("float64", "float32")  # storage of the variance factors


def _int(where: str, v: Any, lo: int = 0) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{where} must be an integer >= {lo}, got {v!r}")


def _positive(where: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0:
        raise ValueError(f"{where} must be a number > 0, got {v!r}")


def _bool(where: str, v: Any) -> None:
    if not isinstance(v, bool):
        raise ValueError(f"{where} must be true or false, got {v!r}")


def _choice(where: str, v: Any, valid: tuple[str, ...]) -> None:
    if v not in valid:
        raise ValueError(f"{where} must be one of {list(valid)}, got {v!r}")


@dataclass(frozen=True)
class HyperConfig:
    """How the kernel hyperparameters are chosen (paper symbols in the comments)."""

    fit: bool = True  # maximise the marginal likelihood (else use the values below)
    subset: int = 300  # points in the likelihood fit
    seed: int = 0  # subset draw
    max_steps: int = 200  # BFGS steps
    variance: float = 1.0  # σ (initial value, or fixed)
    lengthscale: float | tuple[float, ...] = 1.0  # l on inputs in [-1, 1] (initial, or fixed)
    ard: bool = True  # one lengthscale per input
    noise: float = 1e-8  # value noise ν² on value rows when it is not fitted
    fit_noise: bool = True  # fit ν² jointly with σ and l (needs fit)
    noise_init: float = 1e-2  # initial ν²/σ of that fit
    noise_floor: float = 1e-6  # lower bound of the fitted ν²/σ
    grad_noise_scale: float = 0.3  # s in λ_i² = s·Var(∂_i Ỹ)
    fit_grad_noise: bool = False  # also fit s
    lengthscale_scale: float = 1.0  # multiplies the fitted (or given) lengthscales
    output_scales: bool = True  # per-output ML variance scale (closed form, from α)
    full: bool = False  # then refit on all points by the stochastic likelihood (gpg.gp.slq)
    full_max_steps: int = 100  # BFGS steps of that refit
    full_ftol: float = 2e-5  # it ends after 3 steps each lowering the nll per target by less
    probes: int = 30  # its fixed Gaussian probes of log|K̄|
    cg_tol: float = 1e-5  # relative residual of its CG solves of K̄ α = Ȳ
    cg_probe_tol: float = 1e-3  # relative residual of its probe solves (log|K̄| and its gradient)
    cg_max_iter: int = 500  # iteration budget of each of those solves

    def fit_options(self) -> FitOptions:
        """The likelihood fit on the subset, as :func:`gpg.gp.fit.fit_hyperparameters` takes it.

        Returns:
            The fit's options (:class:`gpg.gp.fit.FitOptions`) of this config: ARD, which
                noises are fitted (``ν²`` with its start and floor, the gradient-noise scale
                ``s``), the subset size and seed, and the BFGS steps.
        """
        return FitOptions(
            ard=self.ard,
            fit_grad_noise=self.fit_grad_noise,
            fit_noise=self.fit_noise,
            noise_floor=self.noise_floor,
            noise_init=self.noise_init,
            subset_size=self.subset,
            seed=self.seed,
            max_steps=self.max_steps,
        )

    def full_options(self, noise_init: float) -> FitOptions:
        """The refit on all points by the stochastic likelihood (``full``).

        Args:
            noise_init: the ``ν²/σ`` it starts from (the subset fit's, in
                :func:`gpg.models.fit_hyper`).

        Returns:
            :meth:`fit_options` on every point (no subset), with ``full_max_steps`` BFGS steps
                and the :class:`gpg.gp.fit.Stochastic` settings (probes, CG tolerances and budget,
                ``full_ftol``).
        """
        return dataclasses.replace(
            self.fit_options(),
            noise_init=noise_init,
            subset_size=None,
            max_steps=self.full_max_steps,
            likelihood="stochastic",
            stochastic=Stochastic(
                probes=self.probes,
                tol=self.cg_tol,
                max_iter=self.cg_max_iter,
                probe_tol=self.cg_probe_tol,
                ftol=self.full_ftol,
            ),
        )

    def __post_init__(self):
        w = "hyper."
        for k in ("fit", "ard", "fit_noise", "fit_grad_noise", "output_scales", "full"):
            _bool(w + k, getattr(self, k))
        for k in ("full_max_steps", "probes", "cg_max_iter"):
            _int(w + k, getattr(self, k), 1)
        if isinstance(self.full_ftol, bool) or not (
            isinstance(self.full_ftol, int | float) and self.full_ftol >= 0
        ):
            raise ValueError(f"hyper.full_ftol must be a number >= 0, got {self.full_ftol!r}")
        for k in ("cg_tol", "cg_probe_tol"):
            value = getattr(self, k)
            if isinstance(value, bool) or not (isinstance(value, int | float) and 0 < value < 1):
                raise ValueError(f"hyper.{k} must be in (0, 1), got {value!r}")
        _int(w + "subset", self.subset, 1)
        _int(w + "seed", self.seed)
        _int(w + "max_steps", self.max_steps, 1)
        for k in ("variance", "noise", "noise_init", "noise_floor", "grad_noise_scale"):
            _positive(w + k, getattr(self, k))
        _positive(w + "lengthscale_scale", self.lengthscale_scale)
        ls = self.lengthscale
        if isinstance(ls, list | tuple):
            object.__setattr__(self, "lengthscale", tuple(ls))
            for v in ls:
                _positive(w + "lengthscale", v)
        else:
            _positive(w + "lengthscale", ls)
        if self.fit_noise and not self.noise_floor < self.noise_init:
            raise ValueError(
                f"hyper.noise_floor ({self.noise_floor}) must be below hyper.noise_init "
                f"({self.noise_init})"
            )


@dataclass(frozen=True)
class PartitionConfig:
    """How the inputs are cut into bins."""

    # slab: equal-count intervals along one input | kdtree: median splits | adaptive: intervals
    # of equal output variation along one input (narrower where the outputs change fast)
    scheme: str = "slab"
    bins: int = 10  # number of bins (the paper: 10), unless points_per_bin is set
    points_per_bin: int | None = None  # or: about this many training points per bin
    dim: int = 7  # input cut by slab and adaptive (7 = airspeed)

    def __post_init__(self):
        _choice("partition.scheme", self.scheme, SCHEMES)
        _int("partition.bins", self.bins, 1)
        if self.points_per_bin is not None and (
            isinstance(self.points_per_bin, bool)
            or not isinstance(self.points_per_bin, int)
            or self.points_per_bin < 1
        ):
            raise ValueError(
                f"partition.points_per_bin must be a positive integer, got {self.points_per_bin!r}"
            )
        _int("partition.dim", self.dim)

    def n_bins(self, n_points: int) -> int:
        """The number of bins for a training set.

        Args:
            n_points: the training points.

        Returns:
            About ``n_points / points_per_bin`` (at least 1, at most ``n_points``) when
                ``points_per_bin`` is set, else ``bins``.
        """
        if self.points_per_bin is not None:
            return int(min(max(1, round(n_points / self.points_per_bin)), n_points))
        return self.bins


@dataclass(frozen=True)
class NearConfig:
    """The near set of each bin: ``epsilon`` if set, else ``points`` if set, else ``budget``."""

    budget: float | None = 0.125  # fraction of the points most correlated with the bin
    epsilon: float | None = None  # or: kernel-correlation threshold
    points: int | None = None  # or: this many points, whatever N

    def __post_init__(self):
        if self.budget is not None and not (
            isinstance(self.budget, int | float) and 0 < self.budget <= 1
        ):
            raise ValueError(f"near.budget must be a fraction in (0, 1], got {self.budget!r}")
        if self.epsilon is not None and not (
            isinstance(self.epsilon, int | float) and 0 <= self.epsilon < 1
        ):
            raise ValueError(f"near.epsilon must be in [0, 1), got {self.epsilon!r}")
        if self.points is not None:
            _int("near.points", self.points, 1)
        if self.budget is None and self.epsilon is None and self.points is None:
            raise ValueError("near needs one of epsilon, points and budget")

    def rule(self) -> dict[str, Any]:
        """The keyword of :func:`gpg.gp.partition.near_sets` this config selects.

        Returns:
            One of ``{"epsilon": ...}``, ``{"points": ...}`` or ``{"budget": ...}``, in that
                order of precedence.
        """
        if self.epsilon is not None:
            return {"epsilon": self.epsilon}
        if self.points is not None:
            return {"points": self.points}
        return {"budget": self.budget}


@dataclass(frozen=True)
class InducingConfig:
    """The inducing inputs of ``gpg_pic``."""

    points: int = 250  # U, chosen by k-means on the training inputs (each brings 1+G rows)
    seed: int = 0  # k-means start
    jitter: float = 1e-6  # relative jitter on the diagonal of K̄_uu

    def __post_init__(self):
        if isinstance(self.points, bool) or not isinstance(self.points, int) or self.points < 1:
            raise ValueError(f"inducing.points must be a positive integer, got {self.points!r}")
        _int("inducing.seed", self.seed)
        _positive("inducing.jitter", self.jitter)


SOLVERS = ("auto", "cholesky", "cg")


@dataclass(frozen=True)
class SolverConfig:
    """How ``gpgs_hybrid`` solves ``K̄ α = Ȳ`` for its exact mean (:mod:`gpg.gp.cg`), and where
    every kind's dense solves run (``device``; the one key the other kinds read)."""

    # cholesky: form and factorise K̄ | cg: matrix-free conjugate gradients, K̄ never formed |
    # auto: cholesky when K̄ fits in the available memory, else cg
    method: str = "auto"
    tol: float = 1e-6  # cg: relative residual of every output's solve
    max_iter: int = 2000  # cg: iteration budget (an error past it)
    points: int = 250  # cg: inducing inputs of the Nyström preconditioner (each 1+G rows)
    seed: int = 0  # cg: k-means start of those inputs
    tile: int = 256  # cg: points per tile of K in a product (memory: tile x N)
    # where the dense solves run (K̄, the bins' near sets, PIC's blocks): host (LAPACK in
    # place) | device (JAX's default device, float64) | auto: the accelerator when there is
    # one and the solve fits in its free memory (gpg.linalg.device.place)
    device: str = "auto"

    def __post_init__(self):
        _choice("solver.method", self.method, SOLVERS)
        if not (isinstance(self.tol, int | float) and 0 < self.tol < 1):
            raise ValueError(f"solver.tol must be in (0, 1), got {self.tol!r}")
        _int("solver.max_iter", self.max_iter, 1)
        _int("solver.points", self.points, 1)
        _int("solver.seed", self.seed)
        _int("solver.tile", self.tile, 1)
        _choice("solver.device", self.device, PLACEMENTS)


_SECTIONS = {
    "hyper": HyperConfig,
    "partition": PartitionConfig,
    "near": NearConfig,
    "inducing": InducingConfig,
    "solver": SolverConfig,
}


@dataclass(frozen=True)
class ModelConfig:
    """Everything a model is built with (see the module docstring)."""

    hyper: HyperConfig = field(default_factory=HyperConfig)
    partition: PartitionConfig = field(default_factory=PartitionConfig)
    near: NearConfig = field(default_factory=NearConfig)
    inducing: InducingConfig = field(default_factory=InducingConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    variance_dtype: str = "float64"  # storage of the variance factors (float32: half the bytes)
    mean: str = "exact"  # gpgs_schur: exact k_qnᵀ α_n | paper k_qnᵀ S⁻¹ Ȳ_n
    route: str = "global"  # gpgs_schur: one factorisation for all bins | direct: K̄_ff per bin

    def __post_init__(self):
        _choice("variance_dtype", self.variance_dtype, DTYPES)
        check_options(self.mean, self.route)

    @classmethod
    def resolve(
        cls,
        name: str,
        overrides: Mapping[str, Any] | ModelConfig | None = None,
        defaults: Mapping[str, Any] | None = None,
    ) -> ModelConfig:
        """Shared defaults, then model ``name``'s own defaults, then ``overrides``.

        Args:
            name: the model name, whose ``gpg/conf/model/<name>.yaml`` holds its defaults.
            overrides: nested keys to change, e.g. ``{"hyper": {"subset": 60}}`` (a ``name``
                key is ignored), or a :class:`ModelConfig`, taken as it is (already resolved).
            defaults: the model's own defaults; None reads them with :func:`package_defaults`.

        Returns:
            The resolved, checked config.

        Raises:
            ValueError: if ``overrides`` is not a mapping, or a key is unknown or a value bad
                (the message names it).
        """
        if isinstance(overrides, ModelConfig):
            return overrides
        if overrides is not None and not isinstance(overrides, Mapping):
            raise ValueError(
                "config (the model options) must be a mapping such as {'hyper': {'subset': 60}}, "
                f"got a {type(overrides).__name__}: {overrides!r:.80}"
            )
        own = package_defaults(name) if defaults is None else defaults
        base = merge(cls().to_dict(), renamed_keys(own), "")
        over = renamed_keys(overrides or {})
        over.pop("name", None)
        return cls.from_dict(merge(base, over, ""))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ModelConfig:
        """From a complete mapping, as :meth:`to_dict` writes it.

        Args:
            d: every section and switch; the old key names of :data:`RENAMED_KEYS` are read
                with a ``DeprecationWarning``.

        Returns:
            The config, every field checked.
        """
        kw = {}
        for k, v in renamed_keys(d).items():
            kw[k] = _SECTIONS[k](**v) if k in _SECTIONS else v
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain values, JSON-ready.

        Returns:
            A nested dict of every field; a lengthscale tuple becomes a list.
        """
        out = dataclasses.asdict(self)
        ls = out["hyper"]["lengthscale"]
        if isinstance(ls, tuple):
            out["hyper"]["lengthscale"] = list(ls)
        return out


# Keys renamed in gpg 0.2 (ν² is the value noise; "jitter" now only means numerical jitter, as
# inducing.jitter): the old names are read for one release with a DeprecationWarning.
RENAMED_KEYS = {
    "jitter": "noise",
    "fit_jitter": "fit_noise",
    "jitter_init": "noise_init",
    "jitter_floor": "noise_floor",
}


def renamed_keys(d: Mapping[str, Any]) -> dict[str, Any]:
    """``d`` with the ``hyper`` keys of :data:`RENAMED_KEYS` under their new names."""
    out = dict(d)
    hyper = out.get("hyper")
    if isinstance(hyper, Mapping) and any(k in RENAMED_KEYS for k in hyper):
        new = {}
        for k, v in hyper.items():
            if k in RENAMED_KEYS:
                warnings.warn(
                    f"config key hyper.{k} is deprecated; use hyper.{RENAMED_KEYS[k]}",
                    DeprecationWarning,
                    stacklevel=4,
                )
                k = RENAMED_KEYS[k]
            new[k] = v
        out["hyper"] = new
    return out


def merge(base: Mapping[str, Any], over: Mapping[str, Any] | None, where: str) -> dict[str, Any]:
    """``base`` with ``over``'s (nested) keys replaced; a key ``base`` lacks raises
    ``ValueError`` naming it and listing the valid ones."""
    out = dict(base)
    for k, v in (over or {}).items():
        if k not in base:
            raise ValueError(f"unknown key {where}{k!r}; valid: {sorted(base)}")
        if isinstance(base[k], Mapping):
            if not isinstance(v, Mapping):
                raise ValueError(f"{where}{k} must be a mapping, got {v!r}")
            out[k] = merge(base[k], v, f"{where}{k}.")
        else:
            out[k] = v
    return out


def package_defaults(name: str) -> dict[str, Any]:
    """Model ``name``'s own defaults as its ``gpg/conf/model/<name>.yaml`` states them.

    That file is the one Hydra composes over ``_base.yaml``.

    Args:
        name: the model name.

    Returns:
        The file's keys other than ``defaults`` and ``name``; empty for a name without a file.
    """
    text = conf.read_text("model", name)
    if text is None:
        return {}
    body = yaml.safe_load(text) or {}
    return {k: v for k, v in body.items() if k not in ("defaults", "name")}
