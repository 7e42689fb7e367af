"""gpg: gradient-enhanced partitioned Gaussian processes for quadrotor aerodynamics.

Importing gpg changes no global state (no JAX flag, no matplotlib backend, no signal handler).
Fitting runs in float64 whatever the caller's setting (inside ``jax.enable_x64(True)``); a fitted
:class:`Surrogate` predicts in float64 in a float64 program and, after
``Surrogate.astype(jnp.float32)``, in float32 in a float32 one (docs/design.md, "Dtype policy").

The names below are the package's whole public surface: the four classes most programs need,
and the subpackages and modules, each with its own ``__all__`` (imported when first used, so
that ``import gpg`` stays light).
"""

import importlib
from types import ModuleType

from gpg import checkpoint, models
from gpg._version import __version__
from gpg.gp import ExactGP, Hyper, kernels
from gpg.surrogate import Prediction, Surrogate

__all__ = [
    "ExactGP",
    "Hyper",
    "Prediction",
    "Surrogate",
    "__version__",
    "adapters",
    "checkpoint",
    "conf",
    "config",
    "data",
    "design",
    "envs",
    "export",
    "flight",
    "gp",
    "kernels",
    "kinds",
    "linalg",
    "models",
    "mpc",
    "names",
    "parallel",
    "quadrotor",
    "results",
    "runtime",
    "surrogate",
]

# The exported modules not imported above: imported on first use.
_LAZY = frozenset(__all__) - set(globals())


def __getattr__(name: str) -> ModuleType:
    if name in _LAZY:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'gpg' has no attribute {name!r}")
