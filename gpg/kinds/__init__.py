"""The kinds of model gpg builds, one module each (:mod:`gpg.kinds.base` for the interface).

=========== ================================================ =========================
kind        predictor                                        options read (besides hyper)
=========== ================================================ =========================
exact       :class:`gpg.gp.exact.ExactGP`                    —
local       :class:`gpg.gp.binned.BinnedGP` (far set dropped) partition, near, variance_dtype
schur       :class:`gpg.gp.binned.BinnedGP` (Schur far set)   + mean, route
hybrid      :class:`gpg.gp.hybrid.HybridGP`                  partition, near, variance_dtype
pic         :class:`gpg.gp.binned.BinnedGP` (inducing rows)   partition, inducing, variance_dtype
=========== ================================================ =========================
"""

from gpg.kinds import base, exact, hybrid, local, pic, schur
from gpg.kinds.base import Arrays, Cases, Kind, Product

__all__ = [
    "Arrays",
    "Cases",
    "KINDS",
    "Kind",
    "Product",
    "base",
    "exact",
    "hybrid",
    "local",
    "pic",
    "schur",
]

# The built-in kinds by name (gpg.models.SPECS refers to them; a kind of one's own is passed
# to gpg.models.register instead).
KINDS: dict[str, Kind] = {
    k.name: k for k in (exact.KIND, local.KIND, schur.KIND, hybrid.KIND, pic.KIND)
}
