"""Gymnasium wrappers of :class:`gpg.envs.QuadrotorEnv` (``pip install 'gpg[envs]'``), NumPy in
and out, for Stable-Baselines3 and torch users.

* :class:`GymnasiumEnv`: one environment, a ``gymnasium.Env`` (passes Gymnasium's own
  ``check_env``); no automatic reset, as Gymnasium expects. SB3: ``DummyVecEnv([lambda:
  GymnasiumEnv(env)])``.
* :class:`GymnasiumVectorEnv`: ``num_envs`` environments stepped together by one compiled,
  vmapped JAX call, a ``gymnasium.vector.VectorEnv`` with same-step automatic reset
  (``infos["final_obs"]`` holds the finished episodes' last observations, ``"_final_obs"`` where).
  torch: ``gymnasium.wrappers.vector.NumpyToTorch(GymnasiumVectorEnv(env, 1024))``.

Randomness: each call draws its JAX key from the wrapper's seeded generator, so a seeded reset
gives the same episode every time.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

try:
    import gymnasium as gym
    from gymnasium import spaces
    from gymnasium.vector import AutoresetMode, VectorEnv
    from gymnasium.vector.utils import batch_space
except ImportError as exc:  # an optional extra
    raise ImportError("gpg.envs.gymnasium needs Gymnasium: pip install 'gpg[envs]'") from exc

from gpg.envs.quadrotor import OBS_SIZE, EnvParams, QuadrotorEnv

__all__ = ["GymnasiumEnv", "GymnasiumVectorEnv"]


def _spaces(env: QuadrotorEnv) -> tuple[spaces.Box, spaces.Box]:
    dt = np.dtype(env.dtype)
    # Finite bounds, as Gymnasium's checker asks: the attitude entries lie in [−1, 1]; errors,
    # rates and speeds within ±1e4 hold for any episode that has not yet been ended.
    hi = np.full(OBS_SIZE, 1e4, dtype=dt)
    hi[6:15] = 1.0
    obs = spaces.Box(-hi, hi, (OBS_SIZE,), dtype=dt)
    act = spaces.Box(-1.0, 1.0, (4,), dtype=dt)
    return obs, act


def _key(rng: np.random.Generator) -> jax.Array:
    return jax.random.key(int(rng.integers(0, 2**63 - 1)))


def _info(info: dict[str, Any]) -> dict[str, Any]:
    return {k: np.asarray(v) for k, v in info.items() if k != "final_obs"}


class GymnasiumEnv(gym.Env):
    """One :class:`QuadrotorEnv` as a ``gymnasium.Env`` (see the module docstring).

    Args:
        env: the environment wrapped.
        params: its parameters; None for its :attr:`QuadrotorEnv.default_params`.

    Raises:
        ValueError: if ``env`` is not a :class:`QuadrotorEnv` or ``params`` not an
            :class:`EnvParams`.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: QuadrotorEnv, params: EnvParams | None = None):
        if not isinstance(env, QuadrotorEnv):
            raise ValueError(f"env must be a gpg.envs.QuadrotorEnv, got {type(env).__name__}")
        self.env = env
        self.params = env._params(params)
        self.observation_space, self.action_space = _spaces(env)
        self._reset = jax.jit(env.reset_env)
        self._step = jax.jit(env.step_env)
        self._state = None

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode, as ``gymnasium.Env.reset``.

        Args:
            seed: seeds the wrapper's generator (Gymnasium's ``np_random``), from which every
                later key is drawn; None keeps the generator's stream.
            options: unused (Gymnasium's signature).

        Returns:
            The first observation (25,) and an empty ``info``.
        """
        super().reset(seed=seed)
        obs, self._state = self._reset(_key(self.np_random), self.params)
        return np.asarray(obs), {}

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, np.ndarray]]:
        """One control step, as ``gymnasium.Env.step``: no automatic reset.

        Args:
            action: (4,) the action in [−1, 1] (clipped by the environment).

        Returns:
            The observation (25,), the reward, ``terminated``, ``truncated`` and ``info``
            (the environment's, as NumPy: ``in_domain``, ``bad_action``, ``position_error``,
            ...).

        Raises:
            ValueError: if called before :meth:`reset`.
        """
        if self._state is None:
            raise ValueError("call reset() before step()")
        a = np.asarray(action, dtype=self.action_space.dtype)
        obs, self._state, reward, _, info = self._step(
            _key(self.np_random), self._state, a, self.params
        )
        return (
            np.asarray(obs),
            float(reward),
            bool(info["terminated"]),
            bool(info["truncated"]),
            _info(info),
        )


class GymnasiumVectorEnv(VectorEnv):
    """``num_envs`` :class:`QuadrotorEnv` episodes as a ``gymnasium.vector.VectorEnv``.

    One compiled, vmapped call steps them all, with same-step automatic reset (see the module
    docstring).

    Args:
        env: the environment wrapped.
        num_envs: environments stepped together.
        params: shared by all environments, or (``batched_params``) an :class:`EnvParams`
            batched along a leading axis of size ``num_envs``; None for the defaults.
        batched_params: whether ``params`` carries one set per environment.

    Raises:
        ValueError: if ``env`` is not a :class:`QuadrotorEnv`, ``num_envs`` is not a positive
            integer or ``params`` is not an :class:`EnvParams`.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        env: QuadrotorEnv,
        num_envs: int,
        params: EnvParams | None = None,
        *,
        batched_params: bool = False,
    ):
        if not isinstance(env, QuadrotorEnv):
            raise ValueError(f"env must be a gpg.envs.QuadrotorEnv, got {type(env).__name__}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.env = env
        self.num_envs = num_envs
        self.params = env._params(params)
        self.single_observation_space, self.single_action_space = _spaces(env)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        p_axis = 0 if batched_params else None
        self._reset = jax.jit(jax.vmap(env.reset, in_axes=(0, p_axis)))
        self._step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, p_axis)))
        self._rng = np.random.default_rng()
        self._state = None

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """New episodes in every environment, as ``gymnasium.vector.VectorEnv.reset``.

        Args:
            seed: reseeds the wrapper's generator, from which every later key is drawn; None
                keeps the generator's stream.
            options: unused (Gymnasium's signature).

        Returns:
            The first observations (num_envs, 25) and an empty ``infos``.
        """
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        keys = jax.random.split(_key(self._rng), self.num_envs)
        obs, self._state = self._reset(keys, self.params)
        return np.asarray(obs), {}

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """One control step of every environment, with same-step automatic reset.

        A finished environment returns its next episode's first observation;
        ``infos["final_obs"]`` holds every environment's last observation of the step and
        ``infos["_final_obs"]`` says which of them finished.

        Args:
            actions: (num_envs, 4) the actions in [−1, 1] (clipped by the environment).

        Returns:
            The observations (num_envs, 25), rewards, ``terminated`` and ``truncated``
            (num_envs,) and ``infos`` (the environment's, as NumPy, with ``final_obs`` and
            ``_final_obs``).

        Raises:
            ValueError: if called before :meth:`reset`, or for actions of another shape.
        """
        if self._state is None:
            raise ValueError("call reset() before step()")
        a = np.asarray(actions, dtype=self.single_action_space.dtype)
        if a.shape != (self.num_envs, 4):
            raise ValueError(f"actions must have shape ({self.num_envs}, 4), got {a.shape}")
        keys = jax.random.split(_key(self._rng), self.num_envs)
        obs, self._state, reward, done, info = self._step(keys, self._state, a, self.params)
        infos = _info(info)
        infos["final_obs"] = np.asarray(info["final_obs"])
        infos["_final_obs"] = np.asarray(done)
        return (
            np.asarray(obs),
            np.asarray(reward),
            infos["terminated"],
            infos["truncated"],
            infos,
        )
