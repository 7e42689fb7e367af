"""Host arrays onto JAX's device without compiling anything, and host loops compiled once.

``jnp.asarray`` of a NumPy array, outside a trace, lifts it through a staged identity
(``lax.stage``) in this JAX: a program compiled for every new shape and dtype. Building a model
from host data meets many shapes once each (the bands of a factor, a checkpoint's arrays, the
rows of a Gram matrix in chunks), and each paid a compilation that ``jax.device_put`` does not
need: it copies the bytes.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def asarray(x: Any) -> jax.Array:
    """``jnp.asarray(x)``, a NumPy array copied to the device by ``jax.device_put``: the same
    array (its dtype canonicalised as JAX's config says, uncommitted, not weakly typed) and,
    inside a trace, the same values. The host copy is made here, before the transfer: on the
    CPU, ``device_put`` may take the array's own memory as the device buffer (seen whatever
    ``may_alias`` said), so that writing to ``x`` afterwards would change the JAX array, and
    rows of a buffer given back after the call would be read as zeros. Anything else goes to
    ``jnp.asarray`` as it is."""
    if type(x) is np.ndarray:
        return jax.device_put(np.array(x, order="C"))
    return jnp.asarray(x)


def as_stored(a: np.ndarray) -> jax.Array:
    """:func:`asarray` of ``a`` in its own dtype: a float64 array stays float64 even where
    JAX's x64 is off (a checkpoint's arrays, rows computed in float64 for a float32 program)."""
    with jax.enable_x64(a.dtype.itemsize > 4):
        return asarray(a)


@eqx.filter_jit
def _each_row(fn, X):
    return jax.vmap(fn)(X)


def each_row(fn: Any, X: Any) -> Any:
    """``fn`` at every row of ``X`` in one compiled program, as NumPy arrays: ``jax.vmap``
    outside a trace runs op by op, and each operation compiles on its own for every new
    shape (a few milliseconds each, for a model's columns at a part of flights a few hundred
    of them). ``fn`` an equinox Module (its arrays traced, its program kept for its structure
    and ``X``'s shape) or a function."""
    return jax.tree.map(np.asarray, _each_row(fn, np.asarray(X)))
