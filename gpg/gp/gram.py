"""The stacked targets ``Ȳ``, the Gram matrix ``K̄`` of Eq. (barK) and its log likelihood: the
names of the modules that hold them, in one place.

Rows follow the layout of :mod:`gpg.gp.kernels`: ``N`` value rows, then one block of ``N`` rows
per gradient dimension. Each concern has its module:

* :mod:`gpg.gp.targets`: ``Ȳ`` (:func:`stack_targets`, :func:`mask_targets`) and the training
  data it is stacked from, checked;
* :mod:`gpg.gp.layout`: which row is which, which were observed (:func:`observed_rows`);
* :mod:`gpg.gp.directions`: gradient rows along other directions than the inputs
  (:func:`row_directions`, :func:`to_bases`, :func:`from_bases`);
* :mod:`gpg.gp.assembly`: ``K̄`` plus its noise on the host (:func:`assemble_gram`, written
  block by block into one buffer), on a device (:func:`device_gram`) and traced
  (:func:`noisy_gram`);
* :mod:`gpg.gp.likelihood`: :func:`log_marginal_likelihood`, the differentiable dense form used
  on the hyperparameter-fit subset.
"""

from __future__ import annotations

from gpg.gp.assembly import (
    assemble_gram,
    assemble_rows_gram,
    device_gram,
    mask_gram_inplace,
    noisy_gram,
    rows_gram,
)
from gpg.gp.directions import check_bases as check_bases
from gpg.gp.directions import from_bases, row_directions, to_bases
from gpg.gp.layout import layout_rows as layout_rows
from gpg.gp.layout import observed_rows
from gpg.gp.layout import row_kinds as row_kinds
from gpg.gp.layout import value_row_noise as value_row_noise
from gpg.gp.likelihood import log_marginal_likelihood
from gpg.gp.targets import Checked as Checked
from gpg.gp.targets import check_training_data as check_training_data
from gpg.gp.targets import mask_targets, stack_targets

# The ``name as name`` imports above are the subpackage's own helpers, importable from here as
# before the split into modules; they are not for users, hence not in __all__.
__all__ = [
    "assemble_gram",
    "assemble_rows_gram",
    "device_gram",
    "from_bases",
    "log_marginal_likelihood",
    "mask_gram_inplace",
    "mask_targets",
    "noisy_gram",
    "observed_rows",
    "row_directions",
    "rows_gram",
    "stack_targets",
    "to_bases",
]
