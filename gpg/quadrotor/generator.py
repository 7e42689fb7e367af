"""The built-in mid-fidelity generator: dataset inputs x to outputs y (CHARM + WOPWOP stand-in).

``x = (r1, r2, r3, r4, yaw, pitch, roll, V)`` (rpm, rad, m/s) in the dataset frame, where the
airspeed is ``v_air = (V, 0, 0)`` (the vehicle moves along +x); ``y = (Fx, Fy, Fz, Mx, My, Mz,
L1, L2, L3)``: aerodynamic force (N) and moment about the centre of mass (N·m) in the dataset
frame, without gravity, and the tonal OASPL (dB) at the three microphones.

The body frame (``frame="body"``): ``x_B = (r1, r2, r3, r4, u, v, w)``, the air velocity of
the vehicle in its own frame (FRD, m/s; from any direction, hover at ``0``), and ``y`` the same
quantities in the body frame: force and moment in FRD, the levels at microphones fixed to the
body (the same positions, read in the body frame instead of the airflow frame).
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

__all__ = [
    "GENERATOR_VERSION",
    "Generator",
    "evaluate",
    "evaluate_batch",
    "evaluate_body",
    "jacobian",
    "jacobian_body",
    "vortex_ring_state",
]

# Bump when the physics changes, so that cached datasets are regenerated.
GENERATOR_VERSION = "1"
N_INPUTS = 8
N_GRAD = 7  # gradients exist for rpm and Euler angles, not for airspeed
BODY_INPUTS = 7  # the body frame: rpm and the body-frame air velocity, a gradient along each


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
    """``y(x)`` for one dataset case: wrench in the dataset frame and the three OASPLs.

    The BEMT wrench (:func:`gpg.quadrotor.bemt.aero`) at attitude ``R_WB(yaw, pitch, roll)``
    in the airflow ``v_air = (V, 0, 0)``, and the tonal levels
    (:func:`gpg.quadrotor.acoustics.oaspl`) of the same loads.

    Args:
        gen: the generator (vehicle and model settings).
        x: (8,) input ``(r1..r4, yaw, pitch, roll, V)`` (rpm, rad, m/s).

    Returns:
        The (9,) output ``(Fx, Fy, Fz, Mx, My, Mz, L1, L2, L3)`` (N, N·m, dB).
    """
    x = jnp.asarray(x)
    res = bemt.aero(gen.vehicle, gen.bemt, x[:4], R_WB(x[4:7]), jnp.stack([x[7], 0.0, 0.0]))
    noise = acoustics.oaspl(gen.vehicle, res, gen.acoustics)
    return jnp.concatenate([res.force_W, res.torque_W, noise])


def evaluate_body(gen: Generator, x: Float[ArrayLike, " 7"]) -> Float[Array, " 9"]:
    """``y_B(x_B)`` for one body-frame case: the wrench in the body frame and the OASPLs.

    The same physics as :func:`evaluate` with the attitude the identity and the air velocity
    ``(u, v, w)``: ``evaluate(R_WB(θ), V) = R_WB(θ) evaluate_body(R_WB(θ)ᵀ V e_x)``.

    Args:
        gen: the generator.
        x: (7,) body-frame input ``(r1..r4, u, v, w)`` (rpm, m/s FRD).

    Returns:
        The (9,) output in the body frame: force (N), moment (N·m), levels (dB).
    """
    x = jnp.asarray(x)
    res = bemt.aero(gen.vehicle, gen.bemt, x[:4], jnp.eye(3, dtype=x.dtype), x[4:7])
    noise = acoustics.oaspl(gen.vehicle, res, gen.acoustics)
    return jnp.concatenate([res.force_W, res.torque_W, noise])


def jacobian_body(gen: Generator, x: Float[ArrayLike, " 7"]) -> Float[Array, "9 7"]:
    """Exact ``∂y_B/∂x_B`` along all seven body-frame inputs, by forward-mode autodiff.

    Args:
        gen: the generator.
        x: (7,) body-frame input ``(r1..r4, u, v, w)``.

    Returns:
        The (9, 7) Jacobian of :func:`evaluate_body`.
    """
    return jax.jacfwd(partial(evaluate_body, gen))(jnp.asarray(x))


def jacobian(gen: Generator, x: Float[ArrayLike, " 8"]) -> Float[Array, "9 7"]:
    """Exact ``∂y/∂x_j`` for the 7 rpm and angle inputs, by forward-mode autodiff.

    The airspeed ``V`` is held: the dataset has no gradient along it.

    Args:
        gen: the generator.
        x: (8,) input ``(r1..r4, yaw, pitch, roll, V)``.

    Returns:
        The (9, 7) Jacobian of :func:`evaluate` along ``r1..r4, yaw, pitch, roll``.
    """
    x = jnp.asarray(x)
    return jax.jacfwd(lambda head: evaluate(gen, jnp.concatenate([head, x[7:]])))(x[:7])


_FNS = {"airflow": (evaluate, jacobian), "body": (evaluate_body, jacobian_body)}


def _fns(X: Array):
    """The value and Jacobian functions of ``X``'s frame, told by its width (static)."""
    return _FNS["airflow" if X.shape[1] == N_INPUTS else "body"]


@eqx.filter_jit
def _batch(gen: Generator, X: Array) -> Array:
    return jax.vmap(partial(_fns(X)[0], gen))(X)


@eqx.filter_jit
def _batch_jac(gen: Generator, X: Array) -> tuple[Array, Array]:
    f, jac = _fns(X)
    return jax.vmap(partial(f, gen))(X), jax.vmap(partial(jac, gen))(X)


@float64
def evaluate_batch(
    gen: Generator,
    X: Float[ArrayLike, "N 8"],
    *,
    chunk: int = 512,
    with_jacobian: bool = False,
    progress: bool | str = False,
    workers: int = 1,
    frame: str = "airflow",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``y`` for many inputs (N, 9) as NumPy, in chunks of ``chunk`` rows (bounded memory);
    ``X`` (N, 8) in the airflow frame, (N, 7) in the body frame (``frame="body"``).

    With ``with_jacobian`` also the exact Jacobians (N, 9, 7). The last chunk is padded to the
    chunk size, so one compiled program serves every chunk and the result of a row does not
    depend on where it falls (files are bit-identical across reruns and chunkings).

    ``workers > 1`` evaluates the chunks in that many worker processes (each compiles the same
    program once). The chunks are the same as with one process, so the result is bit-identical
    whatever the number of workers; the work is embarrassingly parallel, one chunk per task.
    Runs in float64; a deferred Ctrl-C stops between chunks.

    Args:
        gen: the generator.
        X: (N, 8) airflow-frame inputs, or (N, 7) body-frame ones with ``frame="body"``.
        chunk: rows per compiled call (the memory bound).
        with_jacobian: also return the Jacobians.
        progress: show a progress bar (a string: its label).
        workers: the number of worker processes (1: this process).
        frame: ``"airflow"`` or ``"body"``, the frame of ``X`` and of the outputs.

    Returns:
        ``y`` (N, 9) as NumPy; with ``with_jacobian`` the pair ``(y, J)`` with ``J``
        (N, 9, 7).

    Raises:
        ValueError: if ``frame`` is unknown, ``X`` is not (N, 8) or (N, 7) as the frame needs,
            or ``workers`` is not a positive integer.
    """
    X = np.asarray(X, dtype=np.float64)
    if frame not in _FNS:
        raise ValueError(f"frame must be 'airflow' or 'body', got {frame!r}")
    d = N_INPUTS if frame == "airflow" else BODY_INPUTS
    if X.ndim != 2 or X.shape[1] != d:
        raise ValueError(f"X must have shape (N, {d}) in the {frame} frame, got {X.shape}")
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


# The vortex-ring state's region in descent, in units of the hover induced velocity v_h: from
# a quarter of v_h to 1.75 v_h of descent through the disk, while the edgewise air is slower
# than v_h (W. Johnson, "Model for vortex ring state influence on rotorcraft flight dynamics",
# NASA/TP-2005-213477: the boundaries of its onset and end from flight and tunnel data).
VRS_DESCENT = (0.25, 1.75)
VRS_EDGEWISE = 1.0


def vortex_ring_state(
    vehicle: Vehicle, x_body: Float[ArrayLike, "N 7"], force_body: Float[ArrayLike, "N 3"]
) -> np.ndarray:
    """Which body-frame cases (N,) lie in the vortex-ring state, where this generator's inflow
    is a regularisation (``BEMTConfig.kappa2``: one momentum root where the real flow is
    unsteady and momentum theory has none or several) and its loads should not be trusted.

    Per case: ``v_h = √(T / (8 ρ A))`` from the thrust of the four rotors ``T = −F_z`` (the
    body-frame force's ``z``, N), the descent through the disks ``w`` (the body-frame air's
    ``z``, positive down: the air comes up through the rotors) and the edgewise speed
    ``√(u² + v²)``: flagged where ``0.25 v_h ≤ w ≤ 1.75 v_h`` and the edgewise speed is below
    ``v_h`` (:data:`VRS_DESCENT`, :data:`VRS_EDGEWISE`).

    Args:
        vehicle: the vehicle, for its rotor radius and the air density.
        x_body: (N, 7) body-frame inputs ``(r1..r4, u, v, w)``.
        force_body: (N, 3) body-frame aerodynamic force (N) of those cases.

    Returns:
        A (N,) boolean array, True where the case lies in the vortex-ring state.
    """
    x = np.asarray(x_body, float)
    thrust = np.maximum(-np.asarray(force_body, float)[:, 2], 0.0)
    area = np.pi * float(vehicle.rotor.radius) ** 2
    v_h = np.sqrt(thrust / (8.0 * float(vehicle.air_density) * area))
    w, edge = x[:, 6], np.hypot(x[:, 4], x[:, 5])
    lo, hi = VRS_DESCENT
    return (v_h > 0) & (w >= lo * v_h) & (w <= hi * v_h) & (edge < VRS_EDGEWISE * v_h)
