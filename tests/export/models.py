"""Small fitted surrogates of every exportable kind (40 cases, fixed hyperparameters), fitted
once per test session, and the query states the export tests share."""

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np

from gpg.quadrotor.frames import half_turn, to_airflow_frame
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_body_dataset, synthetic_dataset

BASE = {"hyper": {"fit": False, "lengthscale": 0.8}}
# Three bins for the hybrid and the local kinds (40 cases would give the hybrid one), a slab
# partition for gpgs_schur, 10 inducing points for PIC: every lookup and row layout is met.
CONFIGS = {
    "gpg": {},
    # near sets of 20 of the 40 points: each bin's variance its own (a wrong bin is seen)
    "gpgs_hybrid": {"partition": {"bins": 3, "points_per_bin": None}, "near": {"points": 20}},
    "gpgs": {"partition": {"bins": 3}},
    "gpg_pic": {"partition": {"bins": 3}, "inducing": {"points": 10}},
    "gpgs_schur": {"partition": {"bins": 2, "scheme": "slab"}},
}


@functools.cache
def dataset():
    return synthetic_dataset(40, seed=3, raw=False)[0]


@functools.cache
def fitted(kind: str) -> Surrogate:
    """``kind`` on the airflow-frame cases; ``"<kind>_body"`` on body-frame cases (inputs
    ``rpm, u, v, w``, the ball of air velocities); ``"<kind>_half"`` reading airflow from
    behind at the state's half-turn image (what the exports must repeat; the synthetic
    data's levels are not the image's, which does not matter to that)."""
    import warnings

    if kind.endswith("_half"):
        return dataclasses.replace(fitted(kind.removesuffix("_half")), half_turn=True)
    if kind.endswith("_body"):
        base = kind.removesuffix("_body")
        ds = synthetic_body_dataset(40, seed=3)[0]
        return Surrogate.fit(ds, base, {**BASE, **CONFIGS[base]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gpgs_schur warns that its far set is correlated
        return Surrogate.fit(dataset(), kind, {**BASE, **CONFIGS[kind]})


def states(n, seed, body=False):
    """Inside the box mostly, some outside (fast, sideways, backwards), some near vertical.
    ``body``: the last fifth 2.5 times faster, beyond the body frame's ball of 20 m/s (inside
    it the body frame has no other limit)."""
    rng = np.random.default_rng(seed)
    rpm = rng.uniform(500, 6500, (n, 4))
    euler = rng.uniform([-np.pi, -0.9, -1.2], [np.pi, 0.9, 1.2], (n, 3))
    v = rng.uniform(-12, 12, (n, 3))
    v[: n // 4, :2] *= 1e-3  # near vertical airflow: the frame-rate flag's region
    if body:
        v[-(n // 5) :] *= 2.5
    return rpm, euler, v


def gp_attitude(sur, rpm, euler, v):
    """The attitude the surrogate's GP reads a state at (the half-turn image's where it reads
    airflow from behind), for the frame-rate margins; un-jitted, to vmap."""
    if not sur.half_turn:
        return jnp.asarray(euler)
    eh = to_airflow_frame(euler, v, sur.hover_speed)[0]
    return jnp.where(jnp.cos(eh[0]) < 0, half_turn(rpm, euler)[1], jnp.asarray(euler))


def seam(sur, euler, v):
    """``|cos ψ_H|`` per state: how far from the half turn's seam (1 without it); un-jitted."""
    return jnp.abs(jnp.cos(to_airflow_frame(euler, v, sur.hover_speed)[0][0]))


def rel_err(got, want):
    """Per state, the largest error over the outputs of one vector, relative to the vector's
    scale (at least 1: a force of 1e-9 N is not held to 1e-10 of itself)."""
    got, want = np.asarray(got), np.asarray(want)
    return np.abs(got - want).max(axis=-1) / np.maximum(1.0, np.abs(want).max(axis=-1))
