"""GP-G's exact mean from the global ``α`` with a near-set variance (GP-G-S-Hybrid)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import jax.numpy as jnp
import numpy as np

from gpg.config import ModelConfig
from gpg.gp import cg, local, partition, pic
from gpg.gp.binned import BinFactors, near_rows, pack
from gpg.gp.exact import ExactGP
from gpg.gp.gram import assemble_gram, device_gram, from_bases, mask_gram_inplace
from gpg.gp.hybrid import HybridGP, Record
from gpg.gp.hyper import Hyper
from gpg.gp.matfree import gram_matvec, gram_matvec_devices
from gpg.gp.mean import GlobalMean, output_scale
from gpg.gp.update import grown_bases, grown_rows, layout_index
from gpg.kinds.base import (
    Arrays,
    Cases,
    Kind,
    Product,
    bin_devices,
    bins_and_near,
    gram_bytes,
    near_set_bytes,
)
from gpg.linalg import dense, memory
from gpg.linalg import device as linalg_device
from gpg.parallel import Devices

__all__ = ["KIND", "Hybrid"]


@dataclass(frozen=True)
class Hybrid(Kind):
    """``gpgs_hybrid``: :class:`gpg.gp.hybrid.HybridGP`, the mean from one factorisation of
    ``K̄``, the variance from :mod:`gpg.gp.local` on the bins' near sets."""

    name = "hybrid"
    reads = ("partition", "near", "variance_dtype", "solver")
    partitioned = True
    needs_gram = True  # by default; solver.method cg trains without K̄
    partial_gradients = True
    directional_gradients = True

    def build(
        self, arrays: Arrays, hyper: Hyper, cfg: ModelConfig, *, devices: Devices = None
    ) -> Product:
        """The global ``α = K̄⁻¹ Ȳ`` for the mean, the bins' near sets for the variance.

        Args:
            arrays: the normalised training arrays; cases with some gradients missing and
                directional gradient rows are taken (on the host path, and not by CG).
            hyper: the fitted hyperparameters.
            cfg: the resolved config: ``solver`` (``method`` cholesky or cg for ``α``,
                ``device``), ``partition``, ``near`` and ``variance_dtype``.
            devices: JAX devices for the CG products and the bins' factorisations; None lets
                ``solver.device`` place them.

        Returns:
            The :class:`~gpg.gp.hybrid.HybridGP` with its training record, the near sets, the
            solver's diagnostics (CG's iterations and residuals) and the timings.
        """
        part, near, Ybar, timings = bins_and_near(arrays, hyper, cfg)
        t0 = time.perf_counter()
        rows, bases = arrays.rows, arrays.bases
        alpha, diagnostics = global_alpha(
            arrays.X, Ybar, rows, hyper, arrays.dims, cfg, devices, bases
        )
        width = max(nb.size for nb in near.near) * (1 + len(arrays.dims))
        devs = bin_devices(
            devices, cfg, width, f"the bins' near sets ({width} rows each)",
            host_only=rows is not None or bases is not None,
        )  # fmt: skip
        factors = local.precompute(
            arrays.X, Ybar, hyper, arrays.dims, near, devices=devs, rows=rows, bases=bases
        )
        model = _assemble(
            arrays.X, Ybar, rows, alpha, factors, near, part, hyper, arrays.dims, cfg, bases
        )
        timings["fit_s"] = time.perf_counter() - t0
        return Product(model, near, diagnostics, timings)

    def condition(self, model: HybridGP, new: Arrays, cfg: ModelConfig) -> HybridGP:
        """The hybrid on its cases and ``new``, hyperparameters and bins kept.

        ``α`` is re-formed on all the cases by the configured solver, the near sets are
        recomputed, and only the bins whose near set changed are factorised again (the
        others' factors are reused as stored). Equal to a rebuild with the same
        hyperparameters and partition.

        Args:
            model: a hybrid that holds its training record.
            new: the new cases (normalised).
            cfg: the resolved config (the solver and the near-set rule).

        Returns:
            The conditioned hybrid, its record grown by ``new``.

        Raises:
            ValueError: if ``model`` holds no training record (a mean view, or one saved by
                gpg < 0.3).
        """
        rec = _record(model)
        local_gp, dims, hyper = model.local, model.local.grad_dims, rec.hyper
        X_old, n_old = np.asarray(rec.X), rec.X.shape[0]
        *_, bases = grown_bases(rec.bases, new.bases, n_old, new.X.shape[0], len(dims))
        X = np.concatenate([X_old, new.X])
        old_idx, new_idx = layout_index(n_old, new.X.shape[0], len(dims))
        Ybar = np.empty((X.shape[0] * (1 + len(dims)), rec.Ybar.shape[1]))
        Ybar[old_idx], Ybar[new_idx] = np.asarray(rec.Ybar), new.targets()
        rows = grown_rows(rec.rows, new.rows, old_idx, new_idx, Ybar.shape[0])
        alpha, _ = global_alpha(X, Ybar, rows, hyper, dims, cfg, None, bases)
        rule = cfg.near.rule()
        before = partition.near_sets(X_old, local_gp.partition, hyper.lengthscale, **rule)
        near = partition.near_sets(X, local_gp.partition, hyper.lengthscale, **rule)
        changed = [
            b for b in range(near.n_bins) if not np.array_equal(near.near[b], before.near[b])
        ]
        redone = local.precompute(X, Ybar, hyper, dims, near, rows=rows, bins=changed, bases=bases)
        fresh = dict(zip(changed, redone, strict=True))
        factors = [
            fresh[b] if b in fresh else _stored_factors(local_gp, b, len(dims))
            for b in range(near.n_bins)
        ]
        part = local_gp.partition
        return _assemble(X, Ybar, rows, alpha, factors, near, part, hyper, dims, cfg, bases)

    def cases(self, model: HybridGP) -> Cases:
        """The cases in the hybrid's training record.

        Args:
            model: a hybrid that holds its training record.

        Returns:
            The recorded inputs (as NumPy), hyperparameters and gradient dims.

        Raises:
            ValueError: if ``model`` holds no training record.
        """
        rec = _record(model)
        return Cases(np.asarray(rec.X), rec.hyper, model.local.grad_dims)

    def posterior(self, model: HybridGP) -> ExactGP:
        """The exact GP-G on the hybrid's training record: one factorisation of ``K̄``.

        Args:
            model: a hybrid that holds its training record.

        Returns:
            The :class:`~gpg.gp.exact.ExactGP` on the recorded cases, with their observed
            rows and gradient directions, and the hybrid's hyperparameters.

        Raises:
            ValueError: if ``model`` holds no training record.
        """
        rec, dims = _record(model), model.local.grad_dims
        X, Ybar = np.asarray(rec.X), np.asarray(rec.Ybar)
        n, g = X.shape[0], len(dims)
        dY = Ybar[n:].reshape(g, n, -1).transpose(1, 2, 0) if g else None
        obs = None if rec.rows is None else np.asarray(rec.rows)[n:].reshape(g, n).T
        bases = None if rec.bases is None else np.asarray(rec.bases)
        return ExactGP.fit(X, Ybar[:n], dY, grad_dims=dims or None, hyper=rec.hyper,
                           observed=obs, bases=bases)  # fmt: skip

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        """The larger of the mean's solve and the near-set precompute.

        The mean's is one dense ``K̄`` for the Cholesky solver, CG's working set (nine
        outputs) otherwise.

        Args:
            cfg: the resolved config (``solver``, ``partition``, ``near``).
            n_points: training points.
            n_grad: gradient dims per point.

        Returns:
            The estimate in bytes.
        """
        if solver_method(cfg, n_points, n_grad) == "cg":
            mean = cg_bytes(cfg, n_points, n_grad, 9)  # the nine outputs of gpg's data
        else:
            mean = gram_bytes(n_points, n_grad)
        return max(mean, near_set_bytes(cfg, n_points, n_grad))


