"""Analytic policy gradients: training steps run through the differentiable environment (the
gradient through steps is checked against finite differences in test_quadrotor_env)."""

import equinox as eqx
import jax
import numpy as np

from gpg.envs import EnvParams, QuadrotorEnv, apg
from gpg.quadrotor.simple_model import SimpleModel


def test_training_steps_run_and_move_the_policy(vehicle):
    env = QuadrotorEnv.create(vehicle, SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09))
    pol = apg.MLPPolicy.create(jax.random.key(0), width=8)
    cfg = apg.APGConfig(n_envs=2, horizon=5, iterations=2)
    trained, curve = apg.train(env, EnvParams.create("hover"), pol, cfg, progress=False)
    assert set(curve) == {"loss", "final_error", "in_domain", "crashed"}
    assert curve["loss"].shape == (2,) and np.all(np.isfinite(curve["loss"]))
    assert not eqx.tree_equal(trained, pol)
    assert trained(np.zeros(25, np.float32)).shape == (4,)
