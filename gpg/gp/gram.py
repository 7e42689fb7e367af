"""The stacked targets ``Ȳ``, the Gram matrix ``K̄`` of Eq. (barK) and its log likelihood.

Rows follow the layout of :mod:`gpg.gp.kernels`: ``N`` value rows, then one block of ``N``
rows per gradient dimension. :func:`assemble_gram` writes ``K̄`` block by block into one buffer
(the only full-size allocation); :func:`log_marginal_likelihood` is the differentiable dense
form used on the hyperparameter-fit subset.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg import _checks
from gpg._precision import highest
from gpg.gp import kernels
from gpg.gp.hyper import Hyper


def stack_targets(Y: Float[Array, "N M"], dY: Float[Array, "N M G"] | None) -> Float[Array, "R M"]:
    """Stack values and gradients into ``Ȳ`` with the layout of :mod:`gpg.gp.kernels`.

    NumPy in, NumPy out (no compilation for the offline fit); JAX arrays stay JAX arrays.
    """
    xp = np if isinstance(Y, np.ndarray) and (dY is None or isinstance(dY, np.ndarray)) else jnp
    if dY is None or dY.shape[2] == 0:
        return Y
    grads = xp.moveaxis(dY, 2, 0).reshape(-1, Y.shape[1])
    return xp.concatenate([Y, grads], axis=0)


@dataclass(frozen=True)
class Checked:
    """Training data after :func:`check_training_data`: float arrays, ``Y`` (N, M), ``dY``
    (N, M, G) or None, and the gradient dims as a tuple."""

    X: np.ndarray
    Y: np.ndarray
    dY: np.ndarray | None
    grad_dims: tuple[int, ...]
    observed: np.ndarray | None = None  # (N, G) bool, None when every gradient was observed

    @property
    def rows(self) -> np.ndarray | None:
        """The observed stacked rows (:func:`observed_rows`)."""
        return observed_rows(self.observed, self.X.shape[0])

    def gradients(self) -> np.ndarray | None:
        """``dY`` with NaN where a gradient was not observed (what :mod:`gpg.data` passes)."""
        if self.dY is None or self.observed is None:
            return self.dY
        return np.where(self.observed[:, None], self.dY, np.nan)

    def targets(self) -> np.ndarray:
        """``Ȳ`` (R, M), 0 on the unobserved rows."""
        dY = self.dY if self.observed is None else np.where(self.observed[:, None], self.dY, 0.0)
        return stack_targets(self.Y, dY)


def check_training_data(X, Y, dY, grad_dims, observed=None) -> Checked:
    X = _checks.as_float_array("X", X, ndim=2)
    Y = _checks.as_float_array("Y", Y, ndim=(1, 2))
    if Y.ndim == 1:
        Y = Y[:, None]
    n, d = X.shape
    if n == 0:
        raise ValueError("X must hold at least one point")
    if Y.shape[0] != n:
        raise ValueError(f"Y has {Y.shape[0]} rows but X has {n}")
    _checks.require_finite("X", X)
    _checks.require_finite("Y", Y)
    if dY is None:
        if grad_dims not in (None, (), []):
            raise ValueError(f"grad_dims={tuple(grad_dims)} given but dY is None")
        if observed is not None:
            raise ValueError("observed given but dY is None: it marks which gradients exist")
        return Checked(X, Y, None, ())
    dY = _checks.as_float_array("dY", dY, ndim=(2, 3))
    if dY.ndim == 2:
        if Y.shape[1] != 1:
            raise ValueError(f"dY must have shape (N, M, G) for M={Y.shape[1]} outputs")
        dY = dY[:, None, :]
    if dY.shape[:2] != Y.shape:
        raise ValueError(f"dY must have shape (N, M, G) = ({n}, {Y.shape[1]}, G), got {dY.shape}")
    if grad_dims is None:
        if dY.shape[2] != d:
            raise ValueError(
                f"dY has {dY.shape[2]} gradient dims but X has {d} inputs: pass grad_dims"
            )
        grad_dims = tuple(range(d))
    grad_dims = kernels.check_dims(grad_dims, d)
    if len(grad_dims) != dY.shape[2]:
        raise ValueError(f"grad_dims names {len(grad_dims)} dims but dY has {dY.shape[2]}")
    if observed is None:
        _checks.require_finite("dY", dY)
        return Checked(X, Y, dY, grad_dims)
    observed = np.asarray(observed)
    if observed.dtype != bool or observed.shape != (n, len(grad_dims)):
        raise ValueError(
            f"observed must be a boolean array of shape (N, G) = ({n}, {len(grad_dims)}), "
            f"got {observed.dtype} {observed.shape}"
        )
    _checks.require_finite("dY", np.where(observed[:, None, :], dY, 0.0))
    return Checked(X, Y, dY, grad_dims, None if observed.all() else observed)


def assemble_gram(
    X: Float[ArrayLike, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    chunk_rows: int = 256,
    bases: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄(X, X)`` plus its noise diagonal, written into a C-ordered NumPy buffer (over
    directional gradient rows with ``bases``, :func:`assemble_rows_gram`).

    Built in blocks of about ``chunk_rows`` rows so that the only full-size allocation is the
    result (``out`` if given), ready for :func:`gpg.linalg.dense.cholesky_inplace`. Small blocks
    stay in cache: 256 rows assembled the 8000-row K̄ fastest on the development machine.
    """
    n = np.asarray(X).shape[0]
    g = len(grad_dims)
    r = n * (1 + g)
    if bases is not None:
        return assemble_rows_gram(np.asarray(X), np.arange(r), hyper, grad_dims, out=out,
                                  bases=bases)  # fmt: skip
    X = jnp.asarray(X)
    if out is None:
        out = np.empty((r, r))
    elif out.shape != (r, r):
        raise ValueError(f"out must have shape ({r}, {r}), got {out.shape}")
    step = max(1, chunk_rows // (1 + g))
    for start in range(0, n, step):
        stop = min(start + step, n)
        rows = np.asarray(
            kernels.gram(X[start:stop], X, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
        )
        width = stop - start
        for blk in range(1 + g):
            out[blk * n + start : blk * n + stop] = rows[blk * width : (blk + 1) * width]
    out.flat[:: r + 1] += np.asarray(hyper.noise_diagonal(n, g))
    return out


def row_kinds(
    index: Int[np.ndarray, " r"], n: int, grad_dims: tuple[int, ...]
) -> tuple[Int[np.ndarray, " r"], Int[np.ndarray, " r"]]:
    """For rows ``index`` of the layout of ``n`` points: each row's point and what it observes
    (``-1`` the value, ``d`` the derivative along input ``d``), as :func:`kernels.row_gram`
    reads them."""
    index = np.asarray(index, dtype=np.int64)
    deriv = np.asarray((-1, *grad_dims), dtype=np.int32)[index // n]
    return index % n, deriv


def check_bases(
    bases: Float[ArrayLike, "N G G"] | None, n: int, grad_dims: tuple[int, ...]
) -> np.ndarray | None:
    """``bases`` as a float (N, G, G) array, or None; ``ValueError`` naming it otherwise."""
    if bases is None:
        return None
    g = len(grad_dims)
    if not g:
        raise ValueError("bases given but the data has no gradient rows")
    bases = _checks.as_float_array("bases", bases, ndim=3)
    if bases.shape != (n, g, g):
        raise ValueError(f"bases must have shape (N, G, G) = ({n}, {g}, {g}), got {bases.shape}")
    _checks.require_finite("bases", bases)
    return bases


def row_directions(
    index: Int[np.ndarray, " r"],
    n: int,
    grad_dims: tuple[int, ...],
    bases: Float[np.ndarray, "N G G"] | None,
    d: int,
) -> tuple[Int[np.ndarray, " r"], Float[np.ndarray, "r D"], Bool[np.ndarray, " r"]]:
    """For rows ``index`` of the layout of ``n`` points: each row's point, its direction in
    the ``d`` inputs (zero on a value row) and whether it is a value row, as
    :func:`kernels.direction_gram` reads them. Gradient row ``g`` of case ``i`` observes the
    derivative along ``Σ_h bases[i, g, h] e_{grad_dims[h]}`` (one-hot without ``bases``)."""
    index = np.asarray(index, dtype=np.int64)
    p, blk = index % n, index // n
    value = blk == 0
    g = np.where(value, 0, blk - 1)
    E = np.zeros((index.size, d))
    dims = np.asarray(grad_dims, dtype=np.int64)
    if bases is None:
        E[np.flatnonzero(~value), dims[g[~value]]] = 1.0
    elif dims.size:
        E[:, dims] = np.asarray(bases)[p, g, :]
        E[value] = 0.0
    return p, E, value


@highest
def to_bases(k: Float[Array, "*Q R"], bases: Float[Array, "N G G"], n: int) -> Float[Array, "*Q R"]:
    """Kernel rows in the coordinate layout (values, then one block per gradient dim) turned
    into the rows a case with gradient ``bases`` observes: ``B_i ∂k`` per case (JAX)."""
    g = bases.shape[1]
    lead = k.shape[:-1]
    grads = k[..., n:].reshape(*lead, g, n)
    turned = jnp.einsum("igh,...hi->...gi", bases.astype(k.dtype), grads)
    return jnp.concatenate([k[..., :n], turned.reshape(*lead, g * n)], axis=-1)


def from_bases(alpha: Float[np.ndarray, "R M"], bases: np.ndarray, n: int) -> np.ndarray:
    """Coefficients over directional rows (0 on rows not observed) as coefficients over the
    coordinate layout, ``Σ_g B_i[g, h] α_{g,i}``: what the folded mean and the exports read,
    so that ``k̄_coordᵀ α_coord = k̄_dirᵀ α``."""
    g = bases.shape[1]
    grads = np.einsum("igh,gim->him", bases, alpha[n:].reshape(g, n, -1))
    return np.concatenate([alpha[:n], grads.reshape(g * n, -1)])


def rows_gram(
    X1: Float[np.ndarray, "N1 D"],
    index1: Int[np.ndarray, " r1"],
    X2: Float[np.ndarray, "N2 D"],
    index2: Int[np.ndarray, " r2"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    chunk: int = 2048,
    bases1: np.ndarray | None = None,
    bases2: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄(X1, X2)`` (no noise) restricted to the layout rows ``index1`` of ``X1`` and columns
    ``index2`` of ``X2``, on the host, without forming the rest: how a model whose cases lack
    some gradients keeps only the rows it observed (a values-only case costs one row, not
    ``1 + G``). Built ``chunk`` rows at a time, the last chunk padded, so that a model that
    grows reuses one compiled program per width. ``bases1``/``bases2`` (N, G, G): cases whose
    gradient rows are derivatives along other directions (:func:`row_directions`)."""
    X1, X2 = np.asarray(X1), np.asarray(X2)
    directional = bases1 is not None or bases2 is not None
    p1, left, kernel = layout_rows(index1, X1.shape[0], grad_dims, bases1, directional, X1.shape[1])
    p2, right, _ = layout_rows(index2, X2.shape[0], grad_dims, bases2, directional, X2.shape[1])
    r1 = p1.shape[0]
    if out is None:
        out = np.empty((r1, p2.shape[0]))
    step = min(chunk, max(r1, 1))
    right = (jnp.asarray(X2[p2]), *(jnp.asarray(a) for a in right))
    for start in range(0, r1, step):
        stop = min(start + step, r1)
        sel = np.arange(start, start + step).clip(max=r1 - 1)  # padded with the last row
        block = kernel(
            jnp.asarray(X1[p1[sel]]), *(jnp.asarray(a[sel]) for a in left), *right,
            hyper.variance, hyper.lengthscale,
        )  # fmt: skip
        out[start:stop] = np.asarray(block)[: stop - start]
    return out


def layout_rows(index, n: int, grad_dims: tuple[int, ...], bases, directional: bool, d: int):
    """Rows ``index`` of the layout of ``n`` points as a row kernel reads them: their points,
    what each observes, and the kernel. Along the inputs, :func:`row_kinds` for
    :func:`kernels.row_gram` (a fifth faster than the general form on coordinate rows); with
    ``directional`` (either side has ``bases``), :func:`row_directions` for
    :func:`kernels.direction_gram`."""
    if not directional:
        p, a = row_kinds(index, n, grad_dims)
        return p, (a,), kernels.row_gram
    p, E, v = row_directions(index, n, grad_dims, None if bases is None else np.asarray(bases), d)
    return p, (E, v), kernels.direction_gram


def assemble_rows_gram(
    X: Float[np.ndarray, "N D"],
    index: Int[np.ndarray, " r"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    bases: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄`` plus its noise diagonal over the layout rows ``index`` only (the observed rows of
    cases that lack some gradients, :func:`observed_rows`): :func:`assemble_gram` for them.
    ``bases`` (N, G, G): the cases' gradient rows are along those directions
    (:func:`row_directions`); row ``g`` keeps the noise ``λ_g²`` of gradient dim ``g``."""
    out = rows_gram(
        X, index, X, index, hyper, grad_dims, out=out, chunk=256, bases1=bases, bases2=bases
    )
    n, g = np.asarray(X).shape[0], len(grad_dims)
    out.flat[:: out.shape[0] + 1] += np.asarray(hyper.noise_diagonal(n, g))[np.asarray(index)]
    return out


@highest
def noisy_gram(
    X: Float[Array, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    rows: Bool[ArrayLike, " R"] | None = None,
) -> Float[Array, "R R"]:
    """``K̄(X, X)`` plus its noise diagonal (``ν²`` on value rows, ``λ²`` on gradient rows) in
    JAX: the one form every traced factorisation starts from (the likelihood, the local bins
    on devices, PIC's blocks). :func:`assemble_gram` is its host twin for large ``K̄``.
    ``rows`` (R,) marks the observed rows (:func:`observed_rows`); the others are decoupled."""
    K = kernels.gram(X, X, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
    K = K + jnp.diag(hyper.noise_diagonal(X.shape[0], len(grad_dims)))
    if rows is None:
        return K
    m = jnp.asarray(rows, dtype=K.dtype)
    return K * m[:, None] * m[None, :] + jnp.diag(1.0 - m)


def observed_rows(observed: Bool[np.ndarray, "N G"] | None, n: int) -> np.ndarray | None:
    """Per stacked row (R,), whether it was observed: value rows always, gradient row ``(i,
    g)`` where ``observed[i, g]``; None when every gradient was (the common case, no mask).

    A case whose simulator run skipped some finite-difference perturbations has no rows for
    those gradient dims. The layout keeps its fixed shape (targets 0 there); the exact GP forms
    and factorises only the observed rows (:func:`rows_gram`, ``ExactGP.order``), and the
    partitioned models' local factors decouple the missing ones (:func:`mask_gram_inplace`:
    identity rows and columns). Either way the posterior is exactly the one conditioned on the
    observed rows alone, with no change to the query code.
    """
    if observed is None:
        return None
    observed = np.asarray(observed, dtype=bool)
    if observed.all():
        return None
    return np.concatenate([np.ones(n, dtype=bool), observed.T.ravel()])


def mask_gram_inplace(K: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """Decouple the unobserved rows of a host ``K̄`` (see :func:`observed_rows`)."""
    if rows is None:
        return K
    miss = np.flatnonzero(~rows)
    K[miss, :] = 0.0
    K[:, miss] = 0.0
    K[miss, miss] = 1.0
    return K


def mask_targets(Ybar: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """``Ȳ`` with the unobserved rows 0 (their stored values, NaN or not, are never read)."""
    if rows is None:
        return Ybar
    out = np.array(Ybar, dtype=float, copy=True)
    out[~rows] = 0.0
    return out


def value_row_noise(row_noise: Float[ArrayLike, " N"], n: int, g: int) -> Float[Array, " R"]:
    """Per-case value noise (N,) spread over the layout's ``n(1+g)`` rows: on the value rows,
    0 on the gradient rows (:mod:`gpg.gp.kernels`: the N value rows come first)."""
    return jnp.concatenate([jnp.asarray(row_noise), jnp.zeros(n * g)])


@highest
def log_marginal_likelihood(
    X: Float[Array, "N D"],
    Ybar: Float[Array, "R M"],
    hyper: Hyper,
    grad_dims: tuple[int, ...] = (),
    rows: Bool[ArrayLike, " R"] | None = None,
    bases: Float[ArrayLike, "N G G"] | None = None,
    row_noise: Float[ArrayLike, " N"] | None = None,
) -> Float[Array, ""]:
    """``Σ_m log N(Ȳ_m | 0, K̄)``: pure JAX, differentiable in ``hyper`` (small N only).

    ``Ybar`` is the stacked target of :func:`stack_targets` (0 on unobserved rows); ``rows``
    the observed rows (:func:`observed_rows`, a host array), which alone are formed and count:
    a values-only case adds one row to the factorisation, not ``1 + G``. ``bases`` (N, G, G):
    directional gradient rows (:func:`row_directions`). ``row_noise`` (N,): each case's own
    value-noise variance, added to ``ν²`` on its value row (heteroscedastic labels).
    """
    n, g = X.shape[0], len(grad_dims)
    extra = None if row_noise is None else value_row_noise(row_noise, n, g)
    if rows is None and bases is None:
        K = noisy_gram(X, hyper, grad_dims)
        if extra is not None:
            K = K + jnp.diag(extra)
    else:
        index = np.arange(n * (1 + g)) if rows is None else np.flatnonzero(np.asarray(rows))
        p, what, kernel = layout_rows(index, n, grad_dims, bases, bases is not None, X.shape[1])
        Xr = jnp.asarray(X)[p]
        what = tuple(jnp.asarray(a) for a in what)
        K = kernel(Xr, *what, Xr, *what, hyper.variance, hyper.lengthscale)
        K = K + jnp.diag(hyper.noise_diagonal(n, g)[index])
        if extra is not None:
            K = K + jnp.diag(extra[index])
        Ybar = Ybar[index]
    c, lower = jsl.cho_factor(K, lower=True)
    alpha = jsl.cho_solve((c, lower), Ybar)
    m = Ybar.shape[1]
    r = Ybar.shape[0]
    return (
        -0.5 * jnp.sum(Ybar * alpha)
        - m * jnp.sum(jnp.log(jnp.diag(c)))
        - 0.5 * m * r * jnp.log(2 * jnp.pi)
    )


def device_gram(
    X: Float[ArrayLike, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    index: Int[np.ndarray, " r"] | None = None,
    bases: np.ndarray | None = None,
    chunk_bytes: int = 1 << 28,
) -> Float[Array, "r r"]:
    """``K̄`` plus its noise diagonal over the layout rows ``index`` (default all), built on
    JAX's default device in float64: the device twin of :func:`assemble_gram` and
    :func:`assemble_rows_gram` (``bases``: directional rows, :func:`row_directions`), for
    :mod:`gpg.linalg.device`. Rows are made a block at a time into one preallocated buffer
    (the kernels' elementwise temporaries of a block stay under ``chunk_bytes``), so the peak
    is the matrix itself."""
    X = np.asarray(X, dtype=np.float64)
    n, g = X.shape[0], len(grad_dims)
    index = np.arange(n * (1 + g)) if index is None else np.asarray(index)
    p, what, kernel = layout_rows(index, n, grad_dims, bases, bases is not None, X.shape[1])
    r = index.size
    # The row kernels hold a few (block x r) temporaries, (block x r x D) for directions.
    per_row = 8 * r * (4 + (X.shape[1] if bases is not None else 0))
    block = int(max(1, min(r, chunk_bytes // per_row)))
    noise = np.asarray(hyper.noise_diagonal(n, g))[index]
    return _device_gram(
        jnp.asarray(X[p]), tuple(jnp.asarray(a) for a in what), jnp.asarray(noise),
        hyper.variance, hyper.lengthscale, kernel=kernel, block=block,
    )  # fmt: skip


@partial(jax.jit, static_argnames=("kernel", "block"))
@highest
def _device_gram(Xr, what, noise, variance, lengthscale, *, kernel, block: int):
    r = Xr.shape[0]
    n_blocks = -(-r // block)

    def fill(i, K):
        # The last block starts early enough to end at r: its first rows are made twice.
        start = jnp.minimum(i * block, r - block)
        rows = (jax.lax.dynamic_slice_in_dim(a, start, block) for a in (Xr, *what))
        part = kernel(*rows, Xr, *what, variance, lengthscale)
        return jax.lax.dynamic_update_slice_in_dim(K, part, start, axis=0)

    K = jax.lax.fori_loop(0, n_blocks, fill, jnp.zeros((r, r), Xr.dtype))
    diag = jnp.arange(r)
    return K.at[diag, diag].add(noise)  # in place: no second r x r array
