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

__all__ = ["Hyper", "gradient_noise"]


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
        """Check shapes and positivity against the data's inputs and gradient dims.

        Needs concrete values (not under jit). Without gradient rows ``λ²`` is unused, so a
        ``grad_noise`` vector meant for another model is accepted.

        Args:
            n_inputs: the number of inputs D (``lengthscale`` is a scalar or (D,)).
            n_grad: the number of gradient dims G (``grad_noise`` is a scalar or (G,)).

        Returns:
            This ``Hyper``, unchanged.

        Raises:
            ValueError: naming the offending field: a shape that does not fit, or a value that
                is not finite and positive.
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
        """The noise on ``K̄``'s diagonal, in the row layout of :mod:`gpg.gp.kernels`.

        Args:
            n_points: the number of points N.
            n_grad: the number of gradient dims G.

        Returns:
            ``(ν², …, ν², λ_1², …, λ_1², …, λ_G², …)``: ``ν²`` on the N value rows, then
            ``λ_g²`` on each block of N gradient rows, length ``N (1 + G)``.
        """
        if n_grad == 0:
            return jnp.full(n_points, self.noise)
        lam = jnp.broadcast_to(self.grad_noise, (n_grad,))
        per_block = jnp.concatenate([self.noise[None], lam])
        return jnp.repeat(per_block, n_points)


def gradient_noise(dY: Float[ArrayLike, "N M G"], s: float = 0.3) -> Float[Array, " G"]:
    """The paper's rule ``λ_i² = s · Var(∂_i Ỹ)``, the variance taken over points and outputs.

    A dimension no case has gets the variance 1 of a normalised gradient; one whose gradients
    are all equal gets the smallest positive variance, so that ``K̄`` stays positive definite.

    Args:
        dY: (N, M, G) the (normalised) gradients; NaN marks a gradient a case does not have
            (:func:`gpg.gp.gram.observed_rows`).
        s: the paper's scale (0.3 in the paper).

    Returns:
        ``λ_i²`` (G,).

    Raises:
        ValueError: if ``dY`` is not a 3-dimensional numeric array, or ``s`` is not > 0.
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
