"""GP-G-S-Hybrid: GP-G's exact mean with a near-set variance (an upper bound on GP-G's)."""

from __future__ import annotations

from typing import Any

from jaxtyping import Array, ArrayLike, Float, Int

from gpg.gp import partition
from gpg.gp.binned import BinnedGP
from gpg.gp.mean import GlobalMean
from gpg.gp.predictor import Predictor


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
        return HybridGP(mean=self.mean, local=self.local.with_output_scale(scale))

    def describe(self) -> dict[str, Any]:
        """The near sets' description: the mean shares their hyperparameters."""
        return self.local.describe()

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        return self.mean(x)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        return self.mean(x), self.local.variance_one(x)

    def mean_view(self) -> HybridGP:
        """The global mean with the near sets' arrays dropped (the mean does not read them)."""
        return HybridGP(mean=self.mean, local=self.local.mean_view())
