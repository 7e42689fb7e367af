"""A fitted surrogate as self-contained C source: :func:`to_c` writes ``<name>.c`` and
``<name>.h`` with the trained arrays as constants and no dependency but libm.

The generated functions compute what :meth:`Surrogate.predict` does for one world-frame state:
the airflow frame (with its hover blend), the attitude in it, the normalisation, the GP (the
global folded mean of :mod:`gpg.gp.mean` or the query's bin's mean, and the variance
``σ − ‖F_b k̄‖²`` of the query's bin, found by the partition's tree), the rotation back to the
world frame and the simplified model ``M``. ``in_domain`` is the data's box, finite inputs
and outputs, rotor speeds ≥ 0 and the airflow frame's turn rate
(:func:`gpg.quadrotor.frames.airflow_frame_rate`, here by central differences, so a query
within rounding of the threshold may be flagged differently). A body-frame surrogate has no
airflow frame: the GP reads ``(rpm, R_WBᵀ v_air)``, ``R_WB`` turns its outputs back, and
``in_domain`` is the rotor box and the ball ``|R_WBᵀ v_air| ≤ V`` (``BODY_FRAME`` in the
source; the call is the same).

``dtype="float"`` stores the GP's arrays in float (half the bytes, for a flight controller's
flash) and evaluates the kernel and the variance's product in float; the frame, the
normalisation and the mean's sums stay in double, and so do the global mean's training
positions and the value block of its coefficients, where its folded sum cancels
(:func:`_split_coef`). A variance factor stored in float32 (the
default model's ``variance_dtype``) is written as float in either dtype: its values are
exactly those floats, and the product is then accumulated in the dtype asked for.
"""

from __future__ import annotations

import json
import re
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gpg._io import atomic_write
from gpg.export.layout import MAX_BYTES, Layout, row_spans, spec
from gpg.names import inputs
from gpg.quadrotor.frames import TINY_SPEED
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

__all__ = ["to_c"]

DTYPES = {"double": (np.float64, "double"), "float": (np.float32, "float")}
# m/s, the step of the wind state's fourth-order central differences in C (the library's
# Jacobian is JAX's): truncation ~h⁴ f⁽⁵⁾/30 and rounding ~ε|f|/h, both near 1e-11 of the
# residual at the model's lengthscales of metres per second (the design notes).
WIND_FD_STEP = 1e-3


