"""Dense factorisations done in place, for the large offline solves.

Why not ``jax.scipy.linalg.cho_factor`` here: on the CPU backend JAX's ``potrf`` runs on one
core and needs an output copy plus a masking pass, so it is slower and holds two copies of the
matrix, where LAPACK's ``dpotrf`` called in place holds one (docs/measurements.md, the
Cholesky of a ready ``K̄``). For the 40000-row matrices of ``data=paper`` (40000² doubles
each) a second copy does not fit in memory at all. The differentiable small-matrix path
(hyperparameter fits) still uses ``jax.scipy.linalg``.

Storage convention: matrices are C-ordered NumPy arrays. A C-ordered symmetric ``K`` read as a
Fortran array is the same ``K``; LAPACK's upper factor ``U`` (``UᵀU = K``) of that Fortran view,
read back in C order, is the lower factor ``L = Uᵀ`` with ``L Lᵀ = K``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg.blas as blas
import scipy.linalg.lapack as lapack

__all__ = [
    "NotPositiveDefiniteError",
    "cho_solve",
    "cholesky_inplace",
    "gram_t",
    "solve_lower",
    "triangular_inverse_inplace",
]

# Above this size the Cholesky factorisation is blocked by hand (see cholesky_inplace).
BLOCKED_ABOVE = 8192


class NotPositiveDefiniteError(ValueError):
    """A Gram matrix that should be positive definite is not, numerically."""


def _check_square_c(name: str, a: np.ndarray) -> None:
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"{name} must be a square matrix, got shape {a.shape}")
    if a.dtype != np.float64 or not a.flags.c_contiguous or not a.flags.writeable:
        raise ValueError(f"{name} must be a writeable C-contiguous float64 array")


def cholesky_inplace(a: np.ndarray, *, what: str = "K̄", block: int = 2048) -> np.ndarray:
    """Overwrite the symmetric positive definite ``a`` with its lower Cholesky factor ``L``.

    Up to :data:`BLOCKED_ABOVE` rows this is one LAPACK ``dpotrf``. Above, it is a right-looking
    blocked factorisation (``dpotrf`` on diagonal blocks, triangular solves for the panels,
    matrix products for the trailing update): the multi-threaded ``dsyrk`` inside OpenBLAS's
    own ``dpotrf`` crashed the development machine (SIGSEGV) from 16000 rows up
    (scipy-openblas 0.3.31, two threads), while its ``dgemm`` runs at any size.

    Args:
        a: (n, n) symmetric positive definite matrix (``K̄``), writeable C-contiguous float64;
            overwritten.
        what: the matrix's name in the error messages.
        block: rows per diagonal block of the blocked factorisation (above
            :data:`BLOCKED_ABOVE` rows only).

    Returns:
        ``a`` itself, holding ``L`` (``L Lᵀ = a``) with its strict upper triangle zeroed.

    Raises:
        NotPositiveDefiniteError: if a pivot is not positive, naming the first that fails.
        ValueError: if ``a`` is not square, or not a writeable C-contiguous float64 array.
    """
    _check_square_c(what, a)
    n = a.shape[0]
    if n > BLOCKED_ABOVE:
        return _blocked_cholesky(a, what, block)
    # clean=1: LAPACK's wrapper zeroes the other triangle, so L is a plain dense lower matrix.
    u, info = lapack.dpotrf(a.T, lower=0, overwrite_a=1, clean=1)
    if info > 0:
        raise _not_pd(what, n, info - 1)
    if info < 0:  # pragma: no cover - argument error inside LAPACK
        raise ValueError(f"dpotrf rejected argument {-info}")
    if not np.may_share_memory(u, a):  # pragma: no cover - the wrapper copied after all
        a[...] = u.T
    return a


def _not_pd(what: str, n: int, pivot: int) -> NotPositiveDefiniteError:
    return NotPositiveDefiniteError(
        f"{what} ({n} rows) is not numerically positive definite: the Cholesky "
        f"factorisation failed at pivot {pivot}. Increase the jitter / gradient noise, or "
        "check for duplicated inputs."
    )


def _blocked_cholesky(a: np.ndarray, what: str, block: int) -> np.ndarray:
    n = a.shape[0]
    for k0 in range(0, n, block):
        k1 = min(k0 + block, n)
        d = np.ascontiguousarray(a[k0:k1, k0:k1])
        u, info = lapack.dpotrf(d.T, lower=0, overwrite_a=1, clean=1)
        if info > 0:
            raise _not_pd(what, n, k0 + info - 1)
        L_kk = u.T if not np.may_share_memory(u, d) else d
        a[k0:k1, k0:k1] = L_kk
        a[k0:k1, k1:] = 0.0
        if k1 == n:
            break
        # Panel: P L_kkᵀ = A_{k1:, k0:k1}, i.e. Pᵀ = L_kk⁻¹ A_{k1:, k0:k1}ᵀ.
        panel = np.ascontiguousarray(a[k1:, k0:k1])
        pt = blas.dtrsm(1.0, L_kk, panel.T, lower=1, side=0, trans_a=0, overwrite_b=1)
        panel = pt.T
        a[k1:, k0:k1] = panel
        # Trailing update of the lower triangle, one block row at a time: A_ij -= P_i P_jᵀ.
        for r0 in range(k1, n, block):
            r1 = min(r0 + block, n)
            a[r0:r1, k1:r1] -= panel[r0 - k1 : r1 - k1] @ panel[: r1 - k1].T
    return a


def gram_t(a: np.ndarray) -> np.ndarray:
    """``aᵀ a`` by ``dgemm``, never ``dsyrk``.

    NumPy would route ``a.T @ a`` to ``dsyrk``, which crashes in OpenBLAS's threaded code for
    large outputs (see :func:`cholesky_inplace`).

    Args:
        a: (n, m) float64 matrix, in C or Fortran order.

    Returns:
        The (m, m) symmetric ``aᵀ a``, C-ordered.
    """
    f = np.asfortranarray(a.T) if not a.flags.c_contiguous else a.T  # F-ordered view of aᵀ
    # The F-ordered result is symmetric: its transpose is the same matrix, C-ordered, no copy.
    return blas.dgemm(1.0, f, f, trans_b=1).T


def solve_lower(L: np.ndarray, b: np.ndarray, *, trans: bool = False) -> np.ndarray:
    """``L⁻¹ b`` (or ``L⁻ᵀ b``) by one ``dtrsm`` on the Fortran views.

    Reading the C-ordered arrays as Fortran ones turns the left solve into a right solve with
    ``Lᵀ``, which avoids the layout copies that ``scipy.linalg.solve_triangular`` makes for
    C-ordered arrays.

    Args:
        L: (n, n) lower-triangular float64 matrix, C-ordered.
        b: (n,) or (n, m) right-hand side; not modified.
        trans: solve with ``Lᵀ`` instead, ``L⁻ᵀ b``.

    Returns:
        A new array of ``b``'s shape: ``L⁻¹ b``, or ``L⁻ᵀ b`` with ``trans``.
    """
    x = np.array(b, dtype=np.float64, order="C", copy=True)
    if x.ndim == 1:
        return solve_lower(L, x[:, None], trans=trans)[:, 0]
    # In Fortran order x is xᵀ (m, n) and L is Lᵀ (upper): L⁻¹ b = (bᵀ L⁻ᵀ)ᵀ, a right solve.
    out = blas.dtrsm(1.0, L.T, x.T, side=1, lower=0, trans_a=1 if trans else 0, overwrite_b=1)
    return out.T


def cho_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``K x = b`` given the lower Cholesky factor of ``K`` (LAPACK ``dpotrs``).

    Args:
        chol: (R, R) lower factor ``L`` of ``K = L Lᵀ``, C-ordered (from
            :func:`cholesky_inplace`).
        b: (R,) or (R, M) right-hand side, e.g. the stacked targets ``Ȳ``.

    Returns:
        ``x = K⁻¹ b``, of ``b``'s shape.

    Raises:
        ValueError: if LAPACK's ``dpotrs`` rejects an argument (``info < 0``).
    """
    x, info = lapack.dpotrs(chol.T, np.asarray(b, dtype=np.float64), lower=0)
    if info != 0:  # pragma: no cover
        raise ValueError(f"dpotrs rejected argument {-info}")
    return x


def triangular_inverse_inplace(chol: np.ndarray) -> np.ndarray:
    """Overwrite the lower-triangular ``chol`` with ``chol⁻¹`` (LAPACK ``dtrtri``).

    Args:
        chol: (n, n) lower-triangular factor ``L``, writeable C-contiguous float64;
            overwritten.

    Returns:
        ``chol`` itself, holding ``L⁻¹`` (lower triangular as well).

    Raises:
        NotPositiveDefiniteError: if ``L`` has a zero on its diagonal, naming the pivot.
        ValueError: if ``chol`` is not square, or not a writeable C-contiguous float64 array.
    """
    _check_square_c("chol", chol)
    inv, info = lapack.dtrtri(chol.T, lower=0, overwrite_c=1)
    if info != 0:
        raise NotPositiveDefiniteError(f"triangular factor is singular at pivot {info - 1}")
    if not np.may_share_memory(inv, chol):  # pragma: no cover
        chol[...] = inv.T
    return chol
