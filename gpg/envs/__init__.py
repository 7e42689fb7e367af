"""gpg inside RL loops: a functional quadrotor environment in gymnax's conventions
(:mod:`gpg.envs.quadrotor`), Dryden turbulence (:mod:`gpg.envs.wind`), a controller's flights
from many resets at once (:mod:`gpg.envs.evaluation`), analytic policy gradients through it
(:mod:`gpg.envs.apg`, needs optax: the ``envs`` extra) and Gymnasium wrappers for NumPy and
torch users (:mod:`gpg.envs.gymnasium`, the ``envs`` extra: imported on its own,
``from gpg.envs.gymnasium import GymnasiumEnv``, since it needs Gymnasium)."""

from gpg.envs import apg, evaluation, wind
from gpg.envs.evaluation import evaluate
from gpg.envs.quadrotor import ACTIONS, OBS_SIZE, TASKS, EnvParams, EnvState, QuadrotorEnv

__all__ = [
    "ACTIONS",
    "OBS_SIZE",
    "TASKS",
    "EnvParams",
    "EnvState",
    "QuadrotorEnv",
    "apg",
    "evaluate",
    "evaluation",
    "wind",
]
