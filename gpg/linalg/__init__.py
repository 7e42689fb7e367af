"""Dense linear algebra for matrices that fill the machine (docs/design.md, Architecture).

dense (in-place LAPACK Cholesky, solves, triangular inverse), device (the same solves on JAX's
device, and the rule that places them), memory (checked big buffers and peak-memory
measurement), tri (banded storage of triangular factors).
"""
