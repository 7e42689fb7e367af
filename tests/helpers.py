"""Test helpers: synthetic datasets with analytic gradients (no generator needed, fast to
build), configs composed as the entry points do, a check of JSON results, and a count of the
programs a call compiles."""

import logging
import math
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.sampling import FDSteps, latin_hypercube, raw_samples
from gpg.quadrotor.vehicle import vehicle_config

LO, HI = Bounds().arrays()


def compiles(caplog, fn):
    """``fn()`` and how many XLA programs it compiled (JAX's compile log, which ``caplog``
    captures): what a test of "one compiled program, none the second time" counts."""
    caplog.clear()
    with jax.log_compiles(True), caplog.at_level(logging.WARNING, logger="jax"):
        out = fn()
    return out, len([r for r in caplog.records if "Finished XLA compilation" in r.getMessage()])


def smooth(x, W):
    """Outputs (N, 9) and exact Jacobians (N, 9, 7) of a smooth function of the scaled inputs."""
    u = 2 * (x - LO) / (HI - LO) - 1
    z = u @ W
    y = np.sin(z) + 0.3 * z
    dz = (np.cos(z) + 0.3)[:, :, None] * (W.T[None, :, :7] * (2 / (HI - LO))[None, None, :7])
    y = y * np.array([3, 3, 20, 0.5, 0.5, 0.2, 5, 5, 5]) + np.array(
        [0, 0, -26, 0, 0, 0, 60, 60, 50]
    )
    dz = dz * np.array([3, 3, 20, 0.5, 0.5, 0.2, 5, 5, 5])[None, :, None]
    return y, dz


def synthetic_dataset(n=60, seed=0, raw=True):
    rng = np.random.default_rng(seed)
    W = rng.normal(scale=0.5, size=(8, 9))
    x = latin_hypercube(n, Bounds(), seed)
    y, J = smooth(x, W)
    kw = {}
    if raw:
        xr, _ = raw_samples(x, FDSteps())
        kw = {"x_raw": xr, "y_raw": smooth(xr, W)[0]}
    return _synthetic(x, y, J, {"name": "synthetic"}, **kw), W


def _synthetic(x, y, J, meta, **kw):
    """A dataset of nine outputs ``y`` and their gradients ``J``, with ``M``'s coefficients
    and the vehicle whose layout ``M`` uses."""
    return Dataset(
        x=x,
        y_aero=y[:, :6],
        jac_aero=J[:, :6],
        y_noise=y[:, 6:],
        jac_noise=J[:, 6:],
        meta={
            "simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9},
            "vehicle": vehicle_config("sui_endurance"),
            **meta,
        },
        **kw,
    )


