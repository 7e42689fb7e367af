"""The built-in mid-fidelity generator: dataset inputs x to outputs y (CHARM + WOPWOP stand-in).

``x = (r1, r2, r3, r4, yaw, pitch, roll, V)`` (rpm, rad, m/s) in the dataset frame, where the
airspeed is ``v_air = (V, 0, 0)`` (the vehicle moves along +x); ``y = (Fx, Fy, Fz, Mx, My, Mz,
L1, L2, L3)``: aerodynamic force (N) and moment about the centre of mass (N·m) in the dataset
frame, without gravity, and the tonal OASPL (dB) at the three microphones.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float
from tqdm.auto import tqdm

from gpg import _interrupt
from gpg._dtype import float64
from gpg.quadrotor import acoustics, bemt
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.vehicle import Vehicle

# Bump when the physics changes, so that cached datasets are regenerated.
GENERATOR_VERSION = "1"
N_INPUTS = 8
N_GRAD = 7  # gradients exist for rpm and Euler angles, not for airspeed


class Generator(eqx.Module):
    """A vehicle plus the static settings of the aerodynamic and acoustic models."""

    vehicle: Vehicle
    bemt: bemt.BEMTConfig = bemt.BEMTConfig()
    acoustics: acoustics.AcousticsConfig = acoustics.AcousticsConfig()

    def __check_init__(self):
        self.vehicle.require_generator()  # a ValueError naming what a minimal vehicle lacks

    def __call__(self, x: Float[ArrayLike, " 8"]) -> Float[Array, " 9"]:
        """Outputs ``y`` (9,) at one dataset input ``x`` (8,)."""
        return evaluate(self, x)


def evaluate(gen: Generator, x: Float[ArrayLike, " 8"]) -> Float[Array, " 9"]:
    """``y(x)`` for one dataset case: wrench in the dataset frame and the three OASPLs."""
    x = jnp.asarray(x)
    res = bemt.aero(gen.vehicle, gen.bemt, x[:4], R_WB(x[4:7]), jnp.stack([x[7], 0.0, 0.0]))
    noise = acoustics.oaspl(gen.vehicle, res, gen.acoustics)
    return jnp.concatenate([res.force_W, res.torque_W, noise])


def jacobian(gen: Generator, x: Float[ArrayLike, " 8"]) -> Float[Array, "9 7"]:
    """Exact ``∂y/∂x_j`` for the 7 rpm and angle inputs, by forward-mode autodiff."""
    x = jnp.asarray(x)
    return jax.jacfwd(lambda head: evaluate(gen, jnp.concatenate([head, x[7:]])))(x[:7])


@eqx.filter_jit
def _batch(gen: Generator, X: Array) -> Array:
    return jax.vmap(partial(evaluate, gen))(X)


@eqx.filter_jit
def _batch_jac(gen: Generator, X: Array) -> tuple[Array, Array]:
    return jax.vmap(partial(evaluate, gen))(X), jax.vmap(partial(jacobian, gen))(X)


@float64
def evaluate_batch(
    gen: Generator,
    X: Float[ArrayLike, "N 8"],
    *,
    chunk: int = 512,
    with_jacobian: bool = False,
    progress: bool | str = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``y`` for many inputs (N, 9) as NumPy, in chunks of ``chunk`` rows (bounded memory).

    With ``with_jacobian`` also the exact Jacobians (N, 9, 7). The last chunk is padded to the
    chunk size, so one compiled program serves every chunk and the result of a row does not
    depend on where it falls (files are bit-identical across reruns and chunkings).
    """
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != N_INPUTS:
        raise ValueError(f"X must have shape (N, {N_INPUTS}), got {X.shape}")
    n = X.shape[0]
    ys, js = [], []
    desc = progress if isinstance(progress, str) else "generator"
    for start in tqdm(range(0, n, chunk), desc=desc, disable=not progress, unit="chunk"):
        _interrupt.check()  # a deferred Ctrl-C stops here, between compiled calls
        block = X[start : start + chunk]
        pad = chunk - block.shape[0]
        if pad:
            block = np.concatenate([block, np.repeat(block[-1:], pad, axis=0)])
        if with_jacobian:
            y, j = _batch_jac(gen, jnp.asarray(block))
            js.append(np.asarray(j)[: chunk - pad])
        else:
            y = _batch(gen, jnp.asarray(block))
        ys.append(np.asarray(y)[: chunk - pad])
    y = np.concatenate(ys) if ys else np.zeros((0, 9))
    if with_jacobian:
        return y, (np.concatenate(js) if js else np.zeros((0, 9, N_GRAD)))
    return y
