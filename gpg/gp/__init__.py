"""The Gaussian-process numerics, knowing nothing of quadrotors (docs/design.md, Architecture).

kernels (RBF with value and gradient rows), hyper (σ, l, ν², λ²), gram (``K̄``, ``Ȳ`` and the log
likelihood under one name, from targets (``Ȳ``, the checked data), layout (which row is which),
directions (directional gradient rows), assembly (``K̄`` on the host, a device or traced) and
likelihood), fit (hyperparameters by marginal likelihood), exact (GP-G), update (its bordered
Cholesky update), mean (the folded exact mean), predictor (the one predict interface), partition
(bins and near sets), binned (the partitioned predictor and its per-bin format), local (near-set
GPs, the far set dropped), schur (the paper's correction and its diagnostics), hybrid
(GP-G-S-Hybrid), pic (GP-G-PIC), inducing (values-only GPs on many cases through inducing
inputs: the flight correction's discrepancies).
"""

from gpg.gp import (
    assembly,
    binned,
    cg,
    directions,
    exact,
    fit,
    gram,
    hybrid,
    hyper,
    inducing,
    kernels,
    layout,
    likelihood,
    local,
    matfree,
    mean,
    partition,
    pic,
    predictor,
    schur,
    slq,
    targets,
    update,
)
from gpg.gp.exact import ExactGP
from gpg.gp.fit import (
    FitError,
    FitOptions,
    FitWarning,
    HyperFitResult,
    Stochastic,
    fit_hyperparameters,
)
from gpg.gp.gram import assemble_gram, log_marginal_likelihood, stack_targets
from gpg.gp.hyper import Hyper, gradient_noise
from gpg.gp.inducing import InducingGP

__all__ = [
    "ExactGP",
    "FitError",
    "FitOptions",
    "FitWarning",
    "Hyper",
    "HyperFitResult",
    "InducingGP",
    "Stochastic",
    "assemble_gram",
    "assembly",
    "binned",
    "cg",
    "directions",
    "exact",
    "fit",
    "fit_hyperparameters",
    "gradient_noise",
    "gram",
    "hybrid",
    "hyper",
    "inducing",
    "kernels",
    "layout",
    "likelihood",
    "local",
    "log_marginal_likelihood",
    "matfree",
    "mean",
    "partition",
    "pic",
    "predictor",
    "schur",
    "slq",
    "stack_targets",
    "targets",
    "update",
]
