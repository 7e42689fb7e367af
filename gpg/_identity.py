"""Modules compared and hashed by identity, so that ``jax.jit(module.method)`` works.

``jax.jit`` hashes the function it compiles; an equinox bound method hashes its module, and a
module holding arrays is not hashable. The objects users call like functions (an environment's
``step``, an MPC's ``solve``) therefore compare by identity: ``jax.jit(env.step)`` then works
as it does in gymnax, and the module's arrays, closed over, are passed to the compiled function
as arguments, not embedded in it.
"""

from __future__ import annotations

import equinox as eqx


class ByIdentity(eqx.Module):
    def __hash__(self) -> int:
        return id(self)

    def __eq__(self, other) -> bool:
        return self is other
