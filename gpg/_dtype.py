"""The dtype policy (docs/design.md, "Dtype policy"): gpg never changes JAX's global settings;
what must run in float64 says so itself.

The Gram matrices of gradient-enhanced GPs are too ill-conditioned for float32 (a float32
Cholesky of the 8000-row ``K̄`` at data=default fails), and finite-difference gradients of the
generator need float64 steps. :func:`float64` runs a fitting or generating function inside
``jax.enable_x64(True)`` and casts the JAX float arrays among its arguments to float64, so it
gives the same result in a float32 program as in a float64 one.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp

P = ParamSpec("P")
R = TypeVar("R")


def _widen(x):
    if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating):
        return x.astype(jnp.float64)
    return x


def _widen_arg(a):
    """A JAX array or an equinox module (a Hyper, a Generator) widened; anything else as it is
    (mapping over a plain dict would rebuild it with its keys sorted)."""
    if isinstance(a, eqx.Module):
        return jax.tree.map(_widen, a)
    return _widen(a)


def float64(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` run with 64-bit JAX, its JAX float arguments (inside equinox modules too) widened."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with jax.enable_x64(True):
            args = tuple(_widen_arg(a) for a in args)
            kwargs = {k: _widen_arg(v) for k, v in kwargs.items()}
            return fn(*args, **kwargs)

    return wrapper
