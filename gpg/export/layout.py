"""What an export reads from a fitted :class:`gpg.Surrogate`: plain NumPy arrays in one layout
that the C, CasADi and ONNX writers share, checked once, with the record every export carries.

A real-time model is a mean and, optionally, a variance, each a closed form over stored
arrays (normalised inputs ``x̂``, paper Eq. normalize_x):

* the **global mean** (``gpg``, ``gp``, ``gpgs_hybrid``): ``σ Σ_p k(x̂, x_p) c_p`` folded as in
  :mod:`gpg.gp.mean`;
* the **binned mean** (``gps_*``, ``gpgs``, ``gpgs_schur``, ``gpg_pic``): bin ``b``'s
  coefficients ``C_b`` (M, R_b) times the kernel row ``k̄(x̂, X_b)`` of its near set;
* the **variance**: ``σ − ‖F_b k̄(x̂, X_b)‖²`` with bin ``b``'s triangular factor (the hybrid's
  and the local kinds' near sets, PIC's inducing rows then the bin's own), or, for the exact
  kinds, one "bin" of every training point with ``F = L⁻¹``.

A bin's near set is kept without the padding the JAX model stores (its real points only,
``R_b = (U + p_b)(1 + G)`` rows: the shared inducing rows first, then the bin's own, each
block value rows then one block per gradient dimension), so every writer loops over real rows.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from typing import Any

import jax
import numpy as np

from gpg._version import __version__
from gpg.gp.binned import BinnedGP, near_rows
from gpg.gp.exact import ExactGP
from gpg.gp.hybrid import HybridGP
from gpg.gp.inducing import variance_factor
from gpg.gp.mean import GlobalMean
from gpg.gp.partition import Partition
from gpg.names import AERO
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

__all__ = ["BankTerm", "Correction", "Discrepancy", "Layout", "OnlineTerm", "TrackedTerm", "spec"]

# A C source holds each constant as text (about 3.5 bytes per stored byte): past this many
# bytes of constants an export is refused unless asked for (the exact GP-G variance at
# data=default is over it, see docs/measurements.md; its mean, or gpgs_hybrid, is what a
# real-time target can hold).
MAX_BYTES = 64 * 2**20


@dataclass(frozen=True)
class Bins:
    """Near sets of a partitioned model (or one bin for an exact model's variance).

    ``points[b]`` (p_b, D) normalised inputs of bin ``b``'s own near points; ``shared`` (U, D)
    rows every bin conditions on first (PIC's inducing inputs) or None; ``coef[b]`` (M, R_b)
    binned mean coefficients or None; ``factor[b]`` (R_b, R_b) the variance factor over the
    same rows (triangular, or dense in PIC's first rows) or None; ``factor_dtype`` its stored
    type. The partition in the arrays of :class:`gpg.gp.partition.Partition`."""

    points: list[np.ndarray]
    shared: np.ndarray | None
    coef: list[np.ndarray] | None
    factor: list[np.ndarray] | None
    factor_dtype: np.dtype
    scheme: str
    split_dim: np.ndarray
    split_value: np.ndarray
    left: np.ndarray
    right: np.ndarray
    depth: int

    @property
    def n_bins(self) -> int:
        return len(self.points)

    @property
    def dim(self) -> int:
        """``D``: inputs of a query (8 in the airflow frame, 7 in the body frame)."""
        return self.points[0].shape[1]

    def rows(self, b: int, n_grad: int) -> int:
        """``R_b``: rows of bin ``b``'s kernel row."""
        u = 0 if self.shared is None else self.shared.shape[0]
        return (u + self.points[b].shape[0]) * (1 + n_grad)

    def lookup(self, xn: np.ndarray) -> int:
        """Bin of one normalised query, as :meth:`gpg.gp.partition.Partition.lookup`."""
        if self.n_bins == 1:
            return 0
        if self.scheme == "slab":
            return int(np.sum(xn[self.split_dim[0]] > self.split_value))
        node = 0
        while node >= 0:
            go_left = xn[self.split_dim[node]] <= self.split_value[node]
            node = int(self.left[node] if go_left else self.right[node])
        return -node - 1

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Each bin's box ``(lo, hi]`` (B, D), ±inf where unbounded: the writers that cannot
        walk the tree (CasADi, ONNX) test a query against every box."""
        if self.scheme != "slab":
            part = Partition(self.split_dim, self.split_value, self.left, self.right,
                             self.n_bins, self.depth, self.scheme)  # fmt: skip
            return part.boxes(self.dim)
        cuts = np.concatenate([[-np.inf], self.split_value, [np.inf]])
        lo, hi = np.full((self.n_bins, self.dim), -np.inf), np.full((self.n_bins, self.dim), np.inf)
        lo[:, self.split_dim[0]], hi[:, self.split_dim[0]] = cuts[:-1], cuts[1:]
        return lo, hi


@dataclass(frozen=True)
class Discrepancy:
    """One load output's discrepancy GP of a model corrected by flights, values only:
    mean ``k(x̂, Z)ᵀ w`` and latent variance ``σ − ‖W k‖² + ‖P k‖²`` (``P`` absent for an
    exact GP, whose ``W`` is ``L⁻¹``; an inducing-point GP's ``W = L⁻¹`` of ``K_mm`` and
    ``P = L_B⁻¹ L⁻¹``, :mod:`gpg.gp.inducing`), its predictive variance
    ``c (max(latent, 0) + ν²)``.

    Attributes:
        points: (m, D) ``Z`` (an exact GP's training inputs), normalised.
        weights: (m,) ``w``.
        lengthscale: (D,).
        sigma: σ.
        noise: ``ν²``.
        output_scale: ``c``.
        whiten: (m, m) ``W``, lower triangular, or None (mean only).
        post: (m, m) ``P``, lower triangular, or None.
    """

    points: np.ndarray
    weights: np.ndarray
    lengthscale: np.ndarray
    sigma: float
    noise: float
    output_scale: float
    whiten: np.ndarray | None
    post: np.ndarray | None

    def variance_factor(self) -> np.ndarray | None:
        """One lower triangle ``T`` with ``‖T k‖² = ‖W k‖² − ‖P k‖²`` for every ``k``
        (:func:`gpg.gp.inducing.variance_factor`; ``W`` itself for an exact GP): half the
        products a query.

        Returns:
            (m, m) ``T``, lower triangular, or None (mean only).
        """
        if self.whiten is None or self.post is None:
            return self.whiten
        return variance_factor(self.whiten, self.post)


@dataclass(frozen=True)
class OnlineTerm:
    """The online term ``η`` of an adapted model (:class:`gpg.flight.correction.Online`) with
    its state when exported: per load output ``j``, ``ψ_j = W_j k_j(x̂, Z)``, mean ``ψ_jᵀ μ_j``,
    variance ``ψ_jᵀ Σ_j ψ_j``; relaxed between labels (``a = e^{−Δt/τ}``) and updated by a
    rank-one Kalman step per label (:func:`gpg.flight.update`).

    Attributes:
        Z: (m, D) inducing inputs, normalised.
        whiten: (6, m, m) ``W_j = L_j⁻¹``.
        variance: (6,) σ of each output's kernel.
        lengthscale: (6, D).
        noise: (6,) the term's value noise ``ν²``.
        tau: (6, m) s, each whitened weight's forgetting time constant (per output, or per
            weight for a term of several time scales).
        mean: (6, m) ``μ`` when exported.
        cov: (6, m, m) ``Σ`` when exported.
        t: s, the state's time when exported.
        shared: ``η``'s prior a share of the offline band (:func:`gpg.flight.adapt`'s
            ``band="shared"``): the loads' band ``max(b − ψᵀψ, 0) + ψᵀΣψ``, not ``b + ψᵀΣψ``.
    """

    Z: np.ndarray
    whiten: np.ndarray
    variance: np.ndarray
    lengthscale: np.ndarray
    noise: np.ndarray
    tau: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    t: float
    shared: bool = False


@dataclass(frozen=True)
class BankTerm:
    """A bank of ``K`` online terms mixed by their predictions ``L`` labels ahead
    (:class:`gpg.flight.Bank`) with its state when exported. Each member is an
    :class:`OnlineTerm`; a second copy of each (``lagged``) takes every label ``L`` labels late,
    from a ring of the last ``L``, and scores the member: its log weight per load output adds
    the log density of each new label under the lagged copy's band (composed with the offline
    band at the label, as the member's own) and decays by ``e^{−Δt/τ_w}``. The prediction is
    the mixture's: mean ``Σ_k w_k η̄_k``, band ``Σ_k w_k band_k`` plus the members' spread.

    Attributes:
        members: the ``K`` terms (their constants and states when exported; one time).
        lagged_mean: (K, 6, m) the lagged copies' means.
        lagged_cov: (K, 6, m, m) their covariances.
        lagged_t: (K,) s, their times.
        ring_x: (L, D) the waiting labels' normalised inputs.
        ring_y: (L, 6) their residuals against the offline mean (normalised, GP frame).
        ring_r: (L, 6) their noise variances.
        ring_t: (L,) s, their times.
        ring_live: (L,) which slots hold a label.
        count: the labels seen.
        log_weight: (K, 6) the members' log weights per load output.
        weight_tau: s, ``τ_w``.
    """

    members: tuple[OnlineTerm, ...]
    lagged_mean: np.ndarray
    lagged_cov: np.ndarray
    lagged_t: np.ndarray
    ring_x: np.ndarray
    ring_y: np.ndarray
    ring_r: np.ndarray
    ring_t: np.ndarray
    ring_live: np.ndarray
    count: int
    log_weight: np.ndarray
    weight_tau: float

    @property
    def ahead(self) -> int:
        """``L``, the labels each member is scored ahead."""
        return int(self.ring_t.shape[0])

    @property
    def weights(self) -> np.ndarray:
        """(K, 6) the members' weights per load output (each column sums to one), as
        :meth:`gpg.flight.Bank.weights` gives them at the exported state."""
        w = np.exp(self.log_weight - self.log_weight.max(0))
        return w / w.sum(0)


@dataclass(frozen=True)
class TrackedTerm:
    """The tracked coefficients of a model prepared by :func:`gpg.flight.track`
    (:class:`gpg.flight.tracking.Tracker`) with their state when exported: a bank of ``K``
    Kalman filters on the drift ``w`` of the columns ``h = (μ_prior, m (where tracked), the
    physical terms, a bias)`` per load output. Between labels each member relaxes,
    ``w ← a ⊙ w``, ``Σ ← (a aᵀ) ⊙ (Σ − Σ_∞) + Σ_∞`` (``a = e^{−Δt/τ}``, the bias's
    ``e^{−Δt/τ_b,k}``); each label is a rank-one update per output and member, and the
    members are reweighed by their predictive densities with a fixed share. The prediction
    adds the mixture's ``hᵀ w̄`` to the offline mean; the loads' variance is the mixture's
    ``hᵀ Σ h`` (with the members' spread) plus ``v`` and the labels' offset ``σ_o²``.

    Attributes:
        stationary: (6, P, P) ``Σ_∞``.
        tau: s, ``τ``.
        bias_tau: (K,) s, each member's ``τ_b``.
        noise: (6,) ``v`` (normalised units).
        share: the fixed share per label.
        bias: (6,) the bias column (normalised units).
        with_simple: ``M``'s loads are a column (after the prior's mean).
        mean: (K, 6, P) the members' means when exported.
        cov: (K, 6, P, P) their covariances.
        log_weight: (K,) their log weights.
        t: s, the state's time when exported.
        offset: (6,) ``σ_o²``, the labels' offset's variance (normalised units; zeros: none),
            in the band, not the gain.
        wind_mean: (3,) m/s, the wind state's mean ``ḡ`` when exported (world), or None: no
            wind state (:func:`gpg.flight.gusts`).
        wind_cov: (3, 3) its covariance ``P_g``.
        wind_tau: s, ``τ_g``.
        wind_sd: (3,) m/s, its stationary standard deviations.
    """

    stationary: np.ndarray
    tau: float
    bias_tau: np.ndarray
    noise: np.ndarray
    share: float
    bias: np.ndarray
    with_simple: bool
    mean: np.ndarray
    cov: np.ndarray
    log_weight: np.ndarray
    t: float
    offset: np.ndarray
    wind_mean: np.ndarray | None = None
    wind_cov: np.ndarray | None = None
    wind_tau: float | None = None
    wind_sd: np.ndarray | None = None


@dataclass(frozen=True)
class Correction:
    """What a model corrected by flights adds to its prior's closed form
    (:class:`gpg.flight.correction.Corrected`), in the GP's normalised units: per load output
    ``j``, the mean ``ρ_j μ_j + κ_j m_j(x) + Σ_t β_jt h_jt(x) + δ_j(x̂)`` and the predictive
    variance ``ρ_j² c_j max(v, 0) + var δ_j + ‖Cⱼᵀ(h̄_j − G_jᵀ k_j)‖²`` (``v`` the prior's
    latent variance, ``h̄`` the integrated columns: the prior's mean, ``m``, then ``h``);
    the levels ``ρ = 1`` and ``c_j max(v, 0)``.

    Attributes:
        scale: (M,) ``ρ``.
        kappa: (6,) ``κ``, or None (no ``M`` term).
        beta: (6, T) the physical columns' coefficients, or None (no physical basis).
        hubs: (4, 3) rotor hubs, body FRD (m), for the rotor columns' moments.
        air_density: kg/m³ of the drag columns.
        rpm_ref: rpm the rotor columns are per.
        deltas: the six discrepancies.
        with_prior: the integrated columns start with the prior's mean.
        with_simple: then ``M``'s loads.
        G: six (m, P) ``K⁻¹ H`` (the integrated basis's variance), or None.
        cov_chol: (6, P, P) ``C``, or None.
        online: the online term of an adapted model, or None.
        tracked: the tracked coefficients of a tracked model, or None.
        bank: the bank of online terms of a model from :func:`gpg.flight.adapt_bank`, or
            None (C writes it with its update, CasADi and ONNX at its exported state).
    """

    scale: np.ndarray
    kappa: np.ndarray | None
    beta: np.ndarray | None
    hubs: np.ndarray
    air_density: float
    rpm_ref: float
    deltas: list[Discrepancy]
    with_prior: bool
    with_simple: bool
    G: list[np.ndarray] | None
    cov_chol: np.ndarray | None
    online: OnlineTerm | None = None
    tracked: TrackedTerm | None = None
    bank: BankTerm | None = None

    @property
    def has_variance(self) -> bool:
        return all(d.whiten is not None for d in self.deltas)

    def nbytes(self, variance: bool) -> int:
        """Bytes of its arrays in double (the writers keep them so), the triangles' halves.

        Args:
            variance: whether the variance's arrays count.

        Returns:
            The bytes.
        """
        n = sum(d.points.size + d.weights.size + d.lengthscale.size + 3 for d in self.deltas)
        n += self.scale.size + 12 + (0 if self.beta is None else self.beta.size + 6)
        if variance and self.has_variance:
            for d in self.deltas:
                m = d.points.shape[0]
                n += (m * (m + 1) // 2) * (1 if d.post is None else 2)
            if self.G is not None:
                n += sum(g.size for g in self.G) + self.cov_chol.size
        if self.online is not None:
            o = self.online
            n += o.Z.size + o.whiten.size + o.lengthscale.size + o.mean.size + o.cov.size + 20
        if self.tracked is not None:
            r = self.tracked
            n += r.stationary.size + r.mean.size + r.cov.size + 3 * r.bias_tau.size + 16
        if self.bank is not None:
            for o in self.bank.members:
                n += o.Z.size + o.whiten.size + o.lengthscale.size + 2 * (o.mean.size + o.cov.size)
            n += self.bank.ring_x.size + 3 * self.bank.ring_y.size + 20
        return 8 * n


@dataclass(frozen=True)
class Layout:
    """Everything an export writes, as float64 NumPy (the factor also in its stored dtype).
    Called ``Spec`` before gpg 0.3 (that name still reads, with a warning, for one release)."""

    model: str
    frame: str  # the GP's inputs: "airflow" (x_H, 8) or "body" (rpm and R_WBᵀ v_air, 7)
    hover_speed: float
    ball_radius: float  # body frame: in_domain holds |R_WBᵀ v_air| <= this (m/s); else inf
    x_lo: np.ndarray
    half: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    allocation: np.ndarray | None
    level_names: tuple[str, ...]
    sigma: float
    lengthscale: np.ndarray  # (D,)
    grad_dims: tuple[int, ...]
    noise: float  # ν², normalised units
    output_scale: np.ndarray  # (M,)
    global_mean: dict[str, np.ndarray] | None  # xs, coef (GlobalMean's arrays)
    bins: Bins | None
    correction: Correction | None = None  # a model corrected by flights: what it adds
    # airflow from behind read at the state's half-turn image (Surrogate.half_turn)
    half_turn: bool = False
    record: dict[str, Any] = field(default_factory=dict)

    @property
    def n_outputs(self) -> int:
        return self.y_mean.size

    @property
    def dim(self) -> int:
        """``D``: inputs of the GP (8 in the airflow frame, 7 in the body frame)."""
        return self.x_lo.size

    @property
    def has_variance(self) -> bool:
        prior = self.bins is not None and self.bins.factor is not None
        return prior and (self.correction is None or self.correction.has_variance)

    def constant_bytes(self, itemsize: int, variance: bool) -> int:
        """Bytes of the GP's arrays at ``itemsize``, what a writer checks against ``max_bytes``.

        The global mean's training positions count in double whatever ``itemsize`` (the C
        writer keeps them so), a variance factor at most at its stored size, and only the
        entries of each row's non-zero span (what the writers keep of a triangle).

        Args:
            itemsize: bytes per stored number (8 for double, 4 for float).
            variance: whether the variance's factors and points count.

        Returns:
            The bytes of constants.
        """
        n = 0
        if self.global_mean is not None:  # positions in double (gpg.export.c_source)
            gm = self.global_mean  # C: coef; ONNX: alpha, of the same size
            n += gm["xs"].size * 8 + (gm["coef"].size + gm["inv_ls"].size + 1) * itemsize
        if self.bins is not None:
            b = self.bins
            pts = sum(p.size for p in b.points) + (0 if b.shared is None else b.shared.size)
            if b.coef is not None:
                n += sum(c.size for c in b.coef) * itemsize
            if variance and b.factor is not None:
                n += pts * itemsize
                fsize = min(itemsize, b.factor_dtype.itemsize)
                n += sum(_triangle_size(f) for f in b.factor) * fsize
            elif b.coef is not None:
                n += pts * itemsize
        if self.correction is not None:
            n += self.correction.nbytes(variance)
        return n


def _triangle_size(F: np.ndarray) -> int:
    """Entries of ``F`` inside each row's first-to-last non-zero span (what a writer keeps)."""
    first, last = row_spans(F)
    return int(np.sum(np.maximum(last - first, 0)))


def row_spans(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``F``: its first non-zero column and one past its last (equal when none)."""
    nz = F.T != 0
    any_ = nz.any(axis=0)
    first = np.where(any_, nz.argmax(axis=0), 0)
    last = np.where(any_, nz.shape[0] - nz[::-1].argmax(axis=0), 0)
    return first, last


def spec(sur: Surrogate, *, variance: bool = True, max_bytes: int | None = None) -> Layout:
    """The export layout of ``sur``, or ``ValueError`` saying why it cannot be exported.

    The exact kinds' variance is checked against ``max_bytes`` on its triangle's size before
    the factor is made dense: the dense ``(N(1+G))²`` factor of a large model would not fit in
    memory.

    Args:
        sur: the fitted surrogate, airflow or body frame.
        variance: whether to keep the variance factors (the mean alone otherwise).
        max_bytes: the most bytes an exact model's variance may take; None for no limit.

    Returns:
        The layout, with its record (gpg version, model, SHA-256 of the arrays, units).

    Raises:
        ValueError: if ``sur`` is not a Surrogate, has a noise model ``M_noise`` (its acoustic
            model is not exported) or a model kind without a closed form here (a model
            corrected by flights included), or is an exact model whose factor has rows in a
            non-layout order (a model grown by ``condition``), whose variance's triangle alone
            is over ``max_bytes``, or whose arrays are not finite; a bank of online terms
            (:func:`gpg.flight.adapt_bank`) without its variance.
    """
    if not isinstance(sur, Surrogate):
        raise ValueError(f"export takes a gpg.Surrogate, got {type(sur).__name__}")
    if sur.noise_model is not None:
        raise ValueError(
            "a surrogate with M_noise cannot be exported (its acoustic model, "
            "gpg.quadrotor.simple_noise, is not): fit without the noise model"
        )
    m = sur.model
    d = int(np.asarray(sur.box_lo).size)
    global_mean, bins = None, None
    if isinstance(m, HybridGP):
        global_mean = _global(m.mean)
        bins = _binned(m.local, coef=False, variance=variance)
        grad_dims, ls, sigma = m.local.grad_dims, m.local.lengthscale, m.local.variance
    elif isinstance(m, ExactGP):
        global_mean = _global(m.mean)
        if variance:
            _check_exact_size(m, max_bytes)
            bins = _exact_bins(m)
        grad_dims, ls, sigma = m.grad_dims, m.hyper.lengthscale, m.hyper.variance
    elif isinstance(m, BinnedGP):
        bins = _binned(m, coef=True, variance=variance)
        grad_dims, ls, sigma = m.grad_dims, m.lengthscale, m.variance
    elif type(m).__name__ == "Corrected":  # gpg.flight: imported only where used
        prior = spec(dataclasses.replace(sur, model=m.prior), variance=variance,
                     max_bytes=max_bytes)  # fmt: skip
        out = dataclasses.replace(prior, model=sur.model_name,
                                  correction=_correction(sur, m, variance))  # fmt: skip
        _require_finite(out)
        return _with_record(out)
    else:
        raise ValueError(
            f"model {sur.model_name!r} ({type(m).__name__}) has no exportable closed form"
        )
    norm = sur.normalizer
    out = Layout(
        model=sur.model_name,
        frame=sur.frame,
        hover_speed=float(sur.hover_speed),
        half_turn=bool(sur.half_turn),
        ball_radius=float(sur.ball_radius) if sur.frame == "body" else float("inf"),
        x_lo=_f64(norm.x_lo),
        half=_f64(norm.half_range),
        y_mean=_f64(norm.y_mean),
        y_std=_f64(norm.y_std),
        box_lo=_f64(sur.box_lo),
        box_hi=_f64(sur.box_hi),
        allocation=None if sur.simple is None else _f64(sur.simple.allocation),
        level_names=tuple(sur.output_names[len(AERO) :]),
        sigma=float(np.asarray(sigma)),
        lengthscale=np.broadcast_to(_f64(ls), (d,)).copy(),
        grad_dims=tuple(int(g) for g in grad_dims),
        noise=float(np.asarray(m.noise)),
        output_scale=_f64(m.output_scale),
        global_mean=global_mean,
        bins=bins,
    )
    _require_finite(out)
    return _with_record(out)


def _f64(a) -> np.ndarray:
    return np.array(a, dtype=np.float64)


def _correction(sur: Surrogate, m: Any, variance: bool) -> Correction:
    """The arrays a model corrected by flights adds to its prior's (:class:`Correction`)."""
    from gpg.gp.inducing import InducingGP

    if m.tracker is not None and m.explicit is None:
        raise ValueError(
            f"model {sur.model_name!r} tracks the coefficients of a correction without the "
            "physical basis (gpg.flight.track): only a tracked correct(..., basis='physical') "
            "exports"
        )
    if m.wind_state() is not None and not variance:
        raise ValueError(
            f"model {sur.model_name!r} tracks a wind state (gpg.flight.gusts): its update reads "
            "the discrepancies' variance, so it exports with variance=True only"
        )
    if len(m.delta) not in (0, 6):
        raise ValueError(f"a corrected model exports with six discrepancies, got {len(m.delta)}")
    d_in = int(m.prior.n_inputs)
    deltas = []
    for d in m.delta:
        h = d.hyper
        ls = np.broadcast_to(_f64(h.lengthscale), (d_in,)).copy()
        if isinstance(d, InducingGP):
            w, W, P = _f64(d.weights)[:, 0], _f64(d.whiten), _f64(d.post)
        else:
            if d.order is not None or d.observed is not None or d.bases is not None:
                raise ValueError("a discrepancy GP grown by condition does not export: refit it")
            w, W, P = _f64(d.alpha)[:, 0], _f64(d.chol_inv.to_dense()), None
        if not variance or W.shape[0] == 0:
            W = P = None
        deltas.append(Discrepancy(points=_f64(d.X), weights=w, lengthscale=ls,
                                  sigma=float(h.variance), noise=float(h.noise),
                                  output_scale=float(np.asarray(d.output_scale)[0]),
                                  whiten=W, post=P))  # fmt: skip
    e = m.explicit
    hubs = np.zeros((4, 3)) if sur.simple is None else _f64(sur.simple.positions)
    if e is not None:
        hubs = _f64(e.physics.positions)
    return Correction(
        scale=_f64(m.scale),
        kappa=None if m.kappa is None else _f64(m.kappa),
        beta=None if e is None else _f64(e.beta),
        hubs=hubs,
        # the physics' constants, or any number where the model has no physical basis
        air_density=1.0 if e is None else float(e.physics.air_density),
        rpm_ref=1.0 if e is None else float(e.physics.rpm_ref),
        deltas=deltas,
        with_prior=bool(e is not None and e.with_prior),
        with_simple=bool(e is not None and e.with_simple),
        G=None if e is None or not variance else [g for g in _f64(e.G)],
        cov_chol=None if e is None or not variance else _f64(e.cov_chol),
        online=None if m.online is None or _is_bank(m.online) else _online(m.online, d_in),
        tracked=None if m.tracker is None else _tracked(m.tracker),
        bank=_bank(m.online, d_in, variance) if _is_bank(m.online) else None,
    )


def _is_bank(o: Any) -> bool:
    return o is not None and hasattr(o, "lagged")


def _bank(b: Any, d_in: int, variance: bool) -> BankTerm:
    """A :class:`gpg.flight.Bank` laid out: its members one by one, the lagged copies'
    states, the ring and the weights."""
    if not variance:
        raise ValueError(
            "a bank of online terms (gpg.flight.adapt_bank) scores its members under the "
            "offline band at each label: it exports with variance=True only"
        )
    k = int(b.log_weight.shape[0])
    return BankTerm(
        members=tuple(
            _online(jax.tree.map(lambda a, i=i: a[i], b.members), d_in) for i in range(k)
        ),  # fmt: skip
        lagged_mean=_f64(b.lagged.mean),
        lagged_cov=_f64(b.lagged.cov),
        lagged_t=_f64(b.lagged.t),
        ring_x=_f64(b.ring_x),
        ring_y=_f64(b.ring_y),
        ring_r=_f64(b.ring_r),
        ring_t=_f64(b.ring_t),
        ring_live=np.asarray(b.ring_live, bool),
        count=int(np.asarray(b.count)),
        log_weight=_f64(b.log_weight),
        weight_tau=float(np.asarray(b.weight_tau)),
    )


def _tracked(r: Any) -> TrackedTerm:
    return TrackedTerm(
        stationary=_f64(r.stationary),
        tau=float(np.asarray(r.tau)),
        bias_tau=_f64(r.bias_tau),
        noise=_f64(r.noise),
        share=float(np.asarray(r.share)),
        bias=_f64(r.bias_column())[:, 0],
        with_simple=bool(r.with_simple),
        mean=_f64(r.mean),
        cov=_f64(r.cov),
        log_weight=_f64(r.log_weight),
        t=float(np.asarray(r.t)),
        offset=np.zeros(6) if r.offset is None else _f64(r.offset),
        **({} if r.wind_mean is None else {
            "wind_mean": _f64(r.wind_mean), "wind_cov": _f64(r.wind_cov),
            "wind_tau": float(np.asarray(r.wind_tau)), "wind_sd": _f64(r.wind_sd)}),
    )  # fmt: skip


def refuse_wind(s: Layout, fmt: str) -> None:
    """Refuse, by name, a tracked model with a wind state in an export that does not write it.

    Args:
        s: the layout.
        fmt: the export's name, for the message.

    Raises:
        ValueError: ``s`` tracks a wind state.
    """
    c = s.correction
    if c is not None and c.tracked is not None and c.tracked.wind_mean is not None:
        raise ValueError(
            f"model {s.model!r} tracks a wind state (gpg.flight.gusts): its prediction "
            f"differentiates the model in the air velocity, which {fmt} does not write (the C "
            "export does); export the model tracked without it (gpg.flight.track with a drift "
            "whose wind_sd is empty)"
        )


def _online(o: Any, d_in: int) -> OnlineTerm:
    return OnlineTerm(
        Z=_f64(o.Z),
        whiten=_f64(o.whiten),
        variance=_f64(o.variance),
        lengthscale=np.broadcast_to(_f64(o.lengthscale), (6, d_in)).copy(),
        noise=_f64(o.noise),
        tau=_f64(o.tau_per_weight()),
        mean=_f64(o.mean),
        cov=_f64(o.cov),
        t=float(np.asarray(o.t)),
        shared=bool(getattr(o, "shared", False)),
    )


def _online_arrays(o: OnlineTerm, prefix: str):
    """An online term's arrays by name, for the record's hash."""
    for key in ("Z", "whiten", "variance", "lengthscale", "noise", "mean", "cov"):
        yield f"{prefix}_{key}", getattr(o, key)
    yield f"{prefix}_tau_t", np.r_[o.tau.ravel(), o.t]


def _bank_arrays(bk: BankTerm):
    """A bank's arrays by name, for the record's hash."""
    for i, o in enumerate(bk.members):
        yield from _online_arrays(o, f"bank{i}")
    for key in ("lagged_mean", "lagged_cov", "lagged_t", "ring_x", "ring_y", "ring_r", "ring_t",
                "log_weight"):  # fmt: skip
        yield f"bank_{key}", getattr(bk, key)
    yield "bank_scalars", np.r_[bk.ring_live.astype(float), bk.count, bk.weight_tau]


def _global(mean: GlobalMean) -> dict[str, np.ndarray]:
    """The folded mean's arrays, and ``alpha``: its coefficients unfolded back to
    ``[α⁰, α^{g_0}, …]`` (N, (1+G)M), for a writer that sums in float: the folded value block
    ``α⁰ − Σ_g (x_g/l_g²) αᵍ`` cancels against ``x_q,g/l_g² Σ k αᵍ``, the unfolded sum
    ``Σ_p k_p [α⁰_p + Σ_g (x_q,g − x_p,g)/l_g² αᵍ_p]`` has no such cancellation."""
    xs, coef, inv_ls = _f64(mean.Xs), _f64(mean.coef), _f64(mean.inv_ls)
    m = coef.shape[1] // (1 + len(mean.grad_dims))
    alpha = coef.copy()
    for i, g in enumerate(mean.grad_dims):
        alpha[:, :m] += (xs[:, g] * inv_ls[g])[:, None] * coef[:, (1 + i) * m : (2 + i) * m]
    return {"xs": xs, "coef": coef, "alpha": alpha, "inv_ls": inv_ls,
            "sigma": _f64(mean.variance).reshape(1)}  # fmt: skip


def _check_exact_size(m: ExactGP, max_bytes: int | None) -> None:
    """Refuse the exact variance when its triangle, at float32 or its stored size if smaller,
    cannot fit ``max_bytes`` whatever the writer (the writers check their own size after)."""
    if max_bytes is None:
        return
    n = int(np.asarray(m.X).shape[0]) * (1 + len(m.grad_dims))
    least = n * (n + 1) // 2 * min(4, np.dtype(m.chol_inv.dtype).itemsize)
    if least > max_bytes:
        raise ValueError(
            f"the variance of exact {type(m).__name__} over {n} rows holds at least "
            f"{least / 2**20:.1f} MiB of constants, over max_bytes={max_bytes / 2**20:.1f} MiB: "
            "export it with variance=False (gpgs_hybrid's near-set variance is the real-time one)"
        )


def _exact_bins(m: ExactGP) -> Bins:
    if m.order is not None or m.observed is not None:
        raise ValueError(
            "this exact model's variance factor covers rows in another order than its layout "
            "(a model grown by condition, or cases without some gradients): export it with "
            "variance=False, or refit it"
        )
    F = m.chol_inv.to_dense()
    if m.bases is not None:  # directional rows (all observed): F P over coordinate rows
        F = (F.astype(np.float64) @ _turn(np.asarray(m.bases, float), 0)).astype(F.dtype)
    return Bins(
        points=[_f64(m.X)],
        shared=None,
        coef=None,
        factor=[F],
        factor_dtype=np.dtype(m.chol_inv.dtype),
        **_one_bin(),
    )


def _one_bin() -> dict[str, Any]:
    z = np.zeros(1)
    return dict(scheme="slab", split_dim=z.astype(int), split_value=z[:0], left=z, right=z, depth=1)


def _binned(m: BinnedGP, *, coef: bool, variance: bool) -> Bins | None:
    """The real rows of every bin of ``m`` (its padding dropped)."""
    if not coef and not (variance and m.factor):
        return None
    g = len(m.grad_dims)
    P = m.Xn.shape[1]
    up = 0 if m.shared is None else m.shared.shape[0] * (1 + g)
    Xn, n_near = np.asarray(m.Xn, float), np.asarray(m.n_near)
    points, coefs, factors = [], [], []
    for b in range(Xn.shape[0]):
        p = int(n_near[b])
        pos = np.concatenate([np.arange(up), up + near_rows(np.arange(p), P, g)])
        points.append(Xn[b, :p].copy())
        if coef:
            coefs.append(np.asarray(m.coef[b], float)[:, pos])
        if variance and m.factor:
            F = m.factor[b].to_dense()[np.ix_(pos, pos)]
            if m.bases is not None:  # directional rows: F P_b reads coordinate kernel rows
                F = (F.astype(np.float64) @ _turn(np.asarray(m.bases[b], float)[:p], up)).astype(
                    F.dtype
                )
            factors.append(F)
    part = m.partition
    return Bins(
        points=points,
        shared=None if m.shared is None else _f64(m.shared),
        coef=coefs if coef else None,
        factor=factors if factors else None,
        factor_dtype=np.dtype(m.factor[0].dtype) if m.factor else np.dtype(np.float64),
        scheme=part.scheme,
        split_dim=np.asarray(part.split_dim, int),
        split_value=_f64(part.split_value),
        left=np.asarray(part.left, int),
        right=np.asarray(part.right, int),
        depth=int(part.depth),
    )


def _turn(B: np.ndarray, up: int) -> np.ndarray:
    """``P`` (r, r) over a bin's rows (``up`` shared rows, then its points' dimension-major
    rows) with ``k̄_dir = P k̄``: gradient row ``g`` of point ``i`` is ``Σ_h B[i, g, h]`` times
    its coordinate row ``h`` (:func:`gpg.gp.gram.to_bases`), so that a factor ``F`` over
    directional rows is ``F P`` over the coordinate rows every writer emits. Only the rows of
    one point mix: ``F P`` stays triangular but for the gradient blocks' trailing square."""
    p, g = B.shape[0], B.shape[1]
    P = np.eye(up + p * (1 + g))
    i = np.arange(p)
    for a in range(g):
        for c in range(g):
            P[up + (1 + a) * p + i, up + (1 + c) * p + i] = B[:, a, c]
    return P


def _arrays(s: Layout):
    yield from ((k, getattr(s, k)) for k in ("x_lo", "half", "y_mean", "y_std", "box_lo", "box_hi"))
    yield "lengthscale", s.lengthscale
    yield "output_scale", s.output_scale
    yield "sigma_noise", np.array([s.sigma, s.noise])
    if s.allocation is not None:
        yield "allocation", s.allocation
    if s.global_mean is not None:
        yield from s.global_mean.items()
    if s.correction is not None:
        c = s.correction
        yield "corr_scale", c.scale
        for key in ("kappa", "beta", "cov_chol"):
            if getattr(c, key) is not None:
                yield f"corr_{key}", getattr(c, key)
        yield "corr_hubs", c.hubs
        if c.online is not None:
            yield from _online_arrays(c.online, "online")
        if c.bank is not None:
            yield from _bank_arrays(c.bank)
        if c.tracked is not None:
            r = c.tracked
            for key in ("stationary", "bias_tau", "noise", "bias", "mean", "cov", "log_weight",
                        "offset", "wind_mean", "wind_cov", "wind_sd"):  # fmt: skip
                if getattr(r, key) is not None:
                    yield f"tracked_{key}", getattr(r, key)
            yield "tracked_scalars", np.array([r.tau, r.share, r.t, r.wind_tau or 0.0,
                                               float(r.with_simple)])  # fmt: skip
        for j, d in enumerate(c.deltas):
            yield f"delta{j}_points", d.points
            yield f"delta{j}_weights", d.weights
            yield (
                f"delta{j}_hyper",
                np.concatenate([d.lengthscale, [d.sigma, d.noise, d.output_scale]]),
            )
            for key in ("whiten", "post"):
                if getattr(d, key) is not None:
                    yield f"delta{j}_{key}", getattr(d, key)
            if c.G is not None:
                yield f"delta{j}_G", c.G[j]
    if s.bins is not None:
        b = s.bins
        for i, p in enumerate(b.points):
            yield f"points{i}", p
            if b.coef is not None:
                yield f"bin_coef{i}", b.coef[i]
            if b.factor is not None:
                yield f"factor{i}", b.factor[i]
        if b.shared is not None:
            yield "shared", b.shared
        yield "split_value", b.split_value


def _require_finite(s: Layout) -> None:
    bad = sorted(k for k, a in _arrays(s) if not np.all(np.isfinite(a)))
    if bad:
        raise ValueError(f"the surrogate holds non-finite arrays {bad}: nothing exported")


def _with_record(s: Layout) -> Layout:
    h = hashlib.sha256()
    for k, a in _arrays(s):
        h.update(k.encode())
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    record = {
        "gpg_version": __version__,
        "model": s.model,
        "arrays_sha256": h.hexdigest(),
        "variance": s.has_variance,
        # the same world-frame call either way; "body": the GP reads rpm and R_WBᵀ v_air
        "gp_frame": s.frame,
        "inputs": "rpm[4] (rpm), euler[3] (rad, yaw pitch roll, R_WB = Rz Ry Rx), "
        "v_air[3] (m/s, vehicle velocity minus wind, world frame x forward y right z down)",
        "outputs": "force[3] (N), torque[3] (N*m), world frame; levels[K] (dB); variance[6+K] "
        "of each (N^2, (N*m)^2, dB^2) in the same frame",
        "levels": list(s.level_names),
        "hover_speed": s.hover_speed,
        "half_turn": s.half_turn,
        **({"ball_radius": s.ball_radius} if s.frame == "body" else {}),
        "max_frame_rate": MAX_FRAME_RATE,
    }
    object.__setattr__(s, "record", record)
    return s


def reference(s: Layout, xn: np.ndarray, b: int | None = None) -> tuple[np.ndarray, float | None]:
    """Normalised mean (M,) and latent variance at one normalised query ``xn`` (D,) in float64
    NumPy from the spec's arrays: the computation every writer emits, for their tests."""
    bins = s.bins
    if b is None:
        b = 0 if bins is None else bins.lookup(xn)
    if s.global_mean is not None:
        mean = global_mean(s, xn)
    else:
        mean = bins.coef[b] @ kernel_row(s, xn, b)
    if not s.has_variance:
        return mean, None
    fk = bins.factor[b] @ kernel_row(s, xn, b)
    return mean, s.sigma - float(fk @ fk)


def global_mean(s: Layout, xn: np.ndarray) -> np.ndarray:
    """The folded global mean of :mod:`gpg.gp.mean` at ``xn``, normalised units."""
    gm = s.global_mean
    inv_ls = gm["inv_ls"]
    k = gm["sigma"][0] * np.exp(-0.5 * np.sum((xn * inv_ls - gm["xs"]) ** 2, axis=1))
    out = (k @ gm["coef"]).reshape(1 + len(s.grad_dims), s.n_outputs)
    g = list(s.grad_dims)
    return out[0] + (xn[g] * inv_ls[g] ** 2) @ out[1:] if g else out[0]


def kernel_row(s: Layout, xn: np.ndarray, b: int) -> np.ndarray:
    """``k̄(x̂, X_b)`` (R_b,): the shared rows, then bin ``b``'s own."""
    bins = s.bins
    blocks = [] if bins.shared is None else [_rows(s, xn, bins.shared)]
    return np.concatenate(blocks + [_rows(s, xn, bins.points[b])])


def _rows(s: Layout, xn: np.ndarray, X: np.ndarray) -> np.ndarray:
    k = s.sigma * np.exp(-0.5 * np.sum(((xn - X) / s.lengthscale) ** 2, axis=1))
    g = list(s.grad_dims)
    diff = (xn[g] - X[:, g]).T / (s.lengthscale[g] ** 2)[:, None]  # (G, p)
    return np.concatenate([k, (k[None] * diff).ravel()])


def __getattr__(name: str):
    # gpg.export.layout.Spec, the name before gpg 0.3: one release
    if name == "Spec":
        from gpg._deprecated import deprecated

        deprecated("gpg.export.layout.Spec", "gpg.export.layout.Layout")
        return Layout
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
