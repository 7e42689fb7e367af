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
    workers: int = 1,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``y`` for many inputs (N, 9) as NumPy, in chunks of ``chunk`` rows (bounded memory).

    With ``with_jacobian`` also the exact Jacobians (N, 9, 7). The last chunk is padded to the
    chunk size, so one compiled program serves every chunk and the result of a row does not
    depend on where it falls (files are bit-identical across reruns and chunkings).

    ``workers > 1`` evaluates the chunks in that many worker processes (each compiles the same
    program once). The chunks are the same as with one process, so the result is bit-identical
    whatever the number of workers; the work is embarrassingly parallel, one chunk per task.
    """
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != N_INPUTS:
        raise ValueError(f"X must have shape (N, {N_INPUTS}), got {X.shape}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    n = X.shape[0]
    starts = range(0, n, chunk)
    desc = progress if isinstance(progress, str) else "generator"
    bar = tqdm(total=len(starts), desc=desc, disable=not progress, unit="chunk")
    if workers > 1 and len(starts) > 1:
        parts = _evaluate_in_processes(gen, X, chunk, with_jacobian, workers, bar)
    else:
        parts = []
        for start in starts:
            _interrupt.check()  # a deferred Ctrl-C stops here, between compiled calls
            parts.append(_evaluate_chunk(gen, X[start : start + chunk], chunk, with_jacobian))
            bar.update()
    bar.close()
    y = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 9))
    if with_jacobian:
        return y, (np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 9, N_GRAD)))
    return y


def _evaluate_chunk(
    gen: Generator, block: np.ndarray, chunk: int, with_jacobian: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """One chunk, padded to ``chunk`` rows with copies of its last row (the same compiled
    program for every chunk)."""
    rows = block.shape[0]
    if rows < chunk:
        block = np.concatenate([block, np.repeat(block[-1:], chunk - rows, axis=0)])
    if with_jacobian:
        y, j = _batch_jac(gen, jnp.asarray(block))
        return np.asarray(y)[:rows], np.asarray(j)[:rows]
    return np.asarray(_batch(gen, jnp.asarray(block)))[:rows], None


_WORKER_GEN: Generator | None = None


def _worker_init(gen_np: Generator) -> None:
    import signal

    # Ctrl-C goes to the whole process group: the parent stops the pool at its next safe
    # point; a worker interrupted inside XLA could crash instead.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    jax.config.update("jax_enable_x64", True)
    global _WORKER_GEN
    # The generator travels with NumPy leaves and becomes JAX arrays only now, after x64 is
    # on: JAX arrays unpickled earlier would have been made float32.
    _WORKER_GEN = jax.tree.map(jnp.asarray, gen_np)


def _worker_chunk(block: np.ndarray, chunk: int, with_jacobian: bool):
    return _evaluate_chunk(_WORKER_GEN, block, chunk, with_jacobian)


def _evaluate_in_processes(gen, X, chunk, with_jacobian, workers, bar):
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # spawn, not fork: a forked child would inherit XLA's threads in an undefined state.
    ctx = multiprocessing.get_context("spawn")
    starts = list(range(0, X.shape[0], chunk))
    parts: list = [None] * len(starts)
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(starts)),
        mp_context=ctx,
        initializer=_worker_init,
        initargs=(jax.tree.map(np.asarray, gen),),
    )
    try:
        futures = {
            pool.submit(_worker_chunk, X[s : s + chunk], chunk, with_jacobian): i
            for i, s in enumerate(starts)
        }
        pending = set(futures)
        while pending:
            _interrupt.check()
            done, pending = _wait(pending)
            for f in done:
                parts[futures[f]] = f.result()
                bar.update()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return parts


def _wait(pending):
    from concurrent.futures import FIRST_COMPLETED, wait

    # A timeout keeps the loop returning to the interrupt check while workers compute.
    return wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
