"""The functional environment: gymnax's interface under jit and vmap, automatic reset,
determinism, the documented observation, float32 by default, the in-domain flag, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.envs import EnvParams, QuadrotorEnv
from gpg.quadrotor.simple_model import SimpleModel


@pytest.fixture(scope="module")
def M(vehicle):
    return SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09)


@pytest.fixture(scope="module")
def env(vehicle, M):
    return QuadrotorEnv.create(vehicle, M)


def test_jit_vmap_autoreset_and_determinism(env):
    params = EnvParams.create("waypoints", max_steps=3)
    n = 8
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    obs, st = reset(jax.random.split(jax.random.key(0), n), params)
    assert obs.shape == (n, 25) and obs.dtype == jnp.float32  # float32 although x64 is on
    a = jnp.zeros((n, 4), jnp.float32)
    outs = []
    for i in range(3):
        obs, st, r, done, info = step(jax.random.split(jax.random.key(10 + i), n), st, a, params)
        outs.append((obs, r))
    assert bool(jnp.all(done)) and bool(jnp.all(info["truncated"]))
    assert bool(jnp.all(st.steps == 0)) and bool(jnp.all(st.time == 0))  # reset after step 3
    assert not np.allclose(info["final_obs"], obs)  # the finished episode's last observation
    # Same keys, same trajectories, bit for bit.
    obs2, st2 = reset(jax.random.split(jax.random.key(0), n), params)
    for i in range(3):
        obs2, st2, r2, *_ = step(jax.random.split(jax.random.key(10 + i), n), st2, a, params)
    np.testing.assert_array_equal(obs2, obs)
    # Each environment draws its own target, wind, mass and inertia.
    assert (
        np.unique(np.asarray(st.mass)).size == n
        and np.unique(np.asarray(st.wind.mean[:, 0])).size == n
    )


def test_hover_observation_is_the_documented_one(env):
    params = EnvParams.create(
        "hover", start_spread=0.0, start_tilt=0.0, start_speed=0.0, target_range=0.0
    )
    obs, st = jax.jit(env.reset)(jax.random.key(1), params)
    r = 0.0  # M flies M: its hover speed is the nominal one
    want = np.array([0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, r, r, r, r, 0, 0, 0])
    np.testing.assert_allclose(obs, want, atol=1e-6)
    np.testing.assert_allclose(st.quad.p, params.start)


def test_geometric_controller_flies_the_environment(vehicle, M):
    """The baseline reaches a hover target 3 m away in calm air: the frames and units of the
    environment agree with the controller's."""
    params = EnvParams.create(
        "hover",
        target_range=3.0,
        wind_max=0.0,
        gust_max=0.0,
        turbulence=0.0,
        mass_spread=0.0,
        inertia_spread=0.0,
    )
    for mode in ("ctbr", "rotor_speeds"):
        e = QuadrotorEnv.create(vehicle, M, action=mode)

        def body(st, k, e=e):
            obs, st, r, d, info = e.step_env(k, st, e.geometric_action(st, params), params)
            return st, info["position_error"]

        _, st = jax.jit(e.reset)(jax.random.key(2), params)
        _, err = jax.jit(
            lambda st: jax.lax.scan(body, st, jax.random.split(jax.random.key(3), 800))
        )(st)
        assert float(err[0]) > 0.5 and float(err[-1]) < 0.1, (mode, float(err[0]), float(err[-1]))


def test_out_of_domain_flag_and_policy(vehicle, synthetic_surrogate):
    env = QuadrotorEnv.create(vehicle, synthetic_surrogate)
    # A strong wind from behind: the airflow comes from the tail, outside the data's ±90° yaw.
    base = dict(wind_max=8.0, wind_heading=0.0, wind_spread=0.0, gust_max=0.0, turbulence=0.0)
    obs, st = jax.jit(env.reset)(jax.random.key(0), EnvParams.create(**base))
    a = jnp.zeros(4, jnp.float32)
    step = jax.jit(env.step)
    _, _, r_flag, done, info = step(jax.random.key(1), st, a, EnvParams.create(**base))
    assert not bool(info["in_domain"]) and not bool(done)
    _, _, r_pen, _, _ = step(jax.random.key(1), st, a, EnvParams.create(**base, ood_penalty=5.0))
    np.testing.assert_allclose(r_flag - r_pen, 5.0, rtol=1e-5)
    *_, done, info = step(jax.random.key(1), st, a, EnvParams.create(**base, ood_terminate=True))
    assert bool(done) and bool(info["terminated"])


def test_bad_input(env, vehicle, M):
    params = env.default_params
    obs, st = jax.jit(env.reset)(jax.random.key(0), params)
    with pytest.raises(ValueError, match="shape \\(4,\\)"):
        env.step(jax.random.key(0), st, jnp.zeros(3), params)
    with pytest.raises(ValueError, match="float array"):
        env.step(jax.random.key(0), st, jnp.zeros(4, jnp.int32), params)
    with pytest.raises(ValueError, match="shape \\(4,\\)"):  # also under jit: shapes are static
        jax.jit(env.step)(jax.random.key(0), st, jnp.zeros(5), params)
    nan = jnp.array([0.0, jnp.nan, 0.0, 0.0], jnp.float32)
    *_, done, info = jax.jit(env.step)(jax.random.key(0), st, nan, params)
    assert bool(info["bad_action"]) and bool(done)
    with pytest.raises(ValueError, match="unknown task"):
        EnvParams.create("circle")
    with pytest.raises(ValueError, match="unknown environment parameters \\['wind'\\]"):
        EnvParams.create(wind=3.0)
    with pytest.raises(ValueError, match="control_dt must be in"):
        EnvParams.create(control_dt=-0.01)
    with pytest.raises(ValueError, match="unknown action mode"):
        QuadrotorEnv.create(vehicle, M, action="rpm")
    with pytest.raises(ValueError, match="EnvParams"):
        env.step(jax.random.key(0), st, jnp.zeros(4), {"task": 0})


def test_differentiable_through_steps(vehicle, M):
    """Reverse mode through a rollout agrees with central differences (float64 environment)."""
    e = QuadrotorEnv.create(vehicle, M, dtype=jnp.float64)
    params = EnvParams.create("hover", dtype=jnp.float64)
    _, st = e.reset(jax.random.key(0), params)

    def ret(a0):
        def body(s, k):
            _, s, r, _, _ = e.step_env(k, s, a0, params)
            return s, r

        return jnp.sum(jax.lax.scan(body, st, jax.random.split(jax.random.key(1), 15))[1])

    ret = jax.jit(ret)
    a0 = jnp.array([0.1, 0.05, -0.02, 0.01])
    g = jax.jit(jax.grad(ret))(a0)
    h = 1e-6
    fd = jnp.array([(ret(a0 + h * d) - ret(a0 - h * d)) / (2 * h) for d in jnp.eye(4)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)
