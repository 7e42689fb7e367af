"""Matrix products at full precision, whatever the backend's default.

On NVIDIA GPUs JAX runs a float32 ``dot_general`` without a stated precision in TF32 (a 10-bit
mantissa): a float32 surrogate then differs from its float64 self by far more than
on the CPU, and nothing says so. gpg does not depend on its caller's global setting
(``JAX_DEFAULT_MATMUL_PRECISION``): every function of its numerics that contracts arrays is
traced under :func:`highest`, so every ``dot_general`` it emits carries ``Precision.HIGHEST``
(float32 products in float32 on every backend; float64 products are unaffected). The context
is read when a function is traced, and the precision is then a parameter of the traced
product, kept by ``jit``, ``vmap``, ``jvp`` and transposition. Custom batching and derivative
rules are traced on their own (when a caller batches or differentiates a traced call), so
they carry the decorator themselves. ``tests/test_precision.py`` walks the programs of the
public predictions and fits and fails on a product without it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import jax

__all__ = ["PRECISION", "highest"]

P = ParamSpec("P")
R = TypeVar("R")

PRECISION = jax.lax.Precision.HIGHEST  # for products that state it themselves


def highest(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` traced (or run eagerly) with every matrix product at ``Precision.HIGHEST``."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapper
