"""The Gaussian-process numerics, knowing nothing of quadrotors (docs/design.md, Architecture).

kernels (RBF with value and gradient rows), hyper (σ, l, ν², λ²), gram (``K̄``, ``Ȳ``, the log
likelihood), fit (hyperparameters by marginal likelihood), exact (GP-G), mean (the folded exact
mean), predictor (the one predict interface), partition (bins and near sets), binned (the
partitioned predictor and its per-bin format), local (near-set GPs, the far set dropped), schur
(the paper's correction and its diagnostics), hybrid (GP-G-S-Hybrid), pic (GP-G-PIC).
"""

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

__all__ = [
    "ExactGP",
    "FitError",
    "FitOptions",
    "FitWarning",
    "Hyper",
    "HyperFitResult",
    "Stochastic",
    "assemble_gram",
    "fit_hyperparameters",
    "gradient_noise",
    "log_marginal_likelihood",
    "stack_targets",
]