def _record(model: HybridGP) -> Record:
    if model.record is None:
        raise ValueError(
            "this hybrid holds no training record (a mean view, or saved by gpg < 0.3): "
            "refit it to condition on new cases"
        )
    return model.record


def _assemble(X, Ybar, rows, alpha, factors, near, part, hyper, dims, cfg, bases=None):
    n_obs = Ybar.shape[0] if rows is None else int(rows.sum())
    scale = output_scale(np.sum(Ybar * alpha, axis=0), n_obs)
    # The mean reads coordinate rows; α is over the directional ones (gpg.gp.gram.from_bases).
    coord = alpha if bases is None else from_bases(alpha, bases, X.shape[0])
    return HybridGP(
        mean=GlobalMean.from_alpha(X, coord, hyper.variance, hyper.lengthscale, dims),
        local=pack(
            X, factors, near, part, hyper, dims, dtype=cfg.variance_dtype, scale=scale, bases=bases
        ),  # fmt: skip
        record=Record(
            jnp.asarray(X),
            jnp.asarray(Ybar),
            hyper,
            None if rows is None else jnp.asarray(rows),
            None if bases is None else jnp.asarray(bases),
        ),  # fmt: skip
    )


def _stored_factors(gp, b: int, g: int) -> BinFactors:
    """Bin ``b``'s factor and coefficients as packed, without the padding (unchanged bins)."""
    p, P = int(gp.n_near[b]), gp.Xn.shape[1]
    pos = near_rows(np.arange(p), P, g)
    dense_f = gp.factor[b].to_dense()[np.ix_(pos, pos)]
    coef = np.asarray(gp.coef[b])[:, pos].T
    return BinFactors(coef, dense_f, True)


