"""GP-G-S-Hybrid: GP-G's exact mean with a near-set variance (an upper bound on GP-G's)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg.gp import partition
from gpg.gp.binned import BinnedGP
from gpg.gp.hyper import Hyper
from gpg.gp.mean import GlobalMean
from gpg.gp.predictor import Predictor

__all__ = [
    "HybridGP",
    "Record",
]


class Record(eqx.Module):
    """The training data a hybrid was built on, normalised: inputs ``X`` (N, D), stacked
    targets ``Ybar`` (R, M) in the layout of :mod:`gpg.gp.kernels`, the hyperparameters,
    which rows were observed (R,) or None for all, and the gradient rows' directions."""

    X: Float[Array, "N D"]
    Ybar: Float[Array, "R M"]
    hyper: Hyper
    rows: Bool[Array, " R"] | None = None
    # (N, G, G): the directions of the gradient rows (gpg.gp.gram.row_directions), or None
    bases: Float[Array, "N G G"] | None = None


class HybridGP(Predictor):
    """GP-G-S-Hybrid: the exact GP-G mean from the global ``α`` (:mod:`gpg.gp.mean`), and the
    variance of the query's bin's near set, ``σ − k_qnᵀ K̄_nn⁻¹ k_qn``.

    Conditioning on a subset of the observations never lowers the posterior variance, so the
    near-set variance is an upper bound on the exact GP-G variance at every query: the
    hybrid has exactly GP-G's accuracy, is continuous in its mean, and is conservative, never
    overconfident, in its uncertainty relative to GP-G.
    """

    mean: GlobalMean
    local: BinnedGP
    # What :meth:`gpg.kinds.hybrid.Hybrid.condition` needs to add cases (None: a model saved
    # before gpg 0.3, or a mean view): small next to the near sets' factors.
    record: Record | None = None

    @property
    def n_inputs(self) -> int:
        return self.local.n_inputs

    @property
    def n_outputs(self) -> int:
        return self.mean.n_outputs

    @property
    def noise(self) -> Float[Array, ""]:
        return self.local.noise

    @property
    def output_scale(self) -> Float[Array, " M"]:
        return self.local.output_scale

    @property
    def partition(self) -> partition.Partition:
        return self.local.partition

    @property
    def n_near(self) -> Int[Array, " B"]:
        return self.local.n_near

    @property
    def variance(self) -> Float[Array, ""]:
        return self.local.variance

    @property
    def lengthscale(self) -> Float[Array, "*L"]:
        return self.local.lengthscale

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> HybridGP:
        """This model with the per-output variance scale replaced (held by the near sets).

        Args:
            scale: (M,) the new per-output scale of the predictive variance.

        Returns:
            A copy with the same mean and record.
        """
        return HybridGP(self.mean, self.local.with_output_scale(scale), self.record)

    def describe(self) -> dict[str, Any]:
        """The near sets' description: the mean shares their hyperparameters.

        Returns:
            :meth:`gpg.gp.binned.BinnedGP.describe` of the near sets.
        """
        return self.local.describe()

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """GP-G's exact posterior mean at one query, from the global ``α``.

        Args:
            x: (D,) one normalised query.

        Returns:
            The (M,) posterior mean.
        """
        return self.mean(x)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """The exact mean and the near-set variance ``σ − k_qnᵀ K̄_nn⁻¹ k_qn`` at one query.

        Args:
            x: (D,) one normalised query.

        Returns:
            The (M,) posterior mean and the scalar latent variance (unclamped), an upper
            bound on GP-G's.
        """
        return self.mean(x), self.local.variance_one(x)

    def mean_view(self) -> HybridGP:
        """The global mean with the near sets' arrays dropped (the mean does not read them).

        Returns:
            A hybrid without variance factors or record: its mean equals this one's, its
            variance is not to be used.
        """
        return HybridGP(mean=self.mean, local=self.local.mean_view(), record=None)
