"""gpg: gradient-enhanced partitioned Gaussian processes for quadrotor aerodynamics.

Importing gpg turns on JAX's 64-bit mode: every fit is done in float64 (the Gram matrices of
gradient-enhanced GPs are too ill-conditioned for float32). Prediction can be cast to float32
explicitly where that is measured to be good enough.
"""

import jax

jax.config.update("jax_enable_x64", True)

from gpg import checkpoint, kernels, models  # noqa: E402
from gpg.gp import ExactGP, Hyper  # noqa: E402
from gpg.surrogate import Prediction, Surrogate  # noqa: E402

__all__ = ["ExactGP", "Hyper", "Prediction", "Surrogate", "checkpoint", "kernels", "models"]
__version__ = "0.1.0"
