"""A controller's flights in the environment, many at once: the figures the learning
experiment and the notebooks compare policies by."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from gpg.envs.quadrotor import EnvParams, QuadrotorEnv

__all__ = ["evaluate"]


def evaluate(
    env: QuadrotorEnv,
    params: EnvParams,
    act: Callable[[Array, Any], Array],
    key: Array,
    n_envs: int,
    steps: int,
) -> dict[str, Any]:
    """A controller flown from many resets at once, without automatic resets: the
    comparison of a learned policy with gpg's geometric controller on the same scenarios
    (same resets, targets, wind, gusts and turbulence for the same ``key``).

    Args:
        env: the environment (:class:`gpg.envs.QuadrotorEnv`).
        params: its parameters (:class:`gpg.envs.EnvParams`).
        act: ``act(obs, state) -> action``, the controller.
        key: draws the resets and the environment's noise.
        n_envs: the number of episodes, flown in one vmapped program.
        steps: the steps of each episode.

    Returns:
        ``rms_position_error_m`` and ``final_position_error_m`` (over episodes),
        ``in_domain_fraction``, ``crashed_fraction`` (episodes terminated by a crash), and
        ``error_per_step_m``, the mean position error at each step (for a figure).
    """

    def one(k):
        k0, k1 = jax.random.split(k)
        obs, st = env.reset_env(k0, params)

        def body(carry, kk):
            obs, st, dead = carry
            obs, st, _, _, info = env.step_env(kk, st, act(obs, st), params)
            dead = dead | info["terminated"]
            return (obs, st, dead), (info["position_error"], info["in_domain"], dead)

        _, out = jax.lax.scan(body, (obs, st, jnp.asarray(False)), jax.random.split(k1, steps))
        return out

    err, ok, dead = jax.jit(jax.vmap(one))(jax.random.split(key, n_envs))
    err, ok, dead = np.asarray(err, float), np.asarray(ok), np.asarray(dead)
    return {
        "rms_position_error_m": float(np.sqrt(np.mean(err**2))),
        "final_position_error_m": float(np.mean(err[:, -1])),
        "in_domain_fraction": float(np.mean(ok)),
        "crashed_fraction": float(np.mean(dead[:, -1])),
        "error_per_step_m": err.mean(0).tolist(),
    }
