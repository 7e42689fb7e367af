"""The one ``predict`` every model shares.

A model answers a single normalised query ``x`` (D,) with ``mean_one`` (M,) or
``mean_var_one`` (mean (M,), latent variance ()); these are written so that ``jax.vmap`` turns
them into efficient batched code, and ``predict`` / ``predict_mean`` are exactly that, jitted,
for a batch ``Xq`` (Q, D). The latent variance is shared by the M outputs (one kernel).

``mean_var_one`` returns the variance as computed, which the Schur forms can make negative
(their ``k_qf ≈ 0`` assumption failing); ``predict`` clips it at zero, ``predict_unclipped``
does not, so that such failures can be counted rather than hidden. ``noise`` is the value-noise
variance ``ν²`` of an observation: the predictive variance of a measured output is the latent
variance plus ``ν²``, and ``output_scale`` (M,) scales that per output (the outputs share one
kernel; the scale is each output's closed-form maximum-likelihood amplitude,
:func:`gpg.gp.mean.output_scale`): ``var_m = output_scale[m] · (latent + ν²)``.
"""

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox import AbstractVar
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._checks import no_hash
from gpg._dtype import in_model_dtype
from gpg._precision import highest
from gpg.gp.partition import Partition

__all__ = ["Predictor", "plain"]


class Predictor(eqx.Module):
    """Interface of every GP model in gpg (exact, partitioned, Schur-corrected).

    A subclass provides ``output_scale`` (M,), the per-output scale of the predictive variance
    (ones for a shared scale), ``partition``, its bins (None for a model without), and
    ``noise``, the value-noise variance ``ν²``, each as a field or a property; and the
    abstract methods below. Callers (the builds, checkpoints, the comparison) use nothing
    else, so a new kind of model needs no branch elsewhere.
    """

    __hash__ = no_hash  # jax.jit(model.predict): say what to call instead

    output_scale: AbstractVar[Float[Array, " M"]]
    partition: AbstractVar[Partition | None]
    # Value-noise variance ν² of an observation (normalised units).
    noise: AbstractVar[Float[Array, ""]]

    @property
    @abc.abstractmethod
    def n_inputs(self) -> int: ...

    @property
    @abc.abstractmethod
    def n_outputs(self) -> int: ...

    @abc.abstractmethod
    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> "Predictor":
        """This model with the per-output variance scale replaced.

        Args:
            scale: (M,) the new ``output_scale``.

        Returns:
            A copy of the model; the arrays it shares are not copied.
        """

    @abc.abstractmethod
    def describe(self) -> dict[str, Any]:
        """Plain values a person reads in a checkpoint's metadata.

        Returns:
            JSON-ready values (:func:`plain`): at least ``hyperparameters`` (signal
            ``variance``, ``lengthscale``, value ``noise`` ν²).
        """

    def predictive_variance(self, var: Float[ArrayLike, "*Q"]) -> Float[Array, "*Q M"]:
        """An observation's predictive variance per output (normalised units).

        Args:
            var: the latent variance at some queries, any shape (negative values count as 0).

        Returns:
            ``output_scale · (max(var, 0) + ν²)``, one more axis (M,) than ``var``.
        """
        return (jnp.maximum(jnp.asarray(var), 0.0) + self.noise)[..., None] * self.output_scale

    def variance_parts(self, var: Float[ArrayLike, "*Q"]) -> dict[str, Float[Array, "*Q M"]]:
        """:meth:`predictive_variance` split into the parts it sums: where a band's width
        comes from (a model that combines more parts names them).

        Args:
            var: the latent variance at some queries, as :meth:`predictive_variance` takes it.

        Returns:
            ``"latent"``: ``output_scale · max(var, 0)``; ``"noise"``: ``output_scale · ν²``;
            each one more axis (M,) than ``var``, their sum :meth:`predictive_variance`'s.
        """
        latent = jnp.maximum(jnp.asarray(var), 0.0)[..., None] * self.output_scale
        return {"latent": latent, "noise": jnp.broadcast_to(self.noise * self.output_scale,
                                                            latent.shape)}  # fmt: skip

    @abc.abstractmethod
    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """Posterior mean at one query, written for ``jax.vmap``.

        Args:
            x: (D,) the normalised query.

        Returns:
            The mean (M,).
        """

    @abc.abstractmethod
    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """Posterior mean and latent variance at one query, written for ``jax.vmap``.

        Args:
            x: (D,) the normalised query.

        Returns:
            The mean (M,) and the latent variance () as computed (not clipped).
        """

    def mean_view(self) -> "Predictor":
        """A predictor whose ``mean_one`` equals this one's, holding only what the mean reads.

        For mean-only real-time loops; its variance is not to be used. The default keeps
        everything.

        Returns:
            The lighter predictor (this one by default).
        """
        return self

    def predict(
        self, Xq: Float[ArrayLike, "Q D"]
    ) -> tuple[Float[Array, "Q M"], Float[Array, " Q"]]:
        """Mean and latent variance, clipped at 0, at a batch of queries (jitted).

        Args:
            Xq: (Q, D) the normalised queries, finite.

        Returns:
            The mean (Q, M) and the latent variance (Q,), at least 0.
        """
        mean, var = self.predict_unclipped(Xq)
        return mean, jnp.maximum(var, 0.0)

    def predict_unclipped(
        self, Xq: Float[ArrayLike, "Q D"]
    ) -> tuple[Float[Array, "Q M"], Float[Array, " Q"]]:
        """As :meth:`predict`, with the variance as computed.

        The variance is negative where a model's assumptions fail: count those, do not trust
        them.

        Args:
            Xq: (Q, D) the normalised queries, finite (a check in the program).

        Returns:
            The mean (Q, M) and the unclipped latent variance (Q,).
        """
        return in_model_dtype(self, lambda: _batch(self, _host.asarray(Xq), True), Xq)

    def predict_mean(self, Xq: Float[ArrayLike, "Q D"]) -> Float[Array, "Q M"]:
        """Mean only: the fast path (no variance is formed).

        Args:
            Xq: (Q, D) the normalised queries.

        Returns:
            The mean (Q, M).
        """
        return in_model_dtype(self, lambda: _batch(self, jnp.asarray(Xq), False)[0], Xq)

    def nbytes(self) -> int:
        """Bytes of the arrays the model holds (what a deployment has to load).

        The leaves kept by ``eqx.is_array`` (JAX arrays, NumPy arrays and scalars) all report
        ``nbytes`` themselves, so nothing is copied to the host.

        Returns:
            The total bytes.
        """
        return int(sum(x.nbytes for x in jax.tree.leaves(eqx.filter(self, eqx.is_array))))


def plain(x: Any) -> Any:
    """An array as nested lists (JSON-ready), for :meth:`Predictor.describe`.

    Args:
        x: an array or scalar (NumPy, JAX or Python).

    Returns:
        Nested lists of Python numbers (a number for a scalar).
    """
    return np.asarray(x).tolist()


def check_query(Xq: Array, n_inputs: int) -> None:
    if Xq.ndim != 2 or Xq.shape[1] != n_inputs:
        raise ValueError(f"Xq must have shape (Q, {n_inputs}), got {Xq.shape}")


@eqx.filter_jit
@highest
def _batch(model: "Predictor", Xq: Array, with_var: bool):
    check_query(Xq, model.n_inputs)
    Xq = eqx.error_if(Xq, ~jnp.all(jnp.isfinite(Xq)), "Xq holds NaN or inf")
    if with_var:
        return jax.vmap(model.mean_var_one)(Xq)
    return jax.vmap(model.mean_one)(Xq), None
