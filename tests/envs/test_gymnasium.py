"""The Gymnasium wrappers: Gymnasium's own checker, and the vector environment equal to the
functional one it wraps."""

import warnings

import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from gpg.envs import EnvParams, QuadrotorEnv
from gpg.envs.gymnasium import GymnasiumEnv, GymnasiumVectorEnv
from gpg.quadrotor.simple_model import SimpleModel


@pytest.fixture(scope="module")
def env(vehicle):
    return QuadrotorEnv.create(vehicle, SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09))


def test_single_environment_passes_gymnasiums_checker(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(GymnasiumEnv(env), skip_render_check=True)
    assert [str(w.message) for w in caught if "gymnasium" in str(w.filename)] == []


def test_vector_environment(env):
    params = EnvParams.create("hover", max_steps=4)
    v = GymnasiumVectorEnv(env, 6, params)
    obs, _ = v.reset(seed=3)
    assert obs.shape == (6, 25) and obs.dtype == np.float32 and v.observation_space.contains(obs)
    again, _ = GymnasiumVectorEnv(env, 6, params).reset(seed=3)
    np.testing.assert_array_equal(obs, again)  # seeded
    for _ in range(4):
        obs, rew, term, trunc, info = v.step(np.zeros((6, 4), np.float32))
        assert rew.shape == (6,) and v.observation_space.contains(obs)
    assert np.all(trunc) and np.all(info["_final_obs"]) and info["final_obs"].shape == (6, 25)
    with pytest.raises(ValueError, match="shape \\(6, 4\\)"):
        v.step(np.zeros((5, 4)))
    # One step of the wrapper is the vmapped functional step with the wrapper's keys.
    v2 = GymnasiumVectorEnv(env, 6, params)
    v2.reset(seed=3)
    rng = np.random.default_rng(3)
    keys = jax.random.split(jax.random.key(int(rng.integers(0, 2**63 - 1))), 6)
    obs0, st = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    a = np.full((6, 4), 0.1, np.float32)
    keys = jax.random.split(jax.random.key(int(rng.integers(0, 2**63 - 1))), 6)
    want = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))(keys, st, a, params)[0]
    np.testing.assert_array_equal(v2.step(a)[0], want)
