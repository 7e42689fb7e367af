"""Dense linear algebra for matrices that fill the machine (docs/design.md, Architecture).

dense (in-place LAPACK Cholesky, solves, triangular inverse), device (the same solves on JAX's
device, and the rule that places them), memory (checked big buffers and peak-memory
measurement), tri (banded storage of triangular factors). The two errors a user may catch are
re-exported here: :class:`NotPositiveDefiniteError` (a ``K̄`` that does not factorise) and
:class:`InsufficientMemory` (a build refused before it allocates).
"""

from gpg.linalg import dense, device, memory, tri
from gpg.linalg.dense import NotPositiveDefiniteError
from gpg.linalg.memory import InsufficientMemory

__all__ = ["InsufficientMemory", "NotPositiveDefiniteError", "dense", "device", "memory", "tri"]
