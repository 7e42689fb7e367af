"""Analytic policy gradients: learn a policy by differentiating batched rollouts of
:class:`gpg.envs.QuadrotorEnv` (the surrogate's derivatives make the whole step differentiable).

The loss of a policy is minus the mean reward over ``n_envs`` episodes of ``horizon`` steps
from random resets, differentiated by reverse mode through every step (truncated
backpropagation through time). Two details make it train: the gradient through the state is
multiplied by ``decay`` at every step (its value is untouched), a short memory that keeps the
gradient of a long, unstable rollout bounded, and the steps do not stop at a termination (the
crash penalty keeps counting), so that ending an episode early never pays. Optimiser: optax's
Adam after global-norm clipping.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from gpg.envs.quadrotor import OBS_SIZE, EnvParams, QuadrotorEnv

__all__ = ["APGConfig", "MLPPolicy", "rollout", "train"]

# Observation scales of the default policy: position error /3 m, velocity error /2 m/s,
# attitude as is, rates /2 rad/s, rotor-speed offsets ×5, reference acceleration /2 m/s².
OBS_SCALE = np.concatenate(
    [
        np.full(3, 1 / 3),
        np.full(3, 1 / 2),
        np.ones(9),
        np.full(3, 1 / 2),
        np.full(4, 5.0),
        np.full(3, 1 / 2),
    ]
)


class MLPPolicy(eqx.Module):
    """``a = tanh(MLP(obs · scale))``: actions in [−1, 1]; the last layer starts small, so that
    the first policy commands about zero (hover thrust and no rates in ``ctbr`` mode)."""

    mlp: eqx.nn.MLP
    scale: Array

    @classmethod
    def create(
        cls, key: PRNGKeyArray, *, width: int = 64, depth: int = 2, dtype: Any = jnp.float32
    ) -> MLPPolicy:
        """A policy with random weights whose first actions are about zero.

        The last layer's weights are scaled by 0.1, so that the untrained policy commands
        about hover thrust and no rates (``ctbr``) instead of a random saturated action.

        Args:
            key: the weights' randomness.
            width: units per hidden layer.
            depth: hidden layers (tanh activations).
            dtype: the floating dtype of the weights and of the observation scales.

        Returns:
            The policy, mapping a (25,) observation to a (4,) action.
        """
        mlp = eqx.nn.MLP(OBS_SIZE, 4, width, depth, activation=jax.nn.tanh, key=key, dtype=dtype)
        last = mlp.layers[-1]
        mlp = eqx.tree_at(lambda m: m.layers[-1].weight, mlp, last.weight * 0.1)
        return cls(mlp, jnp.asarray(OBS_SCALE, dtype))

    def __call__(self, obs: Array) -> Array:
        return jnp.tanh(self.mlp(obs * self.scale))


def rollout(
    env: QuadrotorEnv,
    params: EnvParams,
    policy: Callable,
    key: PRNGKeyArray,
    horizon: int,
    *,
    decay: float = 1.0,
) -> tuple[Array, dict]:
    """One episode of ``horizon`` steps of ``policy`` from a reset, without automatic reset.

    With ``decay`` below 1 the gradient through the state is scaled by ``decay`` at every step
    while its value is untouched (``decay x + (1 − decay) stop_gradient(x)``): truncated
    backpropagation with a short memory. Steps go on after a termination.

    Args:
        env: the environment flown.
        params: the environment's parameters.
        policy: ``action = policy(obs)``, (25,) to (4,).
        key: the reset's and the steps' randomness.
        horizon: steps in the episode.
        decay: the gradient's memory per step, in (0, 1]; 1 keeps the full gradient.

    Returns:
        The summed reward and per-step arrays (horizon,): ``position_error``, ``in_domain``
        and ``terminated``.
    """

    def body(carry, k):
        obs, st = carry
        obs, st, r, _, info = env.step_env(k, st, policy(obs), params)
        if decay != 1.0:
            st = jax.tree.map(
                lambda x: (
                    decay * x + (1.0 - decay) * jax.lax.stop_gradient(x)
                    if eqx.is_inexact_array(x)
                    else x
                ),
                st,
            )
        return (obs, st), (r, info["position_error"], info["in_domain"], info["terminated"])

    k0, k1 = jax.random.split(key)
    obs, st = env.reset_env(k0, params)
    _, (r, err, ok, term) = jax.lax.scan(body, (obs, st), jax.random.split(k1, horizon))
    return jnp.sum(r), {"position_error": err, "in_domain": ok, "terminated": term}


@dataclass(frozen=True)
class APGConfig:
    """Training settings (see the module docstring); checked when made.

    Raises:
        ValueError: if ``n_envs``, ``horizon`` or ``iterations`` is not a positive integer,
            ``decay`` lies outside (0, 1], or ``learning_rate`` or ``clip_norm`` is not > 0.
    """

    n_envs: int = 64  # episodes per gradient step
    horizon: int = 300  # steps per episode
    decay: float = 0.98  # gradient memory per step
    learning_rate: float = 1e-3  # Adam
    clip_norm: float = 1.0  # global gradient norm
    iterations: int = 800  # gradient steps
    seed: int = 0

    def __post_init__(self):
        for k in ("n_envs", "horizon", "iterations"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"apg.{k} must be a positive integer, got {v!r}")
        if not 0.0 < self.decay <= 1.0:
            raise ValueError(f"apg.decay must be in (0, 1], got {self.decay!r}")
        for k in ("learning_rate", "clip_norm"):
            if not getattr(self, k) > 0:
                raise ValueError(f"apg.{k} must be > 0, got {getattr(self, k)!r}")


def train(
    env: QuadrotorEnv,
    params: EnvParams,
    policy: eqx.Module,
    cfg: APGConfig,
    *,
    progress: bool = True,
) -> tuple[eqx.Module, dict[str, np.ndarray]]:
    """Train ``policy`` by analytic policy gradients (see the module docstring).

    Each iteration differentiates the mean reward of ``cfg.n_envs`` rollouts from random
    resets (:func:`rollout`) and takes one step of Adam after global-norm clipping; the
    iterations' keys fold the iteration into ``cfg.seed``.

    Args:
        env: the environment flown.
        params: the environment's parameters (shared by all rollouts).
        policy: the policy to train, an equinox module (e.g. :class:`MLPPolicy`).
        cfg: the training settings.
        progress: whether to show a progress bar.

    Returns:
        The trained policy and the learning curve per iteration: ``loss`` (minus the mean
        reward per step), ``final_error`` (m, mean position error at the last step),
        ``in_domain`` (share of steps) and ``crashed`` (share of episodes).

    Raises:
        ImportError: if optax (the ``envs`` extra) is not installed.
    """
    try:
        import optax
    except ImportError as exc:  # an optional extra
        raise ImportError("gpg.envs.apg.train needs optax: pip install 'gpg[envs]'") from exc
    from tqdm.auto import tqdm

    opt = optax.chain(optax.clip_by_global_norm(cfg.clip_norm), optax.adam(cfg.learning_rate))
    state = opt.init(eqx.filter(policy, eqx.is_inexact_array))

    def loss(pol, key):
        keys = jax.random.split(key, cfg.n_envs)
        ret, info = jax.vmap(lambda k: rollout(env, params, pol, k, cfg.horizon, decay=cfg.decay))(
            keys
        )
        return -jnp.mean(ret) / cfg.horizon, info

    @eqx.filter_jit
    def step(pol, state, key):
        (value, info), g = eqx.filter_value_and_grad(loss, has_aux=True)(pol, key)
        updates, state = opt.update(g, state, eqx.filter(pol, eqx.is_inexact_array))
        curve = {
            "loss": value,
            "final_error": jnp.mean(info["position_error"][:, -1]),
            "in_domain": jnp.mean(info["in_domain"]),
            "crashed": jnp.mean(jnp.any(info["terminated"], axis=1)),
        }
        return eqx.apply_updates(pol, updates), state, curve

    key = jax.random.key(cfg.seed)
    rows = []
    for it in tqdm(range(cfg.iterations), desc="APG", disable=not progress):
        policy, state, curve = step(policy, state, jax.random.fold_in(key, it))
        rows.append({k: float(v) for k, v in curve.items()})
    return policy, {k: np.array([r[k] for r in rows]) for k in rows[0]}