def to_c(
    sur: Surrogate,
    directory: str | Path,
    *,
    name: str = "gpg_model",
    dtype: str = "double",
    variance: bool = True,
    max_bytes: int = MAX_BYTES,
) -> dict[str, Any]:
    """Write ``<directory>/<name>.c`` and ``<name>.h``: ``sur``'s prediction in C.

    The header documents the calls, which return ``in_domain`` (1 or 0):

    * ``int <name>_mean(const double rpm[4], const double euler[3], const double v_air[3],
      double force[3], double torque[3], double *levels)``;
    * with ``variance`` (and a model that has one): ``int <name>_predict(..., double *levels,
      double *variance)``, ``variance[6 + K]`` the predictive variance of force, torque (world
      frame) and levels as :meth:`Surrogate.predict` gives it.

    For a model adapted while flying (:func:`gpg.flight.adapt`) the header also declares its
    online state ``<name>_online`` and ``<name>_online_init``, ``_online_update`` (one label)
    and ``_online_predict``; ``<name>_mean`` and ``_predict`` are the model without the term.
    So does a tracked model (:func:`gpg.flight.track`), its state the filters' and, with a wind
    state (:func:`gpg.flight.gusts`; ``variance`` needed), the wind's: its update and
    prediction take the model's derivative in the air velocity by fourth-order central
    differences (:data:`WIND_FD_STEP`) where the library's is ``jax.jacfwd``. So does a
    model adapted by a bank of online terms (:func:`gpg.flight.adapt_bank`; ``variance``
    needed: its update scores the members under the offline band), its state the members',
    their lagged copies', the ring of waiting labels and the weights.

    Units rpm, rad (yaw, pitch, roll: ``R_WB = Rz Ry Rx``), m/s, N, N·m, dB; world frame x
    forward, y right, z down; the same call for a surrogate of either frame. The header
    declares ``<name>_box_lo[D]`` and ``_box_hi[D]``, the GP's input box (``D`` =
    ``<NAME>_N_INPUTS``: 8 airflow-frame inputs, or 7 body-frame ones). A non-finite input
    gives 0 and zeros, never NaN.

    Args:
        sur: the fitted surrogate, airflow or body frame.
        directory: where to write (made if missing).
        name: the C identifier that names the files, the functions and the header's macros.
        dtype: ``"double"``, or ``"float"`` for the GP's arrays and kernel in float (half the
            bytes; the frame, normalisation and the mean's sums stay in double).
        variance: whether to write ``<name>_predict`` with the variance (for a model that has
            one).
        max_bytes: the most bytes of constants written.

    Returns:
        What was written: ``c`` and ``h`` (paths), ``constant_bytes`` (bytes of the GP's
        constants), ``variance`` (whether ``<name>_predict`` exists) and ``record`` (gpg
        version, model, arrays' SHA-256, units, dtype).

    Raises:
        ValueError: nothing written, for a model :func:`gpg.export.layout.spec` refuses, a
            ``name`` that is not a C identifier, an unknown ``dtype``, or constants over
            ``max_bytes``.
    """
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {list(DTYPES)}, got {dtype!r}")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    s = spec(sur, variance=variance, max_bytes=max_bytes)
    itemsize = np.dtype(DTYPES[dtype][0]).itemsize
    n_const = s.constant_bytes(itemsize, variance=s.has_variance)
    if s.global_mean is not None:  # the folded mean's value block in double (_split_coef),
        # and both blocks' rows padded to whole vectors (_coef_sums)
        n, m = s.global_mean["xs"].shape[0], s.n_outputs
        g = s.global_mean["coef"].shape[1] - m
        n_const += n * (_padded(m, 4) * 8 - m * itemsize)
        n_const += n * (_padded(g, 4) - g) * itemsize
    if s.correction is not None and s.has_variance:  # one triangle per δ (variance_factor),
        # stored in the dtype asked for (treal)
        tri = [(d.points.shape[0] * (d.points.shape[0] + 1)) // 2 for d in s.correction.deltas]
        n_const -= 8 * sum(t for t, d in zip(tri, s.correction.deltas, strict=True)
                           if d.post is not None)  # fmt: skip
        n_const -= (8 - itemsize) * sum(tri)
    if n_const > max_bytes:
        raise ValueError(
            f"the export of {s.model!r} holds {n_const / 2**20:.1f} MiB of constants, over "
            f"max_bytes={max_bytes / 2**20:.1f} MiB (variance=False keeps the mean only; "
            "gpgs_hybrid's near-set variance is the real-time one)"
        )
    record = {**s.record, "dtype": dtype}
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    source = _source(name, dtype, s, record)
    header = _header(name, s, record, dtype)
    c_path, h_path = directory / f"{name}.c", directory / f"{name}.h"
    atomic_write(h_path, header.encode())
    atomic_write(c_path, source.encode())
    return {
        "c": c_path,
        "h": h_path,
        "constant_bytes": n_const,
        "variance": s.has_variance,
        "record": record,
    }


def _literal(a: np.ndarray, np_type) -> str:
    """A C initializer (flat) whose values read back exactly in the C type (17 or 9
    significant digits)."""
    a = np.asarray(a, np_type).ravel()
    digits = 17 if np_type is np.float64 else 9
    suffix = "" if np_type is np.float64 else "f"
    vals = [f"{v:.{digits}g}" for v in a.tolist()] or ["0"]
    # "1" and "1e+20" are integer constants or need a point for an "f" suffix to be valid C
    vals = [t if "." in t else t.replace("e", ".e") if "e" in t else t + "." for t in vals]
    vals = [t + suffix for t in vals]
    lines = [", ".join(vals[i : i + 8]) for i in range(0, len(vals), 8)]
    return "{" + ",\n  ".join(lines) + "}"


def _ints(a) -> str:
    return "{" + ", ".join(str(int(v)) for v in np.asarray(a).ravel()) + "}" if len(a) else "{0}"


def _domain_doc(s: Layout) -> str:
    """The header's paragraph on ``in_domain``, for the surrogate's frame."""
    if s.frame == "body":
        return (
            " * returns in_domain: 1 where the rotor speeds lie in the training data's box and\n"
            " * the air velocity in the body frame, R_WB^T v_air = (u, v, w), lies in the ball\n"
            f" * |(u, v, w)| <= {s.ball_radius:.17g} m/s, the inputs and outputs are finite; 0\n"
            " * otherwise (an extrapolation: the values are returned all the same, zeros for\n"
            " * non-finite input). The GP reads the body frame's inputs (r1..r4, u, v, w): no\n"
            " * coordinate singularity, hover and vertical flow included. Its box (rpm, m/s;\n"
            " * in_domain uses the ball inside it):"
        )
    return (
        " * returns in_domain: 1 inside the training data's box (x_H = rpm, attitude in the\n"
        " * airflow frame, airspeed), rotor speeds >= 0, finite inputs and outputs and a\n"
        " * well-conditioned airflow frame; 0 otherwise (an extrapolation: the values are\n"
        " * returned all the same, zeros for non-finite input). The box of x_H (rpm, rad, m/s):"
    )


def _online_header(name: str, s: Layout, c_type: str) -> str:
    """The adapted or tracked model's state and calls, for a model with an online term."""
    if _online(s) is None:
        return ""
    state, relax = _online_state(name, s, c_type)
    wind = ""
    if s.correction.tracked is not None and s.correction.tracked.wind_mean is not None:
        wind = ("; with the wind state, at v_air plus its mean, the loads' variance widened by "
                "diag(J P_g J^T)")  # fmt: skip
    band = ("the loads' band is the filter's, as gpg's predict of a tracked model"
            if s.correction.tracked is not None else "added")  # fmt: skip
    if s.correction.bank is not None:
        band = ("the members' mixture: their means weighted per load output, the band each "
                "member's with the offline one, plus the spread of their means")  # fmt: skip
    return (
        state
        + f"""
/* the state when the model was exported */
void {name}_online_init({name}_online *st);

/* one label at time t (s): the state relaxed since st->t ({relax}), then conditioned on the
 * label's residual against the offline model, as gpg.flight.update. Returns 1, or 0 (the
 * state untouched) for a label with a non-finite value or a negative variance. force,
 * torque: the measured aerodynamic loads (N, N*m, world); force_var, torque_var their noise
 * variances. */
int {name}_online_update({name}_online *st, double t, const double rpm[4],
                         const double euler[3], const double v_air[3], const double force[3],
                         const double torque[3], const double force_var[3],
                         const double torque_var[3]);

/* as {name}_predict{"" if s.has_variance else " (variance: not written; may be 0)"}, with the
 * online term's mean added and its variance ({band}; the state as it is: not relaxed to a
 * later time){wind} */
int {name}_online_predict(const {name}_online *st, const double rpm[4], const double euler[3],
                          const double v_air[3], double force[3], double torque[3],
                          double *levels, double *variance);
"""
    )


def _online_state(name: str, s: Layout, c_type: str) -> tuple[str, str]:
    """The online state's struct (C) and how it relaxes (words), for :func:`_online_header`."""
    o = _online(s)
    if s.correction.bank is not None:
        return _bank_state(name, s.correction.bank, c_type)
    if s.correction.tracked is not None:
        k, p = o.mean.shape[0], o.mean.shape[2]
        wind = "" if o.wind_mean is None else (
            "\n  double wind_mean[3];        /* m/s, the wind state's mean: the air's deviation "
            "from the logged v_air (world) */\n"
            "  double wind_cov[3][3];      /* and its covariance */")  # fmt: skip
        state = f"""
/* The tracked coefficients of the model (gpg.flight.track): a bank of {k} Kalman filters on the
 * drift of the physical basis's {p} columns per load output (the prior's mean,
 * {"M's loads, " if o.with_simple else ""}the physical terms, a bias). The state is the
 * caller's (fixed size; nothing is allocated), one state per vehicle. {name}_mean and
 * {name}_predict above are the model without it (offline). */
#define {name.upper()}_N_MEMBERS {k}
#define {name.upper()}_N_COLUMNS {p}
typedef struct {{
  {c_type} mean[{k}][6][{p}];       /* each member's drift mean, per load output */
  {c_type} cov[{k}][6][{p}][{p}];   /* and its covariance */
  double log_weight[{k}];       /* the members' log weights */
  double t;                   /* s, the time of the last update */{wind}
}} {name}_online;
"""
        taus = ", ".join(f"{b:.6g}" for b in o.bias_tau)
        if o.wind_mean is not None:
            return state, (
                f"time constants {o.tau:.6g} s, for the bias {taus} s and for the wind state "
                f"{o.wind_tau:.6g} s; the wind is conditioned first, linearised at its mean "
                "(its derivative by central differences), then the coefficients at the air "
                "velocity it implies"
            )
        return state, f"time constants {o.tau:.6g} s and, for the bias, {taus} s"
    m = o.Z.shape[0]
    state = f"""
/* The online term of the adapted model (gpg.flight.adapt): the state is the caller's (fixed
 * size, {m} inducing inputs per load output; nothing is allocated), one state per vehicle.
 * {name}_mean and {name}_predict above are the model without it (offline). */
#define {name.upper()}_N_INDUCING {m}
typedef struct {{
  {c_type} mean[6][{m}];       /* the whitened weights' mean, per load output */
  {c_type} cov[6][{m}][{m}];   /* and their covariance */
  double t;                 /* s, the time of the last update */
}} {name}_online;
"""
    if np.all(o.tau == o.tau[0, 0]):
        return state, f"forgetting time constant {o.tau[0, 0]:.6g} s"
    if np.all(o.tau == o.tau[:, :1]):  # one per load output, in the outputs' order
        return state, "forgetting time constants " + ", ".join(
            f"{v:.6g}" for v in o.tau[:, 0]
        ) + " s"
    return state, f"forgetting time constants {o.tau.min():.6g}-{o.tau.max():.6g} s, one per weight"


def _bank_state(name: str, b: Any, c_type: str) -> tuple[str, str]:
    """A bank's state struct (C) and how it relaxes (words), for :func:`_online_state`."""
    k, (m, d), ahead = len(b.members), b.members[0].Z.shape, b.ahead
    state = f"""
/* The bank of online terms of the model (gpg.flight.adapt_bank): {k} terms of {m} inducing
 * inputs per load output, mixed by their predictions {ahead} labels ahead. The state is the
 * caller's (fixed size; nothing is allocated), one state per vehicle. {name}_mean and
 * {name}_predict above are the model without it (offline). */
#define {name.upper()}_N_MEMBERS {k}
#define {name.upper()}_N_INDUCING {m}
#define {name.upper()}_AHEAD {ahead}
typedef struct {{
  {c_type} mean[{k}][6][{m}];          /* each member's whitened weights' mean, per load output */
  {c_type} cov[{k}][6][{m}][{m}];      /* and their covariance */
  {c_type} lag_mean[{k}][6][{m}];      /* the same terms {ahead} labels late: what scores them */
  {c_type} lag_cov[{k}][6][{m}][{m}];
  double lag_t[{k}];               /* s, the lagged terms' times */
  double ring_x[{ahead}][{d}];           /* the last labels (normalised inputs), waiting for them */
  double ring_y[{ahead}][6];           /* their residuals against the offline mean */
  double ring_r[{ahead}][6];           /* their noise variances */
  double ring_t[{ahead}];              /* s, their times */
  int ring_live[{ahead}];              /* which slots hold a label */
  long count;                   /* the labels seen */
  double log_weight[{k}][6];       /* each member's log weight per load output */
  double t;                     /* s, the time of the last update */
}} {name}_online;
"""
    taus = ", ".join(f"{o.tau.min():.6g}-{o.tau.max():.6g}" if o.tau.min() != o.tau.max()
                     else f"{o.tau.min():.6g}" for o in b.members)  # fmt: skip
    return state, (f"the members' forgetting time constants {taus} s, their weights' "
                   f"{b.weight_tau:.6g} s")  # fmt: skip


def _header(name: str, s: Layout, record: dict[str, Any], dtype: str) -> str:
    guard = name.upper() + "_H"
    n_levels = len(s.level_names)
    meta = json.dumps(record, indent=1, sort_keys=True).replace("*/", "* /")
    names = inputs(s.frame)
    box = "\n".join(
        f" *   {names[i]:9s} [{s.box_lo[i]:.17g}, {s.box_hi[i]:.17g}]" for i in range(s.dim)
    )
    predict = (
        f"""
/* as {name}_mean, and variance[{6 + n_levels}]: the predictive variance of force[3] (N^2),
 * torque[3] ((N*m)^2), world frame, and of levels (dB^2), as gpg's Surrogate.predict */
int {name}_predict(const double rpm[4], const double euler[3], const double v_air[3],
                   double force[3], double torque[3], double *levels, double *variance);
"""
        if s.has_variance
        else ""
    )
    return f"""/* {name}: a gpg surrogate's prediction, generated by gpg.export.to_c.
 *
 * {meta}
 *
 * int {name}_mean(rpm, euler, v_air, force, torque, levels)
 *   rpm[4]    rotor speeds, rpm (r1 rear-right, r2 rear-left, r3 front-left, r4 front-right)
 *   euler[3]  yaw, pitch, roll in rad: R_WB = Rz(yaw) Ry(pitch) Rx(roll), body FRD
 *   v_air[3]  air velocity of the vehicle, m/s, world frame (x forward, y right, z down):
 *             vehicle velocity minus wind
 *   force[3], torque[3]  out: aerodynamic force (N) and torque (N*m), world frame
 *   levels[{n_levels}]  out: tonal noise levels, dB ({", ".join(s.level_names) or "none"})
{_domain_doc(s)}
{box}
 * Not thread-hostile: no state is kept between calls.
 */
#ifndef {guard}
#define {guard}

#define {name.upper()}_N_LEVELS {n_levels}
#define {name.upper()}_HAS_VARIANCE {int(s.has_variance)}

#define {name.upper()}_N_INPUTS {s.dim}

extern const double {name}_box_lo[{s.dim}];
extern const double {name}_box_hi[{s.dim}];

int {name}_mean(const double rpm[4], const double euler[3], const double v_air[3],
                double force[3], double torque[3], double *levels);
{predict}{_online_header(name, s, DTYPES[dtype][1])}
#endif
"""


# Long by design: one declaration per array the C code reads, in the order it reads them;
# split, the dtype choices would be made in several places.
def _constants(name: str, dtype: str, s: Layout) -> list[str]:
    """The arrays as C constants: the GP's in ``real`` (the dtype asked for), the variance
    factor in ``freal`` (never wider than it is stored), the rest in double."""
    np_type = DTYPES[dtype][0]
    m = s.n_outputs
    f_type = (
        np.float32
        if dtype == "float" or (s.bins is not None and s.bins.factor_dtype == np.float32)
        else np.float64
    )
    out = [
        f"#define TINY_SPEED {TINY_SPEED!r}",
        f"#define HOVER_SPEED {s.hover_speed!r}",
        f"#define MAX_FRAME_RATE {MAX_FRAME_RATE!r}",
        f"#define N_OUT {m}",
        f"#define D_IN {s.dim}",
        f"#define BODY_FRAME {int(s.frame == 'body')}",
        f"#define HALF_TURN {int(s.half_turn)}",
        # the inputs held to the box: the rotor speeds alone in the body frame (the ball
        # inside the box of u, v, w is in_domain's test there)
        f"#define N_BOX {4 if s.frame == 'body' else s.dim}",
        f"#define BALL_RADIUS {s.ball_radius if s.frame == 'body' else 0.0!r}",
        f"#define N_GRAD {len(s.grad_dims)}",
        f"typedef {DTYPES[dtype][1]} real;",
        f"typedef {'float' if f_type is np.float32 else 'double'} freal;",
        f"#define FREAL_IS_REAL {int(f_type is np_type)}",
    ]

    def dbl(key, a):
        out.append(f"static const double {key}[{max(a.size, 1)}] = {_literal(a, np.float64)};")

    def rl(key, a, c_type="real", t=np_type):
        out.append(f"static const {c_type} {key}[{max(a.size, 1)}] = {_literal(a, t)};")

    for key in ("x_lo", "half", "y_mean", "y_std", "output_scale"):
        dbl(key.upper(), getattr(s, key))
    if s.bins is not None:  # the bins' kernel rows
        dbl("LENGTHSCALE", s.lengthscale)
    dbl("SIGMA_NOISE", np.array([s.sigma, s.noise]))
    out.append(f"static const int GRAD_DIMS[{max(len(s.grad_dims), 1)}] = {_ints(s.grad_dims)};")
    for key in ("box_lo", "box_hi"):
        out.append(f"const double {name}_{key}[{s.dim}] = {_literal(getattr(s, key), np.float64)};")
    if s.allocation is not None:
        dbl("ALLOCATION", s.allocation)
    if s.global_mean is not None:
        gm = s.global_mean
        out.append(f"#define N_MEAN {gm['xs'].shape[0]}")
        dbl("INV_LS_M", gm["inv_ls"])
        dbl("SIGMA_M", gm["sigma"])
        # double whatever the dtype: a float position moves every kernel value by ~1e-7
        # relative, which the mean's cancelling sum amplifies (see docs/measurements.md)
        dbl("XS_T", gm["xs"].T)
        value, grad = _split_coef(gm, s.grad_dims, m, np_type)
        # rows padded to whole vectors of four (_coef_sums loads them as vectors)
        dbl("COEF0", _pad_columns(value, _padded(value.shape[1], 4)))
        rl("COEFG", _pad_columns(grad, _padded(grad.shape[1], 4)))
    b = s.bins
    if b is None:
        return out
    n_pts = [p.shape[0] for p in b.points]
    out.append(f"#define N_BINS {b.n_bins}")
    out.append(f"#define N_SHARED {0 if b.shared is None else b.shared.shape[0]}")
    out.append(f"#define MAX_ROWS {max(b.rows(i, len(s.grad_dims)) for i in range(b.n_bins))}")
    out.append(f"#define SLAB {int(b.scheme == 'slab')}")
    out.append(f"static const int SPLIT_DIM[{max(b.split_dim.size, 1)}] = {_ints(b.split_dim)};")
    dbl("SPLIT_VALUE", b.split_value)
    out.append(f"#define N_CUTS {b.split_value.size}")
    if b.scheme != "slab":
        out.append(f"static const int LEFT[{max(b.left.size, 1)}] = {_ints(b.left)};")
        out.append(f"static const int RIGHT[{max(b.right.size, 1)}] = {_ints(b.right)};")
    out.append(f"static const int BIN_NPTS[{b.n_bins}] = {_ints(n_pts)};")
    out.append(f"static const long BIN_PT_OFF[{b.n_bins}] = {_ints(np.cumsum([0] + n_pts[:-1]))};")
    rl("PTS", np.concatenate(b.points))
    rl("SHARED", b.shared if b.shared is not None else np.zeros(0))
    if b.coef is not None:
        sizes = [c.size for c in b.coef]
        out.append(
            f"static const long BCOEF_OFF[{b.n_bins}] = {_ints(np.cumsum([0] + sizes[:-1]))};"
        )
        rl("BCOEF", np.concatenate([c.ravel() for c in b.coef]))
    if b.factor is not None:
        firsts, lens, data, row_base, offs, pos = [], [], [], [], [], 0
        for F in b.factor:
            first, last = row_spans(F)
            row_base.append(sum(len(f) for f in firsts))
            firsts.append(first)
            lens.append(last - first)
            for i in range(F.shape[0]):
                offs.append(pos)
                data.append(F[i, first[i] : last[i]])
                pos += last[i] - first[i]
        out.append(f"static const long ROW_BASE[{b.n_bins}] = {_ints(row_base)};")
        out.append(f"static const int ROW_FIRST[{len(offs)}] = {_ints(np.concatenate(firsts))};")
        out.append(f"static const int ROW_LEN[{len(offs)}] = {_ints(np.concatenate(lens))};")
        out.append(f"static const long ROW_OFF[{len(offs)}] = {_ints(offs)};")
        rl("FACT", np.concatenate(data), "freal", f_type)
    return out


# gpg/export/c/clones.c: the hot loops also in an AVX2/FMA version that glibc's loader picks
# on CPUs that have it (GCC's function multiversioning): the default x86-64 target has 2-wide
# doubles only (the mean's time with and without them: docs/measurements.md).
# With them (GPG_CLONES), the variance's row products and the global mean (its kernel values
# and its coefficients' sums) also have AVX-512 versions, picked at run time
# (latent_variance, global_mean's clones, coef_sums). Off elsewhere (ARM, clang, musl, MSVC)
# and with -DGPG_NO_CLONES; -DGPG_NO_AVX512 leaves out the AVX-512 versions alone (for CPUs
# that slow their clock for 512-bit work). The values do not depend on the version beyond
# FMA rounding and the order of the variance's partial sums (the mean's AVX-512 and AVX2
# versions give the same bits).


def _source(name: str, dtype: str, s: Layout, record: dict[str, Any]) -> str:
    flags = {
        "HAS_BINS": s.bins is not None,
        "HAS_VAR": s.has_variance,
        "HAS_GLOBAL_MEAN": s.global_mean is not None,
        "HAS_ALLOCATION": s.allocation is not None,
        "HAS_CORR": s.correction is not None,
        "HAS_ONLINE": _online(s) is not None,
        "HAS_TRACKER": s.correction is not None and s.correction.tracked is not None,
        "IS_BANK": s.correction is not None and s.correction.bank is not None,
    }
    defs = [f"#define {k} {int(v)}" for k, v in flags.items()]
    defs.append(f"#define ONLINE_T {name}_online")
    defs += [f"#define BOX_LO {name}_box_lo"]
    defs.append(f"#define BOX_HI {name}_box_hi")
    head = (
        f"/* {name}.c: generated by gpg.export.to_c (gpg {record['gpg_version']}, model "
        f"{record['model']}, arrays sha256 {record['arrays_sha256']}). See {name}.h. */\n"
        f'#include <math.h>\n#include <string.h>\n#include "{name}.h"\n\n' + fragment("clones.c")
    )
    public = f"""
int {name}_mean(const double rpm[4], const double euler[3], const double v_air[3],
                double force[3], double torque[3], double *levels) {{
  return evaluate(rpm, euler, v_air, force, torque, levels, 0 ONLINE_PASS(0));
}}
"""
    if s.has_variance:
        public += f"""
int {name}_predict(const double rpm[4], const double euler[3], const double v_air[3],
                   double force[3], double torque[3], double *levels, double *variance) {{
  return evaluate(rpm, euler, v_air, force, torque, levels, variance ONLINE_PASS(0));
}}
"""
    if _online(s) is not None:
        public += _online_public(name, s)
    consts = "\n".join(defs + _constants(name, dtype, s))
    m = s.n_outputs
    sums = ""
    if s.global_mean is not None:
        sums = _coef_sums(m, m * len(s.grad_dims), 4 if dtype == "float" else 8)
    corr = ""
    if s.correction is not None:
        corr = "\n".join(_correction_constants(s, dtype)) + "\n" + fragment("correction.c")
    if _online(s) is not None:
        corr += fragment("tracker.c" if s.correction.tracked is not None else "online.c")
    if s.correction is not None and s.correction.bank is not None:
        corr += fragment("bank.c")
    # the correction's code reads the body's helpers (the vector clones' switch among them)
    body = fragment("body.c").replace("/*@CORRECTION@*/", corr)
    return head + consts + "\n" + fragment("frames.c") + sums + body + public


def _online(s: Layout):
    """The online state's term: an adapted model's ``η``, a tracked model's filter or a
    bank of online terms."""
    if s.correction is None:
        return None
    c = s.correction
    return next((o for o in (c.online, c.tracked, c.bank) if o is not None), None)


def _online_t(s: Layout) -> float:
    """The online state's time when exported."""
    o = _online(s)
    return o.members[0].t if hasattr(o, "members") else o.t


# Long by design: the three calls as one C template, read as C.
def _online_public(name: str, s: Layout) -> str:
    """The online term's three calls (``<name>.h`` documents them)."""
    var = "variance" if s.has_variance else "0"
    return f"""
void {name}_online_init({name}_online *st) {{
  int j, p, q;
#if HAS_TRACKER
  int k;
  for (k = 0; k < TRACK_K; k++) {{
    st->log_weight[k] = TRACK_LW0[k];
    for (j = 0; j < 6; j++)
      for (p = 0; p < TRACK_P; p++) {{
        st->mean[k][j][p] = (real)TRACK_MEAN0[((long)k * 6 + j) * TRACK_P + p];
        for (q = 0; q < TRACK_P; q++)
          st->cov[k][j][p][q] = (real)TRACK_COV0[(((long)k * 6 + j) * TRACK_P + p) * TRACK_P + q];
      }}
  }}
#if TRACK_WIND
  for (p = 0; p < 3; p++) {{
    st->wind_mean[p] = WIND_MEAN0[p];
    for (q = 0; q < 3; q++) st->wind_cov[p][q] = WIND_COV0[p * 3 + q];
  }}
#endif
#elif IS_BANK
  int k;
  for (k = 0; k < ONLINE_K; k++) {{
    st->lag_t[k] = BANK_LAGGED_T0[k];
    for (j = 0; j < 6; j++) {{
      st->log_weight[k][j] = BANK_LOG_WEIGHT0[k * 6 + j];
      for (p = 0; p < N_IND; p++) {{
        long at = ((long)k * 6 + j) * N_IND + p;
        st->mean[k][j][p] = (real)ONLINE_MEAN0[at];
        st->lag_mean[k][j][p] = (real)BANK_LAGGED_MEAN0[at];
        for (q = 0; q < N_IND; q++) {{
          st->cov[k][j][p][q] = (real)ONLINE_COV0[at * N_IND + q];
          st->lag_cov[k][j][p][q] = (real)BANK_LAGGED_COV0[at * N_IND + q];
        }}
      }}
    }}
  }}
  for (k = 0; k < BANK_L; k++) {{
    for (p = 0; p < D_IN; p++) st->ring_x[k][p] = BANK_RING_X0[k * D_IN + p];
    for (j = 0; j < 6; j++) {{
      st->ring_y[k][j] = BANK_RING_Y0[k * 6 + j];
      st->ring_r[k][j] = BANK_RING_R0[k * 6 + j];
    }}
    st->ring_t[k] = BANK_RING_T0[k];
    st->ring_live[k] = RING_LIVE0[k];
  }}
  st->count = BANK_COUNT0;
#else
  for (j = 0; j < 6; j++)
    for (p = 0; p < N_IND; p++) {{
      st->mean[j][p] = (real)ONLINE_MEAN0[j * N_IND + p];
      for (q = 0; q < N_IND; q++)
        st->cov[j][p][q] = (real)ONLINE_COV0[((long)j * N_IND + p) * N_IND + q];
    }}
#endif
  st->t = {_online_t(s)!r};
}}

/* the label's residual y against the offline mean and its noise variance r (normalised, GP
 * frame) at the air velocity v_air; x, xn the GP's input, prior the prior's normalised mean
 * (the tracked columns read it); dl (when not null) each delta's latent variance there,
 * scaled (zeros without them); band (when not null) the offline model's band of the loads
 * there (normalised, the prior's latent variance in it: a bank's members are scored under
 * it) */
static void label_rows(const double rpm[4], const double euler[3], const double v_air[3],
                       const double force[3], const double torque[3], const double force_var[3],
                       const double torque_var[3], double x[D_IN], double xn[D_IN],
                       double prior[N_OUT], double y[6], double r[6], double *dl, double *band) {{
  double rwh[3][3], yn[N_OUT], f[3], tq[3], eg[3], latent = 0.0;
  int i, k;
  gp_input(rpm, euler, v_air, x, rwh, eg);
  for (i = 0; i < D_IN; i++) xn[i] = (x[i] - X_LO[i]) / HALF[i] - 1.0;
#if HAS_GLOBAL_MEAN
  global_mean(xn, yn);
#else
  {{
    real kr[MAX_ROWS];
    binned_mean(xn, lookup(xn), kr, yn);
  }}
#endif
  for (i = 0; i < N_OUT; i++) prior[i] = yn[i];
  if (dl) for (i = 0; i < 6; i++) dl[i] = 0.0;
#if HAS_VAR
  {{
    double pvn[N_OUT]; /* the offline band, beside delta's variance */
    if (band) {{ /* its prior's part too */
      real kb[MAX_ROWS];
      int bb = lookup(xn), nb = kernel_row(xn, bb, kb);
      latent = latent_variance(kb, bb, nb);
    }}
    corrected(x, xn, yn, latent, dl || band ? pvn : 0, dl);
    if (band) for (i = 0; i < 6; i++) band[i] = pvn[i];
  }}
#else
  corrected(x, xn, yn, 0.0, 0, 0);
  (void)band; (void)latent;
#endif
  for (i = 0; i < 3; i++) {{ f[i] = force[i]; tq[i] = torque[i]; }}
#if HAS_ALLOCATION
  {{ /* the label's residual against M, world frame */
    double u[4] = {{0.0, 0.0, 0.0, 0.0}}, rwb[3][3];
    for (i = 0; i < 4; i++)
      for (k = 0; k < 4; k++) u[i] += ALLOCATION[i * 4 + k] * rpm[k] * rpm[k];
    rot_wb(euler[0], euler[1], euler[2], rwb);
    for (i = 0; i < 3; i++) {{
      f[i] -= rwb[i][2] * -u[0];
      for (k = 0; k < 3; k++) tq[i] -= rwb[i][k] * u[1 + k];
    }}
  }}
#endif
  for (i = 0; i < 3; i++) {{
    y[i] = 0.0; y[3 + i] = 0.0; r[i] = 0.0; r[3 + i] = 0.0;
    for (k = 0; k < 3; k++) {{
      y[i] += rwh[k][i] * f[k]; y[3 + i] += rwh[k][i] * tq[k];
      r[i] += rwh[k][i] * rwh[k][i] * force_var[k];
      r[3 + i] += rwh[k][i] * rwh[k][i] * torque_var[k];
    }}
  }}
  for (i = 0; i < 6; i++) {{
    y[i] = (y[i] - Y_MEAN[i]) / Y_STD[i] - yn[i];
    r[i] /= Y_STD[i] * Y_STD[i];
  }}
}}

#if HAS_TRACKER && TRACK_WIND
/* fourth-order central differences at step WIND_FD_STEP (m/s) about v_air + g */
static const double FD_AT[4] = {{2.0, 1.0, -1.0, -2.0}}, FD_W[4] = {{-1.0, 8.0, -8.0, 1.0}};

/* J[6][3]: the label's residual's derivative in the wind at g (the library's jax.jacfwd) */
static void wind_jacobian(const double rpm[4], const double euler[3], const double v_air[3],
                          const double g[3], const double force[3], const double torque[3],
                          const double force_var[3], const double torque_var[3],
                          double J[6][3]) {{
  double v[3], x[D_IN], xn[D_IN], prior[N_OUT], y[6], r[6];
  int a, c, i, j;
  for (a = 0; a < 3; a++) {{
    for (j = 0; j < 6; j++) J[j][a] = 0.0;
    for (c = 0; c < 4; c++) {{
      for (i = 0; i < 3; i++) v[i] = v_air[i] + (g[i] + (i == a ? FD_AT[c] * WIND_FD_STEP : 0.0));
      label_rows(rpm, euler, v, force, torque, force_var, torque_var, x, xn, prior, y, r, 0, 0);
      for (j = 0; j < 6; j++) J[j][a] += FD_W[c] * y[j];
    }}
    for (j = 0; j < 6; j++) J[j][a] /= 12.0 * WIND_FD_STEP;
  }}
}}
#endif

int {name}_online_update({name}_online *st, double t, const double rpm[4],
                         const double euler[3], const double v_air[3], const double force[3],
                         const double torque[3], const double force_var[3],
                         const double torque_var[3]) {{
  double x[D_IN], xn[D_IN], prior[N_OUT], y[6], r[6];
  int i;
  if (!isfinite(t)) return 0;
  for (i = 0; i < 4; i++) if (!isfinite(rpm[i])) return 0;
  for (i = 0; i < 3; i++)
    if (!isfinite(euler[i]) || !isfinite(v_air[i]) || !isfinite(force[i]) ||
        !isfinite(torque[i]) || !(force_var[i] >= 0.0) || !(torque_var[i] >= 0.0) ||
        !isfinite(force_var[i]) || !isfinite(torque_var[i]))
      return 0;
#if HAS_TRACKER
  double h[6][TRACK_P];
  tracker_relax(st, t);
#if TRACK_WIND
  {{ /* the wind first, its innovation's band the coefficients' own; then the coefficients at
      * the air velocity it implies (gpg.flight.correction.advance) */
    double v[3], g[3], e[6], n[6], dl[6], mix[6], var[6], J[6][3];
    for (i = 0; i < 3; i++) {{ g[i] = st->wind_mean[i]; v[i] = v_air[i] + g[i]; }}
    label_rows(rpm, euler, v, force, torque, force_var, torque_var, x, xn, prior, e, r, dl, 0);
    track_columns(x, prior, h);
    tracker_mix(st, h, mix, var);
    wind_jacobian(rpm, euler, v_air, g, force, torque, force_var, torque_var, J);
    for (i = 0; i < 6; i++) n[i] = r[i] + dl[i] + TRACK_NOISE[i] + var[i];
    wind_kalman(st, e, J, n, mix);
    for (i = 0; i < 3; i++) v[i] = v_air[i] + st->wind_mean[i];
    label_rows(rpm, euler, v, force, torque, force_var, torque_var, x, xn, prior, y, r, 0, 0);
  }}
#else
  label_rows(rpm, euler, v_air, force, torque, force_var, torque_var, x, xn, prior, y, r, 0, 0);
#endif
  track_columns(x, prior, h);
  tracker_measure(st, h, y, r);
#elif IS_BANK
  {{ /* the members scored under the offline band at the label (gpg.flight.Bank) */
    double band[6];
    label_rows(rpm, euler, v_air, force, torque, force_var, torque_var, x, xn, prior, y, r, 0,
               band);
    bank_update(st, t, xn, y, r, band);
  }}
  (void)prior;
#else
  label_rows(rpm, euler, v_air, force, torque, force_var, torque_var, x, xn, prior, y, r, 0, 0);
  online_kalman(0, st->mean, st->cov, &st->t, t, xn, y, r);
  (void)prior;
#endif
  return 1;
}}

int {name}_online_predict(const {name}_online *st, const double rpm[4], const double euler[3],
                          const double v_air[3], double force[3], double torque[3],
                          double *levels, double *variance) {{
#if HAS_TRACKER && TRACK_WIND
  /* at v_air + g, the loads' variance widened by diag(J P_g J^T), J the world loads'
   * derivative in the air velocity there (gpg.surrogate's _predict_in_wind) */
  double v[3], f[3], tq[3], lv[N_LEVELS > 0 ? N_LEVELS : 1], J[6][3], extra;
  int a, b, c, i, ok;
  for (i = 0; i < 3; i++) v[i] = v_air[i] + st->wind_mean[i];
  ok = evaluate(rpm, euler, v, force, torque, levels, variance, st);
  if (!variance) return ok;
  for (a = 0; a < 3; a++) {{
    for (i = 0; i < 6; i++) J[i][a] = 0.0;
    for (c = 0; c < 4; c++) {{
      for (i = 0; i < 3; i++)
        v[i] = v_air[i] + (st->wind_mean[i] + (i == a ? FD_AT[c] * WIND_FD_STEP : 0.0));
      evaluate(rpm, euler, v, f, tq, lv, 0, st);
      for (i = 0; i < 3; i++) {{ J[i][a] += FD_W[c] * f[i]; J[3 + i][a] += FD_W[c] * tq[i]; }}
    }}
    for (i = 0; i < 6; i++) J[i][a] /= 12.0 * WIND_FD_STEP;
  }}
  for (i = 0; i < 6; i++) {{
    extra = 0.0;
    for (a = 0; a < 3; a++)
      for (b = 0; b < 3; b++) extra += J[i][a] * st->wind_cov[a][b] * J[i][b];
    variance[i] += extra;
    if (!isfinite(extra)) ok = 0;
  }}
  return ok;
#else
  (void)variance;
  return evaluate(rpm, euler, v_air, force, torque, levels, {var} ONLINE_PASS(st));
#endif
}}
"""


# Long by design: one declaration per array the correction's C reads, in the order it reads them.
def _correction_constants(s: Layout, dtype: str = "double") -> list[str]:
    """The arrays of a model corrected by flights (:class:`gpg.export.layout.Correction`), in
    double whatever the dtype (``gpg/export/c/correction.c`` reads them, and sums in double),
    but for the variance's triangles, packed row by row: stored in ``dtype`` (``treal``), the
    largest array, read whole at every query."""
    c = s.correction
    out: list[str] = []

    def dbl(key, a):
        a = np.asarray(a, float)
        out.append(f"static const double {key}[{max(a.size, 1)}] = {_literal(a, np.float64)};")

    n = [d.points.shape[0] for d in c.deltas]
    off = np.cumsum([0] + n[:-1])
    n_terms = 0 if c.beta is None else c.beta.shape[1]
    n_int = 0 if c.G is None else c.G[0].shape[1]
    out += [
        f"#define HAS_KAPPA {int(c.kappa is not None)}",
        f"#define N_TERMS {n_terms}",
        f"#define N_INTEGRATED {n_int}",
        f"#define CORR_WITH_PRIOR {int(c.with_prior)}",
        f"#define CORR_WITH_SIMPLE {int(c.with_simple)}",
        f"#define N_DELTA {len(n)}",
        f"#define CORR_RPM_REF {c.rpm_ref!r}",
        f"#define CORR_AIR_DENSITY {c.air_density!r}",
    ]
    terms = (c.online,) if c.online is not None else ()
    terms = c.bank.members if c.bank is not None else terms
    if terms:  # one term, or a bank's members one after the other
        o = terms[0]
        out += [f"#define N_IND {o.Z.shape[0]}", f"#define ONLINE_SHARED {int(o.shared)}",
                f"#define ONLINE_K {len(terms)}"]  # fmt: skip
        dbl("ONLINE_TAU", np.stack([t.tau for t in terms]))  # (K, 6, N_IND): per weight
        dbl("ONLINE_Z", np.stack([t.Z for t in terms]))
        dbl("ONLINE_WHITEN_T", np.stack([np.swapaxes(t.whiten, 1, 2) for t in terms]))
        for key, attr in (("VAR", "variance"), ("LS", "lengthscale"), ("NU", "noise"),
                          ("MEAN0", "mean"), ("COV0", "cov")):  # fmt: skip
            dbl(f"ONLINE_{key}", np.stack([getattr(t, attr) for t in terms]))
    if c.bank is not None:
        bk = c.bank
        live = _ints(bk.ring_live.astype(int))
        out += [f"#define BANK_L {bk.ahead}", f"#define BANK_WTAU {bk.weight_tau!r}",
                f"#define BANK_COUNT0 {bk.count}",
                f"static const int RING_LIVE0[{bk.ahead}] = {live};"]  # fmt: skip
        for key in ("lagged_mean", "lagged_cov", "lagged_t", "ring_x", "ring_y", "ring_r",
                    "ring_t", "log_weight"):  # fmt: skip
            dbl(f"BANK_{key.upper()}0", getattr(bk, key))
    if c.tracked is not None:
        r = c.tracked
        k, p = r.mean.shape[0], r.mean.shape[2]
        out += [f"#define TRACK_K {k}", f"#define TRACK_P {p}",
                f"#define TRACK_SIMPLE {int(r.with_simple)}", f"#define TRACK_TAU {r.tau!r}",
                f"#define TRACK_SHARE {r.share!r}"]  # fmt: skip
        dbl("TRACK_BIAS_TAU", r.bias_tau)
        dbl("TRACK_NOISE", r.noise)
        dbl("TRACK_OFFSET", r.offset)
        dbl("TRACK_BIAS", r.bias)
        dbl("TRACK_STAT", r.stationary)
        dbl("TRACK_MEAN0", r.mean)
        dbl("TRACK_COV0", r.cov)
        dbl("TRACK_LW0", r.log_weight)
        out.append(f"#define TRACK_WIND {int(r.wind_mean is not None)}")
        if r.wind_mean is not None:  # the wind state (gpg.flight.gusts)
            out += [f"#define WIND_TAU {r.wind_tau!r}", f"#define WIND_FD_STEP {WIND_FD_STEP!r}"]
            dbl("WIND_SD", r.wind_sd)
            dbl("WIND_MEAN0", r.wind_mean)
            dbl("WIND_COV0", r.wind_cov)
    dbl("CORR_SCALE", c.scale)
    if c.kappa is not None:  # a term of M implies M: the prior's allocation
        dbl("CORR_KAPPA", c.kappa)
        dbl("CORR_ALLOCATION", s.allocation)
    if c.beta is not None:
        dbl("CORR_BETA", c.beta)
        dbl("CORR_HUBS", c.hubs)
    if not n:
        return out
    out += [
        f"#define DELTA_MAX {max(n)}",
        f"static const int DELTA_N[6] = {_ints(n)};",
        f"static const long DELTA_PT_OFF[6] = {_ints(off)};",
    ]
    # each discrepancy's points over its lengthscales, input by input (delta_row's loops over
    # them vectorise)
    dbl("DELTA_ZL_T", np.concatenate([(d.points / d.lengthscale).T.ravel() for d in c.deltas]))
    dbl("DELTA_W", np.concatenate([d.weights for d in c.deltas]))
    dbl("DELTA_LS", np.concatenate([d.lengthscale for d in c.deltas]))
    dbl("DELTA_SIGMA", [d.sigma for d in c.deltas])
    dbl("DELTA_NU", [d.noise for d in c.deltas])
    dbl("DELTA_OS", [d.output_scale for d in c.deltas])
    if s.has_variance:
        tri = [(m * (m + 1)) // 2 for m in n]
        out.append(f"static const long DELTA_TRI_OFF[6] = {_ints(np.cumsum([0] + tri[:-1]))};")
        # the latent variance's one triangle per discrepancy (Discrepancy.variance_factor)
        packed = np.concatenate(
            [T[np.tril_indices(T.shape[0])] for T in (d.variance_factor() for d in c.deltas)]
        )
        t_type, c_type = (np.float32, "float") if dtype == "float" else (np.float64, "double")
        out += [f"typedef {c_type} treal;", f"#define TREAL_IS_DOUBLE {int(c_type == 'double')}"]
        out.append(f"static const treal DELTA_TRI[{packed.size}] = {_literal(packed, t_type)};")
        if c.G is not None:
            dbl("CORR_G", np.concatenate([g.ravel() for g in c.G]))
            dbl("CORR_C", c.cov_chol)
    return out


def fragment(name: str) -> str:
    """A fixed part of the generated C, kept as a C file of its own in ``gpg/export/c/`` (the
    frames, the prediction's body, the vector clones' switch), read from the installed package
    (:mod:`importlib.resources`): C to read and edit as C, not inside Python strings."""
    return resources.files("gpg.export").joinpath("c", name).read_text(encoding="utf-8")


def _split_coef(
    gm: dict[str, np.ndarray], grad_dims, m: int, np_type
) -> tuple[np.ndarray, np.ndarray]:
    """The folded mean's value block ``c⁰`` (N, M), kept in double, and its gradient blocks
    ``cᵍ`` (N, G·M) in the dtype asked for. The value block is where the folded sum cancels
    (``c⁰ = α⁰ − Σ_g (x_p,g/l_g²) αᵍ``), so it stays in double; and it is refolded from the
    stored ``cᵍ`` so that their rounding enters the mean as ``Σ_p k_p (x_g − x_p,g)/l_g² δᵍ_p``,
    small where ``k_p`` is not, instead of ``Σ_p k_p x_g/l_g² δᵍ_p``. This lowers the float
    export's mean error at the cost of the value block's N·M numbers in double instead of
    float (the figures at data=default: docs/measurements.md). In double it changes nothing."""
    coef, xs, inv_ls = gm["coef"], gm["xs"], gm["inv_ls"]
    value, grad = coef[:, :m].copy(), coef[:, m:].astype(np_type)
    delta = coef[:, m:] - grad.astype(np.float64)
    for i, g in enumerate(grad_dims):
        value += (xs[:, g] * inv_ls[g])[:, None] * delta[:, i * m : (i + 1) * m]
    return value, grad


def _coef_sums(
    m: int, n_grad: int, real_bytes: int = 4, most: int = 11, block_bytes: int = 24576
) -> str:
    """``acc[j] = sum_p k[p] C[p, j]`` for the global mean (``C`` = ``COEF0`` for its ``m``
    value columns in double, then ``COEFG`` for its ``n_grad`` gradient ones in ``real`` of
    ``real_bytes``), each row padded to whole vectors of four (:func:`_padded`), in versions
    picked at run time.

    * AVX-512: :func:`_coef_sums_avx512`, one pass.
    * AVX2 with FMA (GCC on x86-64 Linux, as the variance's clones): one pass over the points
      per group of at most ``most`` sums of four doubles held in registers (the groups of
      about equal size, the two blocks mixed: 16 registers hold eleven sums beside a load
      and the kernel value); a point's coefficients are a few vector loads (float ones
      widened to double as they are loaded) and fused multiply-adds against its broadcast
      kernel value. The passes go block by block of points whose rows fill at most
      ``block_bytes`` (within an L1 data cache: the default leaves room), the sums kept in
      memory between blocks: every pass after the first reads its block from L1, not again
      from L2. Each sum still adds its points in their order (``-DGPG_MEAN_BLOCK=n`` sets
      another block: the same bits).
    * Anywhere else (and with -DGPG_NO_VECTOR): :func:`_coef_sums_scalar`'s named sums, which
      compilers vectorise for the vectors the target has (32-byte vector types split in two
      on SSE2 were slower).

    The sums are double in both dtypes: the folded mean cancels (its terms' absolute sum is
    hundreds of times the mean at data=default), and float sums and products, tried, put the
    float export's mean beyond its 1e-5 from ``predict``."""
    w0, wg = _padded(m, 4), _padded(n_grad, 4)
    block = max(8, block_bytes // (8 * w0 + real_bytes * wg))
    v0 = [("COEF0", w0, q) for q in range(w0 // 4)]
    vg = [("COEFG", wg, q) for q in range(wg // 4)]
    both = v0 + vg
    n_pass = -(-len(both) // most)
    per = -(-len(both) // n_pass)  # passes of about equal size, the two arrays mixed
    passes = [both[i : i + per] for i in range(0, len(both), per)]
    L = [
        _coef_sums_scalar(m, n_grad, w0, wg).rstrip("\n"),
        "#if defined(GPG_CLONES) && !defined(GPG_NO_VECTOR)",
        "/* the same sums for AVX2 with FMA: sums of four doubles held in registers, one pass",
        " * over a block of points per group of them, block by block (gpg/export/c_source.py:",
        " * _coef_sums) */",
        "#pragma GCC push_options",
        '#pragma GCC target("arch=x86-64-v3")',
        "typedef double cs_vd __attribute__((vector_size(32)));",
        f"#ifndef GPG_MEAN_BLOCK /* points a block: their rows fill <= {block_bytes} bytes */",
        f"#define GPG_MEAN_BLOCK {block}",
        "#endif",
        "/* four of real widened to double: one vcvtps2pd from memory in float",
        " * (__builtin_convertvector went through the stack in halves, slower) */",
        "#define CS_LOAD(V, P) \\",
        "  do { const real *q_ = (P); (V) = (cs_vd){q_[0], q_[1], q_[2], q_[3]}; } while (0)",
        "FUSED static void coef_sums_avx2(const double *k, double *acc) {",
        f"  double s[{w0 + wg}];",
        "  cs_vd t;",
        "  int p, j, p0;",
        f"  for (j = 0; j < {w0 + wg}; j++) s[j] = 0.0;",
        "  for (p0 = 0; p0 < N_MEAN; p0 += GPG_MEAN_BLOCK) {",
        "    const int p1 = p0 + GPG_MEAN_BLOCK < N_MEAN ? p0 + GPG_MEAN_BLOCK : N_MEAN;",
    ]
    L += [line for vs in passes for line in _coef_pass(vs, w0, wg)]
    L += [
        "  }",
        f"  for (j = 0; j < {m}; j++) acc[j] = s[j];",
        f"  for (j = 0; j < {n_grad}; j++) acc[{m} + j] = s[{w0} + j];",
        "}",
        "#pragma GCC pop_options",
        *_coef_sums_avx512(m, n_grad, w0, wg),
        "static void coef_sums(const double *k, double *acc) {",
        "#if !defined(GPG_NO_AVX512)",
        '  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl")) {',
        "    coef_sums_avx512(k, acc);",
        "    return;",
        "  }",
        "#endif",
        '  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))',
        "    coef_sums_avx2(k, acc);",
        "  else",
        "    coef_sums_any(k, acc);",
        "}",
        "#else",
        "#define coef_sums coef_sums_any",
        "#endif",
    ]
    return "\n".join(L) + "\n"


def _coef_pass(vs: list[tuple[str, int, int]], w0: int, wg: int) -> list[str]:
    """One pass of :func:`_coef_sums`'s AVX2 version over a block of points ``p0 .. p1``: the
    sums ``vs`` (each an array, its width and its vector's index) loaded from ``s`` into
    registers, then stored back."""
    names = [f"a{i}" for i in range(len(vs))]
    offsets = [(0 if array == "COEF0" else w0) + 4 * q for array, _, q in vs]
    L = ["  {", "    cs_vd " + ", ".join(names) + ";"]
    L += [f"    memcpy(&{n}, s + {o}, sizeof t);" for n, o in zip(names, offsets, strict=True)]
    L += ["    for (p = p0; p < p1; p++) {", "      const double kp = k[p];"]
    if any(a == "COEF0" for a, _, _ in vs):
        L.append(f"      const double *c0 = COEF0 + (long)p * {w0};")
    if any(a == "COEFG" for a, _, _ in vs):
        L.append(f"      const real *cg = COEFG + (long)p * {wg};")
    for n, (array, _, q) in zip(names, vs, strict=True):
        load = (f"memcpy(&t, c0 + {4 * q}, sizeof t);" if array == "COEF0"
                else f"CS_LOAD(t, cg + {4 * q});")  # fmt: skip
        L.append(f"      {load} {n} += kp * t;")
    L.append("    }")
    L += [f"    memcpy(s + {o}, &{n}, sizeof t);" for n, o in zip(names, offsets, strict=True)]
    L.append("  }")
    return L


def _coef_sums_avx512(m: int, n_grad: int, w0: int, wg: int) -> list[str]:
    """``coef_sums_avx512``: :func:`_coef_sums`'s sums for CPUs with AVX-512, in one pass
    over the points: each row as vectors of eight doubles (a four-wide one for a row's last
    four), every sum in one of the 32 registers; the products and sums in the AVX2 version's
    order per element, so the two agree bit for bit."""
    vecs = [(a, w, 8 * q, 8) for a, w in (("COEF0", w0), ("COEFG", wg)) for q in range(w // 8)]
    vecs += [(a, w, w - 4, 4) for a, w in (("COEF0", w0), ("COEFG", wg)) if w % 8]
    L = [
        "#if !defined(GPG_NO_AVX512)",
        "#pragma GCC push_options",
        '#pragma GCC target("arch=x86-64-v4")',
        "typedef double cs_v8 __attribute__((vector_size(64)));",
        "#define CS_LOAD8(V, P) \\",
        "  do { const real *q_ = (P); \\",
        "       (V) = (cs_v8){q_[0], q_[1], q_[2], q_[3], q_[4], q_[5], q_[6], q_[7]}; \\",
        "  } while (0)",
        "FUSED static void coef_sums_avx512(const double *k, double *acc) {",
        f"  double s[{w0 + wg}];",
        "  cs_v8 t8;",
        "  cs_vd t4;",
        "  int p, j;",
        "  "
        + " ".join(
            f"cs_v{n if n == 8 else 'd'} b{i} = {{0}};" for i, (_, _, _, n) in enumerate(vecs)
        ),
        "  for (p = 0; p < N_MEAN; p++) {",
        "    const double kp = k[p];",
        f"    const double *c0 = COEF0 + (long)p * {w0};",
        f"    const real *cg = COEFG + (long)p * {wg};",
    ]
    for i, (array, _, o, n) in enumerate(vecs):
        t = "t8" if n == 8 else "t4"
        if array == "COEF0":
            load = f"memcpy(&{t}, c0 + {o}, sizeof {t});"
        else:
            load = f"CS_LOAD{'8' if n == 8 else ''}({t}, cg + {o});"
        L.append(f"    {load} b{i} += kp * {t};")
    L.append("  }")
    for i, (array, _, o, _n) in enumerate(vecs):
        base = 0 if array == "COEF0" else w0
        L.append(f"  memcpy(s + {base + o}, &b{i}, sizeof b{i});")
    L += [
        f"  for (j = 0; j < {m}; j++) acc[j] = s[j];",
        f"  for (j = 0; j < {n_grad}; j++) acc[{m} + j] = s[{w0} + j];",
        "}",
        "#pragma GCC pop_options",
        "#endif",
    ]
    return L


def _coef_sums_scalar(m: int, n_grad: int, w0: int, wg: int, block: int = 24) -> str:
    """``coef_sums_any``: :func:`_coef_sums`'s sums in scalar C, ``block`` at a time in named
    locals held in registers across the loop over the points (each sum keeps its order), the
    rows ``w0`` and ``wg`` wide."""
    parts = [
        "/* acc[j] = sum_p k[p] C[p, j], the sums in blocks held in registers */",
        "HOT static void coef_sums_any(const double *k, double *acc) {",
        "  int p;",
    ]
    groups = [("COEF0", m, w0, 0, j0) for j0 in range(0, m, block)]
    groups += [("COEFG", n_grad, wg, m, j0) for j0 in range(0, n_grad, block)]
    for array, width, stride, acc0, j0 in groups:
        b = min(block, width - j0)
        names = [f"a{q}" for q in range(b)]
        parts.append("  {")
        parts.append(f"    double {', '.join(n + ' = 0.0' for n in names)};")
        parts.append("    for (p = 0; p < N_MEAN; p++) {")
        parts.append(f"      const {'double' if array == 'COEF0' else 'real'} *c = "
                     f"{array} + (long)p * {stride} + {j0};")  # fmt: skip
        parts.append("      const double kp = k[p];")
        for i in range(0, b, 4):
            parts.append(
                "      "
                + " ".join(f"a{q} += kp * (double)c[{q}];" for q in range(i, min(b, i + 4)))
            )
        parts.append("    }")
        for i in range(0, b, 4):
            parts.append(
                "    " + " ".join(f"acc[{acc0 + j0 + q}] = a{q};" for q in range(i, min(b, i + 4)))
            )
        parts.append("  }")
    parts.append("}")
    return "\n".join(parts) + "\n"


def _pad_columns(a: np.ndarray, width: int) -> np.ndarray:
    """``a`` (N, C) with zero columns up to ``width``."""
    return np.pad(a, ((0, 0), (0, width - a.shape[1])))


def _padded(n: int, lanes: int) -> int:
    """``n`` rounded up to whole vectors of ``lanes``."""
    return -(-n // lanes) * lanes
