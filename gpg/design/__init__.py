"""Spending the simulator's budget: conditioning on new cases, choosing the next ones.

* :func:`condition` (also :meth:`gpg.Surrogate.condition`): a fitted surrogate on more cases,
  hyperparameters, normaliser and bins kept, equal to a :func:`rebuild` with the same
  hyperparameters; with the rule for when to refit instead (:mod:`gpg.design.conditioning`).
* :func:`propose`: the next batch of cases, with the gradient perturbations worth running at
  each (:mod:`gpg.design.proposal`, on the criterion of :mod:`gpg.design.acquisition`).
* :mod:`gpg.design.cases`: the ask/tell CSV files for an external solver.
"""

from gpg.design import acquisition, cases
from gpg.design.acquisition import GRADIENTS, Batch, subsets
from gpg.design.conditioning import (
    _outside as _outside,  # read by tests/data/test_convert.py as gpg.design._outside
)
from gpg.design.conditioning import (
    condition,
    merge_datasets,
    new_cases,
    posterior,
    rebuild,
    training_cases,
)
from gpg.design.proposal import Proposal, propose
from gpg.design.proposal import box_samples as box_samples  # read by tests/data/test_convert.py

__all__ = [
    "GRADIENTS",
    "Batch",
    "Proposal",
    "acquisition",
    "cases",
    "condition",
    "merge_datasets",
    "new_cases",
    "posterior",
    "propose",
    "rebuild",
    "subsets",
    "training_cases",
]