def compose_plain(name: str, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """``conf/<name>.yaml`` composed by Hydra with ``overrides``, as plain values (what the
    ``experiments`` entry points pass to ``experiments.runs``)."""
    from hydra import compose, initialize_config_dir

    from experiments._hydra import plain
    from experiments.runs.config import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return plain(compose(config_name=name, overrides=list(overrides)))


def finite_numbers(obj: Any) -> bool:
    """True when every number in a JSON-like structure is finite (None allowed)."""
    if isinstance(obj, dict):
        return all(finite_numbers(v) for v in obj.values())
    if isinstance(obj, list):
        return all(finite_numbers(v) for v in obj)
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return True
    if isinstance(obj, int | float):
        return math.isfinite(obj)
    return True


# The Higham–Mary probabilistic bound: a sum of n terms rounded with unit roundoff u is off by
# at most λ √n u Σ|terms| with probability ≥ 1 − 2 exp(−λ²/2) (λ = 5: 1 − 7e-6), whatever
# order the machine sums in. The order is what differs between machines: XLA sends float32
# products to YNNPACK, which picks its kernels and blocking from the CPU it detects at run time
# (``--xla_cpu_max_isa`` does not limit it; ``--xla_cpu_experimental_ynn_fusion_type=`` turns
# it off and moves a float32 variance by ~1e-4 relative).
LAMBDA = 5.0


def variance_rtol(sur, rpm, euler, v_air, unit_roundoff: float | None = None) -> np.ndarray:
    """Per query, the relative accuracy of a surrogate's predictive variance, from the dtype
    its variance factor is stored in (float32 for the default model, ``variance_dtype``) and
    the conditioning of ``σ − ‖F k‖²``: ``F k`` is summed in that dtype over the ``R`` rows of
    the factor, so the latent variance is off by at most
    ``λ √R u (2 ‖F k‖ ‖|F| |k|‖ + ‖F k‖²)``; each component of the predictive variance is
    ``(latent + ν²)`` times fixed positive weights, so its relative error is that over
    ``latent + ν²``. Computed in float64 NumPy from the stored factor (an independent
    reference of the quadratic form); exact ``gpg`` and binned models. The kernel row ``k`` itself
    is off by ``u (|x/l|² + |x_p/l|²)`` relative per entry (the library expands the squared
    distance), which moves the latent variance by ``2 ‖F k‖ ‖|F| δk‖``. ``unit_roundoff``: a
    coarser ``u`` than the stored factor's, for a computation done in a narrower type (an
    export in float)."""
    import jax
    import jax.numpy as jnp

    from gpg.surrogate import gp_inputs

    model = getattr(sur.model, "local", sur.model)  # the hybrid's near-set part
    exact = hasattr(model, "chol_inv")  # exact GP-G: one factor of every observed row

    @jax.jit
    @jax.vmap
    def rows(r, e, v):
        xn = sur.normalizer.x(gp_inputs(sur, r, e, v)[0])  # the half-turn image's, where read
        if exact:
            return _exact_row(model, xn), 0
        b = model.partition.lookup(xn)
        return model.kernel_row(xn, b), b

    K, B = (np.asarray(a) for a in rows(*(jnp.asarray(a, float) for a in (rpm, euler, v_air))))
    # |x/l|² + |x_p/l|² at most, over the box [-1, 1]^D and the stored points (padding aside)
    d = int(np.asarray(sur.box_lo).size)
    ls = np.broadcast_to(np.asarray(model.hyper.lengthscale if exact else model.lengthscale), (d,))
    pts = np.asarray(model.X if exact else model.Xn).reshape(-1, d)
    pts = pts[np.abs(pts).max(axis=1) < 10]
    reach = float(np.sum(1 / ls**2) + np.max(np.sum((pts / ls) ** 2, axis=1)))
    out = []
    for k, b in zip(K.astype(float), B, strict=True):
        if exact:
            F, sigma, noise = model.chol_inv, model.hyper.variance, model.hyper.noise
        else:
            F, sigma, noise = model.factor[int(b)], model.variance, model.noise
        u = max(float(np.finfo(F.dtype).eps) / 2, unit_roundoff or 0.0)
        Fd = F.to_dense()
        fk, bound = Fd @ k, np.abs(Fd) @ np.abs(k)
        quad = float(fk @ fk)
        dq = LAMBDA * np.sqrt(k.size) * u * (2 * np.linalg.norm(fk) * np.linalg.norm(bound) + quad)
        dk = LAMBDA * max(float(np.finfo(float).eps) / 2, unit_roundoff or 0.0) * reach * np.abs(k)
        dq += 2 * np.linalg.norm(fk) * np.linalg.norm(np.abs(Fd) @ dk)
        # + the weights' products and the rotation to the world frame: a few u of float64
        out.append(dq / (max(float(sigma) - quad, 0.0) + float(noise)) + 8 * np.finfo(float).eps)
    return np.asarray(out)


def _exact_row(model, xn):
    """The exact GP's kernel row at ``xn`` in its factor's row order."""
    from gpg.gp import kernels

    h = model.hyper
    k = kernels.query_rows(xn[None], model.X, h.variance, h.lengthscale, model.grad_dims)[0]
    return k if model.order is None else k[model.order]


def smooth_body(x, W):
    """:func:`smooth` for body-frame inputs ``(rpm, u, v, w)`` (N, 7): outputs (N, 9) and exact
    Jacobians along all seven inputs (N, 9, 7)."""
    scale = np.array([1 / 3500.0] * 4 + [1 / 20.0] * 3)
    u = x * scale - np.array([1.0] * 4 + [0.0] * 3)
    z = u @ W
    out_scale = np.array([3, 3, 20, 0.5, 0.5, 0.2, 5, 5, 5])
    y = (np.sin(z) + 0.3 * z) * out_scale + np.array([0, 0, -26, 0, 0, 0, 60, 60, 50])
    dz = (np.cos(z) + 0.3)[:, :, None] * (W.T[None] * scale[None, None, :])
    return y, dz * out_scale[None, :, None]


def synthetic_body_dataset(n=60, seed=0):
    """A body-frame dataset (the envelope's ball of air velocities) of a smooth analytic
    function with exact gradients along all seven inputs."""
    rng = np.random.default_rng(seed)
    W = rng.normal(scale=0.5, size=(7, 9))
    x = latin_hypercube(n, Bounds(), seed, "body")
    y, J = smooth_body(x, W)
    meta = {
        "frame": "body",
        "bounds": {"rpm": [0.0, 7000.0], "airspeed": [0.0, 20.0]},
        "name": "synthetic_body",
    }
    return _synthetic(x, y, J, meta), W