def global_alpha(X, Ybar, rows, hyper, dims, cfg, devices, bases=None) -> tuple[np.ndarray, dict]:
    """The global ``α = K̄⁻¹ Ȳ`` by the configured solver, and its diagnostics (over the
    directional rows with ``bases``)."""
    if solver_method(cfg, X.shape[0], len(dims)) == "cg":
        if rows is not None or bases is not None:
            raise ValueError(
                "solver.method=cg needs every gradient at every case along the inputs; with "
                "cases that lack some, or converted (directional) gradients, use "
                "solver.method=cholesky"
            )
        return cg_alpha(X, Ybar, hyper, dims, cfg.solver, devices)
    return exact_alpha(X, Ybar, hyper, dims, rows, bases, cfg.solver.device), {}


def solver_method(cfg: ModelConfig, n_points: int, n_grad: int) -> str:
    """``cholesky`` or ``cg``: ``solver.method``, with ``auto`` resolved by whether a dense
    ``K̄`` fits in the memory available now."""
    method = cfg.solver.method
    if method == "auto":
        fits = gram_bytes(n_points, n_grad) <= 0.9 * memory.available_bytes()
        method = "cholesky" if fits else "cg"
    return method


def cg_bytes(cfg: ModelConfig, n_points: int, n_grad: int, n_outputs: int) -> int:
    """Peak bytes of :func:`cg_alpha`: the Nyström factor ``V`` and ``K̄_xu`` while it is
    made, the product's columns and one tile of ``K``, and a few CG vectors."""
    rows = n_points * (1 + n_grad)
    u = min(cfg.solver.points, n_points) * (1 + n_grad)
    columns = n_points * (n_grad + 1) * (n_grad + 2) * n_outputs
    return int(
        8
        * (
            2.2 * rows * u
            + u * u * 3
            + columns * 2
            + cfg.solver.tile * n_points * 3
            + 8 * rows * n_outputs
        )
    )


def cg_alpha(
    X, Ybar, hyper: Hyper, dims: tuple[int, ...], sc, devices=None
) -> tuple[np.ndarray, dict]:
    """``α = K̄⁻¹ Ȳ`` by preconditioned CG (:mod:`gpg.gp.cg`), and how the solve went;
    ``devices`` spreads each product's row tiles over JAX devices (:mod:`gpg.parallel`)."""
    t0 = time.perf_counter()
    Xj = jnp.asarray(X)
    Z = pic.inducing_inputs(X, min(sc.points, X.shape[0]), seed=sc.seed)
    precond = cg.Nystrom.create(Xj, hyper, dims, jnp.asarray(Z))
    setup = time.perf_counter() - t0
    if devices is None:
        matvec = partial(gram_matvec, Xj, hyper, dims, tile=sc.tile)
    else:
        matvec = partial(gram_matvec_devices, Xj, hyper, dims, devices=devices, tile=sc.tile)
    alpha, info = cg.solve(matvec, jnp.asarray(Ybar), precond, tol=sc.tol, max_iter=sc.max_iter)
    return np.asarray(alpha), {
        "solver": "cg",
        "cg_iterations": info.iterations,
        "cg_residual": info.residual.tolist(),
        "cg_setup_s": setup,
        "cg_solve_s": info.solve_s,
    }


def exact_alpha(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    dims: tuple[int, ...],
    rows=None,
    bases=None,
    device: str = "auto",
) -> np.ndarray:
    """``α = K̄⁻¹ Ȳ`` by one Cholesky factorisation of ``K̄`` (no inverse kept), in place on
    the host or on the accelerator (``device``, :func:`gpg.linalg.device.place`); ``rows``
    the observed rows (:func:`gpg.gp.gram.observed_rows`), ``bases`` the directions of the
    gradient rows (:func:`gpg.gp.gram.row_directions`)."""
    r = Ybar.shape[0]
    what = f"the global α over {r} rows"
    if linalg_device.place(device, linalg_device.solve_bytes(r, False), what) == "device":
        index = None if rows is None else np.flatnonzero(rows)
        K = device_gram(X, hyper, dims, index=index, bases=bases)
        part, _, _ = linalg_device.factor_solve(
            K, Ybar if index is None else Ybar[index], inverse=False, what=what
        )
        if index is None:
            return part
        alpha = np.zeros_like(Ybar)  # the rows not observed are decoupled: α = 0 there
        alpha[index] = part
        return alpha
    memory.require(what, int(r * r * 8 * 1.1))
    buf = memory.square_buffer(r)
    gram = assemble_gram(np.asarray(X), hyper, dims, out=buf.array, bases=bases)
    chol = dense.cholesky_inplace(mask_gram_inplace(gram, rows))
    alpha = dense.cho_solve(chol, Ybar)
    del chol, buf
    return alpha


KIND = Hybrid()
