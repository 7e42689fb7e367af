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
from typing import Any, ParamSpec, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp

P = ParamSpec("P")
R = TypeVar("R")


def _widen(x):
    if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating):
        return x.astype(jnp.float64)
    return x


def _narrow(x) -> bool:
    return (
        isinstance(x, jax.Array)
        and jnp.issubdtype(x.dtype, jnp.floating)
        and x.dtype != jnp.float64
    )


@jax.jit
def _widen_all(tree):
    # One program for a module's narrow leaves: cast one by one outside a trace, each leaf's
    # shape compiled a conversion of its own (a surrogate's float32 factors, dozens of shapes).
    return jax.tree.map(lambda x: x.astype(jnp.float64), tree)


def _widen_arg(a):
    """A JAX array or an equinox module (a Hyper, a Generator) widened; anything else as it is
    (mapping over a plain dict would rebuild it with its keys sorted). A module's float64
    arrays are kept as they are, not copied."""
    if isinstance(a, eqx.Module):
        narrow, rest = eqx.partition(a, _narrow)
        if not jax.tree.leaves(narrow):
            return a
        return eqx.combine(_widen_all(narrow), rest)
    return _widen(a)


def float64(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` run with 64-bit JAX, its JAX float arguments (inside equinox modules too) widened,
    and every matrix product it traces at full precision (:mod:`gpg._precision`)."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with jax.enable_x64(True), jax.default_matmul_precision("highest"):
            args = tuple(_widen_arg(a) for a in args)
            kwargs = {k: _widen_arg(v) for k, v in kwargs.items()}
            return fn(*args, **kwargs)

    return wrapper


def in_model_dtype(model: Any, fn: Callable[[], R], *args: Any) -> R:
    """``fn()`` computed in ``model``'s float64 when the program runs in float32, its float
    outputs given back in float32 (docs/design.md, "Dtype policy": a query is computed in the
    model's dtype). A fitted model holds float64; without this, every operation of a float32
    program on it is truncated with a warning. Inside a trace (a user's ``jit``), or when the
    program is float64 or the model float32, ``fn()`` as it is: cast the model first
    (``Surrogate.astype``) to trace it in float32."""
    leaves = jax.tree.leaves((eqx.filter(model, eqx.is_array), args))
    if (
        jax.config.read("jax_enable_x64")
        or any(isinstance(a, jax.core.Tracer) for a in leaves)
        or not any(getattr(a, "dtype", None) == jnp.float64 for a in leaves)
    ):
        return fn()
    with jax.enable_x64(True):
        out = fn()
        return jax.tree.map(
            lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, out
        )
