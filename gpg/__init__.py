"""gpg: gradient-enhanced partitioned Gaussian processes for quadrotor aerodynamics.

Importing gpg changes no global state (no JAX flag, no matplotlib backend, no signal handler).
Fitting runs in float64 whatever the caller's setting (inside ``jax.enable_x64(True)``); a fitted
:class:`Surrogate` predicts in float64 in a float64 program and, after
``Surrogate.astype(jnp.float32)``, in float32 in a float32 one (docs/design.md, "Dtype policy").
"""

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
    "checkpoint",
    "kernels",
    "models",
]
