"""Kernel and noise hyperparameters of the (gradient-enhanced) GP (paper symbols).

``σ`` and ``l`` of the RBF kernel, the value-noise nugget ``ν²`` and the gradient-row noise
``λ_i²`` of Eq. (gradient_covariance_noise), with the paper's rule for ``λ_i²``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg import _checks
from gpg._deprecated import deprecated


class Hyper(eqx.Module):
    """Kernel and noise hyperparameters (paper symbols in brackets).

    Attributes:
        variance: signal variance σ of the RBF kernel.
        lengthscale: radius scale ``l``: a scalar (isotropic) or one per input (ARD).
        noise: ``ν²``, the value-noise variance, added to the diagonal of value rows (called
            ``jitter`` before gpg 0.2: that name still reads and constructs it, with a
            ``DeprecationWarning``, for one release).
        grad_noise: ``λ_i²`` added to the diagonal of the rows of gradient dimension ``i``;
            a scalar (same for all) or one per gradient dimension.
    """

    variance: Float[Array, ""]
    lengthscale: Float[Array, "*L"]
    noise: Float[Array, ""]
    grad_noise: Float[Array, "*G"]

    def __init__(self, variance=1.0, lengthscale=1.0, noise=1e-8, grad_noise=1e-6, *, jitter=None):
        if jitter is not None:
            deprecated("Hyper(jitter=...)", "Hyper(noise=...)")
            noise = jitter
        self.variance = jnp.asarray(variance, dtype=float)
        self.lengthscale = jnp.asarray(lengthscale, dtype=float)
        self.noise = jnp.asarray(noise, dtype=float)
        self.grad_noise = jnp.asarray(grad_noise, dtype=float)

    @property
    def jitter(self) -> Float[Array, ""]:
        """Deprecated name of :attr:`noise` (``ν²``); numerical jitter is another thing."""
        deprecated("Hyper.jitter", "Hyper.noise")
        return self.noise

    def validate(self, n_inputs: int, n_grad: int) -> Hyper:
        """Check shapes and positivity against ``n_inputs`` inputs and ``n_grad`` gradient dims.

        Raises ``ValueError`` naming the offending field. Needs concrete values (not under jit).
        """
        for name in ("variance", "noise"):
            if getattr(self, name).ndim != 0:
                raise ValueError(f"hyper.{name} must be a scalar, got {getattr(self, name).shape}")
        if self.lengthscale.shape not in ((), (n_inputs,)):
            raise ValueError(
                f"hyper.lengthscale must be a scalar or have shape ({n_inputs},), "
                f"got {self.lengthscale.shape}"
            )
        # Without gradient rows λ² is unused, so a vector meant for another model is accepted.
        if n_grad and self.grad_noise.shape not in ((), (n_grad,)):
            raise ValueError(
                f"hyper.grad_noise must be a scalar or have shape ({n_grad},), "
                f"got {self.grad_noise.shape}"
            )
        for name in ("variance", "lengthscale", "noise", "grad_noise"):
            _checks.require_positive(f"hyper.{name}", np.asarray(getattr(self, name)))
        return self

    def noise_diagonal(self, n_points: int, n_grad: int) -> Float[Array, " R"]:
        """Diagonal ``(ν², …, ν², λ_1², …, λ_G², …)`` of length ``n_points·(1+n_grad)``."""
        if n_grad == 0:
            return jnp.full(n_points, self.noise)
        lam = jnp.broadcast_to(self.grad_noise, (n_grad,))
        per_block = jnp.concatenate([self.noise[None], lam])
        return jnp.repeat(per_block, n_points)


def gradient_noise(dY: Float[ArrayLike, "N M G"], s: float = 0.3) -> Float[Array, " G"]:
    """The paper's rule ``λ_i² = s · Var(∂_i Ỹ)``, the variance taken over points and outputs.

    ``dY`` are the (normalised) gradients, ``s`` the paper's scale (0.3 in the paper). NaN
    marks a gradient a case does not have (:func:`gpg.gp.gram.observed_rows`); a dimension
    no case has gets the variance 1 of a normalised gradient.
    """
    dY = _checks.as_float_array("dY", dY, ndim=3)
    if not s > 0:
        raise ValueError(f"s must be > 0, got {s}")
    flat = dY.reshape(-1, dY.shape[2])
    seen = ~np.isnan(flat)
    count = seen.sum(axis=0)
    mean = np.where(seen, flat, 0.0).sum(axis=0) / np.maximum(count, 1)
    var = np.where(seen, (flat - mean) ** 2, 0.0).sum(axis=0) / np.maximum(count, 1)
    var = np.where(count > 0, var, 1.0)
    # A dimension whose gradients are all equal would get zero noise; keep K̄ positive definite.
    return jnp.asarray(s * np.maximum(var, np.finfo(float).tiny))
