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
from pathlib import Path
from typing import Any

import numpy as np

from gpg._io import atomic_write
from gpg.export.layout import MAX_BYTES, Layout, row_spans, spec
from gpg.names import inputs
from gpg.quadrotor.frames import TINY_SPEED
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

DTYPES = {"double": (np.float64, "double"), "float": (np.float32, "float")}


def to_c(
    sur: Surrogate,
    directory: str | Path,
    *,
    name: str = "gpg_model",
    dtype: str = "double",
    variance: bool = True,
    max_bytes: int = MAX_BYTES,
) -> dict[str, Any]:
    """Write ``<directory>/<name>.c`` and ``.h`` for ``sur``; returns what was written (paths,
    bytes of the GP's constants, the record of gpg version, model, arrays' SHA-256, units).

    The header documents the calls, which return ``in_domain`` (1 or 0):

    * ``int <name>_mean(const double rpm[4], const double euler[3], const double v_air[3],
      double force[3], double torque[3], double *levels)``;
    * with ``variance`` (and a model that has one): ``int <name>_predict(..., double *levels,
      double *variance)``, ``variance[6 + K]`` the predictive variance of force, torque (world
      frame) and levels as :meth:`Surrogate.predict` gives it.

    Units rpm, rad (yaw, pitch, roll: ``R_WB = Rz Ry Rx``), m/s, N, N·m, dB; world frame x
    forward, y right, z down; the same call for a surrogate of either frame. The header
    declares ``<name>_box_lo[D]`` and ``_box_hi[D]``, the GP's input box (``D`` =
    ``<NAME>_N_INPUTS``: 8 airflow-frame inputs, or 7 body-frame ones). A non-finite input
    gives 0 and zeros, never NaN.
    ``ValueError`` (nothing written) for a model :func:`gpg.export.layout.spec` refuses, a bad
    ``name`` or ``dtype``, or constants over ``max_bytes``."""
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {list(DTYPES)}, got {dtype!r}")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    s = spec(sur, variance=variance, max_bytes=max_bytes)
    itemsize = np.dtype(DTYPES[dtype][0]).itemsize
    n_const = s.constant_bytes(itemsize, variance=s.has_variance)
    if s.global_mean is not None:  # the folded mean's value block in double (_split_coef)
        n_const += s.global_mean["xs"].shape[0] * s.n_outputs * (8 - itemsize)
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
    header = _header(name, s, record)
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


def _header(name: str, s: Layout, record: dict[str, Any]) -> str:
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
{predict}
#endif
"""


_FRAMES = r"""
/* R = Rz(yaw) Ry(pitch) Rx(roll) */
static void rot_wb(double yaw, double pitch, double roll, double R[3][3]) {
  double cy = cos(yaw), sy = sin(yaw), cp = cos(pitch), sp = sin(pitch);
  double cr = cos(roll), sr = sin(roll);
  R[0][0] = cy * cp; R[0][1] = cy * sp * sr - sy * cr; R[0][2] = cy * sp * cr + sy * sr;
  R[1][0] = sy * cp; R[1][1] = sy * sp * sr + cy * cr; R[1][2] = sy * sp * cr - cy * sr;
  R[2][0] = -sp;     R[2][1] = cp * sr;                R[2][2] = cp * cr;
}

#if !BODY_FRAME
static double safe_atan2(double y, double x, double tiny) {
  if (fabs(x) <= tiny && fabs(y) <= tiny) return 0.0;
  return atan2(y, x);
}

static double norm3(const double v[3]) {
  double s = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  return s <= 0.0 ? 0.0 : sqrt(s);
}

/* wind axes Rz(heading) Ry(climb) of the direction d */
static void wind_axes(const double d[3], double R[3][3]) {
  double dxy[3] = {d[0], d[1], 0.0};
  double heading = safe_atan2(d[1], d[0], TINY_SPEED);
  double climb = safe_atan2(-d[2], norm3(dxy), TINY_SPEED);
  rot_wb(heading, climb, 0.0, R);
}

/* R_WH of the airflow frame, blended toward the body heading (gpg.quadrotor.frames) */
static void airflow_frame(const double v[3], double yaw, double R[3][3]) {
  double h = HOVER_SPEED, d[3], x[3], y[3], z[3], c, dxy2, n, yx;
  int i;
  if (h <= 0.0) { wind_axes(v, R); return; }
  c = 1.0 - (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) / (h * h);
  c = h * (c > 0.0 ? c * c : 0.0);
  d[0] = v[0] + c * cos(yaw); d[1] = v[1] + c * sin(yaw); d[2] = v[2];
  dxy2 = d[0] * d[0] + d[1] * d[1];
  if (dxy2 >= h * h) { wind_axes(d, R); return; }
  n = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] > 0.0 ? norm3(d) : 1.0;
  for (i = 0; i < 3; i++) x[i] = d[i] / n;
  c = 1.0 - dxy2 / (h * h);
  c = h * (c > 0.0 ? c * c : 0.0);
  y[0] = -d[1] - c * sin(yaw); y[1] = d[0] + c * cos(yaw); y[2] = 0.0;
  yx = y[0] * x[0] + y[1] * x[1] + y[2] * x[2];
  for (i = 0; i < 3; i++) y[i] -= yx * x[i];
  n = y[0] * y[0] + y[1] * y[1] + y[2] * y[2] > 0.0 ? norm3(y) : 1.0;
  for (i = 0; i < 3; i++) y[i] /= n;
  z[0] = x[1] * y[2] - x[2] * y[1];
  z[1] = x[2] * y[0] - x[0] * y[2];
  z[2] = x[0] * y[1] - x[1] * y[0];
  for (i = 0; i < 3; i++) { R[i][0] = x[i]; R[i][1] = y[i]; R[i][2] = z[i]; }
}

static void euler_from_r(double R[3][3], double e[3]) {
  double cp = hypot(R[0][0], R[1][0]);
  e[1] = safe_atan2(-R[2][0], cp, 0.0);
  if (cp < 1e-12) { e[0] = safe_atan2(-R[0][1], R[1][1], 0.0); e[2] = 0.0; }
  else { e[0] = safe_atan2(R[1][0], R[0][0], 0.0); e[2] = safe_atan2(R[2][1], R[2][2], 0.0); }
}

/* the attitude in the airflow frame, and R_WH */
static void to_airflow(const double euler[3], const double v[3], double eh[3], double rwh[3][3]) {
  double rwb[3][3], rhb[3][3];
  int i, j, k;
  airflow_frame(v, euler[0], rwh);
  rot_wb(euler[0], euler[1], euler[2], rwb);
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) {
      rhb[i][j] = 0.0;
      for (k = 0; k < 3; k++) rhb[i][j] += rwh[k][i] * rwb[k][j];
    }
  euler_from_r(rhb, eh);
}

/* frames.airflow_frame_rate by central differences (rad per m/s) */
static double frame_rate(const double euler[3], const double v[3]) {
  double se = 0.0, sr = 0.0, step = 1e-6, vp[3], vm[3], ep[3], em[3], rp[3][3], rm[3][3], t;
  int j, a, b;
  if (HOVER_SPEED <= 0.0 && v[0] * v[0] + v[1] * v[1] <= TINY_SPEED * TINY_SPEED) return INFINITY;
  for (j = 0; j < 3; j++) {
    for (a = 0; a < 3; a++) { vp[a] = v[a]; vm[a] = v[a]; }
    vp[j] += step; vm[j] -= step;
    to_airflow(euler, vp, ep, rp);
    to_airflow(euler, vm, em, rm);
    for (a = 0; a < 3; a++) {
      t = ep[a] - em[a];
      t -= 6.283185307179586 * floor((t + 3.141592653589793) / 6.283185307179586);
      se += t * t;
      for (b = 0; b < 3; b++) { t = rp[a][b] - rm[a][b]; sr += t * t; }
    }
  }
  se = sqrt(se) / (2.0 * step);
  sr = sqrt(sr / 2.0) / (2.0 * step);
  return se > sr ? se : sr;
}
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
        # relative, which the mean's cancelling sum amplifies (measured 5e-5 at data=default)
        dbl("XS_T", gm["xs"].T)
        value, grad = _split_coef(gm, s.grad_dims, m, np_type)
        dbl("COEF0", value)
        rl("COEFG", grad)
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


_BODY = r"""
#define N_LEVELS (N_OUT - 6)

#if HAS_BINS
/* the query's bin (gpg.gp.partition.Partition.lookup): a value on a split goes left */
static int lookup(const double xn[D_IN]) {
#if SLAB
  int b = 0, i;
  for (i = 0; i < N_CUTS; i++) b += xn[SPLIT_DIM[0]] > SPLIT_VALUE[i];
  return b;
#else
  int node = 0;
  if (N_BINS == 1) return 0;
  while (node >= 0) node = xn[SPLIT_DIM[node]] <= SPLIT_VALUE[node] ? LEFT[node] : RIGHT[node];
  return -node - 1;
#endif
}

/* k(x, X_p) for n points, then one block of gradient rows k (x_a - X_pa) / l_a^2 per
 * gradient dimension a (gpg.gp.kernels.query_rows) */
HOT static void krows(const double xn[D_IN], const real *X, int n, real *out) {
  int p, i, g, a;
  double r2, t, k;
  for (p = 0; p < n; p++) {
    r2 = 0.0;
    for (i = 0; i < D_IN; i++) {
      t = (xn[i] - (double)X[p * D_IN + i]) / LENGTHSCALE[i];
      r2 += t * t;
    }
    k = SIGMA_NOISE[0] * exp(-0.5 * r2);
    out[p] = (real)k;
    for (g = 0; g < N_GRAD; g++) {
      a = GRAD_DIMS[g];
      out[(1 + g) * n + p] = (real)(k * (xn[a] - (double)X[p * D_IN + a]) /
                                    (LENGTHSCALE[a] * LENGTHSCALE[a]));
    }
  }
}

/* the kernel row of bin b's near set (shared rows first); returns its length R_b */
static int kernel_row(const double xn[D_IN], int b, real *k) {
  int u = N_SHARED * (1 + N_GRAD);
  if (N_SHARED) krows(xn, SHARED, N_SHARED, k);
  krows(xn, PTS + BIN_PT_OFF[b] * D_IN, BIN_NPTS[b], k + u);
  return u + BIN_NPTS[b] * (1 + N_GRAD);
}
#endif

#if HAS_VAR
/* sigma - |F_b k|^2, F_b row by row (each row's non-zero span, contiguous): a dot product
 * per row whose four partial sums stay in registers (the column-by-column axpy it replaces
 * was bound by its stores, one sum by its additions' latency). With GCC or clang the sums are
 * vectors: 32 bytes (AVX2), and 64 bytes in a version for CPUs with AVX-512, picked at run
 * time (64-byte vectors split in two on AVX2 were 3x slower). -DGPG_NO_VECTOR, or another
 * compiler, takes the scalar loop. */
#if (defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 9)) && !defined(GPG_NO_VECTOR)
#if FREAL_IS_REAL
#define VLOAD(V, T, F) memcpy(&(V), (F), sizeof(V))
#else
#define VLOAD(V, T, F) \
  do { T##_f t_; memcpy(&t_, (F), sizeof t_); (V) = __builtin_convertvector(t_, T); } while (0)
#endif
#define ROW_DOT(NAME, T, W)                                                                  \
  static inline real NAME(const freal *f, const real *k, int len) {                         \
    T a = {0}, b = {0}, c = {0}, d = {0}, kv, fv;                                            \
    real s = 0;                                                                              \
    int i, j;                                                                                \
    for (i = 0; i + 4 * (W) <= len; i += 4 * (W)) {                                          \
      memcpy(&kv, k + i, sizeof kv); VLOAD(fv, T, f + i); a += fv * kv;                      \
      memcpy(&kv, k + i + (W), sizeof kv); VLOAD(fv, T, f + i + (W)); b += fv * kv;          \
      memcpy(&kv, k + i + 2 * (W), sizeof kv); VLOAD(fv, T, f + i + 2 * (W)); c += fv * kv;  \
      memcpy(&kv, k + i + 3 * (W), sizeof kv); VLOAD(fv, T, f + i + 3 * (W)); d += fv * kv;  \
    }                                                                                        \
    for (; i + (W) <= len; i += (W)) {                                                       \
      memcpy(&kv, k + i, sizeof kv); VLOAD(fv, T, f + i); a += fv * kv;                      \
    }                                                                                        \
    a += b; c += d; a += c;                                                                  \
    for (j = 0; j < (W); j++) s += a[j];                                                     \
    for (; i < len; i++) s += (real)f[i] * k[i];                                             \
    return s;                                                                                \
  }
typedef real v32 __attribute__((vector_size(32)));
typedef freal v32_f __attribute__((vector_size(32 / sizeof(real) * sizeof(freal))));
ROW_DOT(row_dot, v32, (int)(32 / sizeof(real)))
#else
static real row_dot(const freal *f, const real *k, int len) {
  real s0 = 0, s1 = 0, s2 = 0, s3 = 0;
  int i;
  for (i = 0; i + 3 < len; i += 4) {
    s0 += (real)f[i] * k[i]; s1 += (real)f[i + 1] * k[i + 1];
    s2 += (real)f[i + 2] * k[i + 2]; s3 += (real)f[i + 3] * k[i + 3];
  }
  for (; i < len; i++) s0 += (real)f[i] * k[i];
  return (s0 + s1) + (s2 + s3);
}
#endif

#define LATENT_VARIANCE(NAME, DOT)                                                           \
  static double NAME(const real *k, int b, int nr) {                                        \
    double q = 0.0, v;                                                                       \
    long base = ROW_BASE[b];                                                                 \
    int r;                                                                                   \
    for (r = 0; r < nr; r++) {                                                               \
      v = (double)DOT(FACT + ROW_OFF[base + r], k + ROW_FIRST[base + r], ROW_LEN[base + r]); \
      q += v * v;                                                                            \
    }                                                                                        \
    return SIGMA_NOISE[0] - q;                                                               \
  }
HOT LATENT_VARIANCE(latent_variance_any, row_dot)

#if defined(GPG_CLONES) && !defined(GPG_NO_AVX512) && !defined(GPG_NO_VECTOR)
#pragma GCC push_options
#pragma GCC target("arch=x86-64-v4")
typedef real v64 __attribute__((vector_size(64)));
typedef freal v64_f __attribute__((vector_size(64 / sizeof(real) * sizeof(freal))));
ROW_DOT(row_dot64, v64, (int)(64 / sizeof(real)))
LATENT_VARIANCE(latent_variance64, row_dot64)
#pragma GCC pop_options
#define HAS_AVX512()                                                                         \
  (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&               \
   __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq"))
#else
#define HAS_AVX512() 0
#define latent_variance64 latent_variance_any
#endif

static double latent_variance(const real *k, int b, int nr) {
  return HAS_AVX512() ? latent_variance64(k, b, nr) : latent_variance_any(k, b, nr);
}
#endif

#if HAS_GLOBAL_MEAN
/* exp(x) for x <= 0 without a branch or a call, so that the loop over the training points
 * vectorises: x = n ln2 + r with |r| <= ln2/2 (n rounded to nearest by adding 1.5 * 2^52),
 * exp(r) by its Taylor polynomial of degree 13 (truncation below 1e-17 relative), 2^n written
 * into the exponent's bits; 0 below -708, where exp leaves the normal doubles (a select by
 * bit masks from the sign of x + 708: a comparison would be a branch at -O2) */
static inline double vexp(double x) {
  const double shift = 6755399441055744.0, lowest = -708.0;
  double y = x + 708.0, t, n, r, p, s;
  unsigned long long bits, keep, xb, lb;
  memcpy(&keep, &y, sizeof keep);
  keep = ~(unsigned long long)((long long)keep >> 63);
  memcpy(&xb, &x, sizeof xb);
  memcpy(&lb, &lowest, sizeof lb);
  xb = (xb & keep) | (lb & ~keep);
  memcpy(&y, &xb, sizeof y);
  t = y * 1.4426950408889634 + shift;
  n = t - shift;
  r = (y - n * 0.693147180369123816490) - n * 1.90821492927058770002e-10;
  p = 1.6059043836821613e-10;
  p = p * r + 2.08767569878680989792e-09;
  p = p * r + 2.50521083854417187751e-08;
  p = p * r + 2.75573192239858906526e-07;
  p = p * r + 2.75573192239858906526e-06;
  p = p * r + 2.48015873015873015873e-05;
  p = p * r + 1.98412698412698412698e-04;
  p = p * r + 1.38888888888888888889e-03;
  p = p * r + 8.33333333333333333333e-03;
  p = p * r + 4.16666666666666666667e-02;
  p = p * r + 1.66666666666666666667e-01;
  p = p * r + 0.5;
  p = p * r + 1.0;
  p = p * r + 1.0;
  memcpy(&bits, &t, sizeof bits);
  bits = (bits - 0x4338000000000000ULL + 1023ULL) << 52;
  memcpy(&s, &bits, sizeof s);
  p = p * s;
  memcpy(&bits, &p, sizeof bits);
  bits &= keep;
  memcpy(&p, &bits, sizeof p);
  return p;
}

/* the folded exact mean of gpg.gp.mean (normalised units): sum_p k(x, x_p) c_p, in three
 * passes over the points (squared distances, kernel values, the coefficients' sums) that each
 * vectorise or keep their sums in registers. (The unfolded sum of gpg.export.layout's alpha
 * was tried: no more accurate in float here, where the coefficients' own rounding dominates,
 * and half again slower.) */
HOT static void global_mean(const double xn[D_IN], double yn[N_OUT]) {
  double k[N_MEAN], acc[N_OUT * (1 + N_GRAD)], xl;
  int i, j, p;
  for (p = 0; p < N_MEAN; p++) k[p] = 0.0;
  for (i = 0; i < D_IN; i++) {
    const double *col = XS_T + (long)i * N_MEAN;
    xl = xn[i] * INV_LS_M[i];
    for (p = 0; p < N_MEAN; p++) { double t = xl - col[p]; k[p] += t * t; }
  }
  for (p = 0; p < N_MEAN; p++) k[p] = vexp(-0.5 * k[p]);
  coef_sums(k, acc);
  for (j = 0; j < N_OUT; j++) {
    double mu = acc[j];
    for (i = 0; i < N_GRAD; i++) {
      int a = GRAD_DIMS[i];
      mu += xn[a] * INV_LS_M[a] * INV_LS_M[a] * acc[(1 + i) * N_OUT + j];
    }
    yn[j] = SIGMA_M[0] * mu;
  }
}
#endif

static int evaluate(const double rpm[4], const double euler[3], const double v_air[3],
                    double force[3], double torque[3], double *levels, double *variance) {
  double rwh[3][3], x[D_IN], xn[D_IN], yn[N_OUT], y[N_OUT], span, tol, latent = 0.0;
  int i, j, b = 0, nr = 0, in_domain = 1;
#if HAS_BINS
  real k[MAX_ROWS];
#endif
  for (i = 0; i < 3; i++) { force[i] = 0.0; torque[i] = 0.0; }
  for (i = 0; i < N_LEVELS; i++) levels[i] = 0.0;
  if (variance) for (i = 0; i < N_OUT; i++) variance[i] = 0.0;
  for (i = 0; i < 4; i++) if (!isfinite(rpm[i])) return 0;
  for (i = 0; i < 3; i++) if (!isfinite(euler[i]) || !isfinite(v_air[i])) return 0;
  for (i = 0; i < 4; i++) x[i] = rpm[i];
#if BODY_FRAME
  /* the GP's frame is the body's: x = (rpm, R_WB^T v_air), in domain inside the ball */
  rot_wb(euler[0], euler[1], euler[2], rwh);
  for (i = 0; i < 3; i++)
    x[4 + i] = rwh[0][i] * v_air[0] + rwh[1][i] * v_air[1] + rwh[2][i] * v_air[2];
  if (x[4] * x[4] + x[5] * x[5] + x[6] * x[6] >
      (BALL_RADIUS * (1.0 + 1e-9)) * (BALL_RADIUS * (1.0 + 1e-9)))
    in_domain = 0;
#else
  {
    double eh[3];
    to_airflow(euler, v_air, eh, rwh);
    for (i = 0; i < 3; i++) x[4 + i] = eh[i];
    x[7] = norm3(v_air);
  }
#endif
  for (i = 0; i < N_BOX; i++) {
    span = BOX_HI[i] - BOX_LO[i];
    tol = 1e-9 * (span > 1.0 ? span : 1.0);
    if (x[i] < BOX_LO[i] - tol || x[i] > BOX_HI[i] + tol) in_domain = 0;
  }
  for (i = 0; i < 4; i++) if (rpm[i] < 0.0) in_domain = 0;
#if !BODY_FRAME
  if (in_domain && !(frame_rate(euler, v_air) <= MAX_FRAME_RATE)) in_domain = 0;
#endif
  for (i = 0; i < D_IN; i++) xn[i] = (x[i] - X_LO[i]) / HALF[i] - 1.0;
#if HAS_BINS
  b = lookup(xn);
#endif
#if HAS_GLOBAL_MEAN
  global_mean(xn, yn);
#else
  nr = kernel_row(xn, b, k);
  for (j = 0; j < N_OUT; j++) {
    const real *c = BCOEF + BCOEF_OFF[b] + (long)j * nr;
    double s = 0.0;
    for (i = 0; i < nr; i++) s += (double)c[i] * (double)k[i];
    yn[j] = s;
  }
#endif
#if HAS_VAR
  if (variance) {
    if (!nr) nr = kernel_row(xn, b, k);
    latent = latent_variance(k, b, nr);
  }
#endif
  (void)b; (void)nr; (void)latent;
  for (j = 0; j < N_OUT; j++) y[j] = yn[j] * Y_STD[j] + Y_MEAN[j];
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) { force[i] += rwh[i][j] * y[j]; torque[i] += rwh[i][j] * y[3 + j]; }
  for (i = 0; i < N_LEVELS; i++) levels[i] = y[6 + i];
#if HAS_ALLOCATION
  /* M at the world attitude: A r^2 = (sum T, tau_x, tau_y, tau_z), thrust along -z_B */
  {
    double u[4] = {0.0, 0.0, 0.0, 0.0}, fb[3], rwb[3][3];
    for (i = 0; i < 4; i++)
      for (j = 0; j < 4; j++) u[i] += ALLOCATION[i * 4 + j] * rpm[j] * rpm[j];
    fb[0] = 0.0; fb[1] = 0.0; fb[2] = -u[0];
    rot_wb(euler[0], euler[1], euler[2], rwb);
    for (i = 0; i < 3; i++)
      for (j = 0; j < 3; j++) { force[i] += rwb[i][j] * fb[j]; torque[i] += rwb[i][j] * u[1 + j]; }
  }
#endif
  if (variance) {
    /* c_m (latent + nu^2) std_m^2 per output in H, then diag(R diag(d) R^T) for the vectors */
    double pv[N_OUT];
    for (j = 0; j < N_OUT; j++)
      pv[j] = OUTPUT_SCALE[j] * ((latent > 0.0 ? latent : 0.0) + SIGMA_NOISE[1]) * Y_STD[j] *
              Y_STD[j];
    for (i = 0; i < 3; i++) {
      variance[i] = 0.0; variance[3 + i] = 0.0;
      for (j = 0; j < 3; j++) {
        variance[i] += rwh[i][j] * rwh[i][j] * pv[j];
        variance[3 + i] += rwh[i][j] * rwh[i][j] * pv[3 + j];
      }
    }
    for (i = 6; i < N_OUT; i++) variance[i] = pv[i];
    for (i = 0; i < N_OUT; i++) if (!isfinite(variance[i])) in_domain = 0;
  }
  for (i = 0; i < 3; i++) if (!isfinite(force[i]) || !isfinite(torque[i])) in_domain = 0;
  for (i = 0; i < N_LEVELS; i++) if (!isfinite(levels[i])) in_domain = 0;
  return in_domain;
}
"""


# The hot loops also in an AVX2/FMA version that glibc's loader picks on CPUs that have it
# (GCC's function multiversioning): the default x86-64 target has 2-wide doubles only. Measured
# at data=default on the development CPU: the mean 15.9 -> 11.3 us. With them (GPG_CLONES), the
# variance's row products also have an AVX-512 version, picked at run time (latent_variance).
# Off elsewhere (ARM, clang, musl, MSVC) and with -DGPG_NO_CLONES; -DGPG_NO_AVX512 leaves out
# the AVX-512 version alone (for CPUs that slow their clock for 512-bit work). The values do
# not depend on the version beyond FMA rounding and the order of the variance's partial sums.
_CLONES = """#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && \\
    defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__) && !defined(GPG_NO_CLONES)
#define GPG_CLONES 1
#define HOT __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define HOT
#endif

"""


def _source(name: str, dtype: str, s: Layout, record: dict[str, Any]) -> str:
    flags = {
        "HAS_BINS": s.bins is not None,
        "HAS_VAR": s.has_variance,
        "HAS_GLOBAL_MEAN": s.global_mean is not None,
        "HAS_ALLOCATION": s.allocation is not None,
    }
    defs = [f"#define {k} {int(v)}" for k, v in flags.items()]
    defs += [f"#define BOX_LO {name}_box_lo"]
    defs.append(f"#define BOX_HI {name}_box_hi")
    head = (
        f"/* {name}.c: generated by gpg.export.to_c (gpg {record['gpg_version']}, model "
        f"{record['model']}, arrays sha256 {record['arrays_sha256']}). See {name}.h. */\n"
        f'#include <math.h>\n#include <string.h>\n#include "{name}.h"\n\n' + _CLONES
    )
    public = f"""
int {name}_mean(const double rpm[4], const double euler[3], const double v_air[3],
                double force[3], double torque[3], double *levels) {{
  return evaluate(rpm, euler, v_air, force, torque, levels, 0);
}}
"""
    if s.has_variance:
        public += f"""
int {name}_predict(const double rpm[4], const double euler[3], const double v_air[3],
                   double force[3], double torque[3], double *levels, double *variance) {{
  return evaluate(rpm, euler, v_air, force, torque, levels, variance);
}}
"""
    consts = "\n".join(defs + _constants(name, dtype, s))
    m = s.n_outputs
    sums = _coef_sums(m, m * len(s.grad_dims)) if s.global_mean is not None else ""
    return head + consts + "\n" + _FRAMES + sums + _BODY + public


def _split_coef(
    gm: dict[str, np.ndarray], grad_dims, m: int, np_type
) -> tuple[np.ndarray, np.ndarray]:
    """The folded mean's value block ``c⁰`` (N, M), kept in double, and its gradient blocks
    ``cᵍ`` (N, G·M) in the dtype asked for. The value block is where the folded sum cancels
    (``c⁰ = α⁰ − Σ_g (x_p,g/l_g²) αᵍ``), so it stays in double; and it is refolded from the
    stored ``cᵍ`` so that their rounding enters the mean as ``Σ_p k_p (x_g − x_p,g)/l_g² δᵍ_p``,
    small where ``k_p`` is not, instead of ``Σ_p k_p x_g/l_g² δᵍ_p``. At data=default this
    takes the float export's mean error from 1.9e-5 to below 1e-5 of the force's scale for 36 kB
    (the float mean-only export then holds 388 kB). In double it changes nothing."""
    coef, xs, inv_ls = gm["coef"], gm["xs"], gm["inv_ls"]
    value, grad = coef[:, :m].copy(), coef[:, m:].astype(np_type)
    delta = coef[:, m:] - grad.astype(np.float64)
    for i, g in enumerate(grad_dims):
        value += (xs[:, g] * inv_ls[g])[:, None] * delta[:, i * m : (i + 1) * m]
    return value, grad


def _coef_sums(m: int, n_grad: int, block: int = 24) -> str:
    """``acc[j] = sum_p k[p] C[p, j]`` for the global mean (``C`` = ``COEF0`` for its ``m``
    value columns, then ``COEFG`` for its ``n_grad`` gradient ones), ``block`` sums at a time
    in named locals: held in registers across the loop over the points instead of loaded and
    stored each time (3x faster at -O2 at data=default; each sum keeps its order)."""
    parts = [
        "/* acc[j] = sum_p k[p] C[p, j], the sums in blocks held in registers */",
        "HOT static void coef_sums(const double *k, double *acc) {",
        "  int p;",
    ]
    groups = [("COEF0", m, 0, j0) for j0 in range(0, m, block)]
    groups += [("COEFG", n_grad, m, j0) for j0 in range(0, n_grad, block)]
    for array, width, acc0, j0 in groups:
        b = min(block, width - j0)
        names = [f"a{q}" for q in range(b)]
        parts.append("  {")
        parts.append(f"    double {', '.join(n + ' = 0.0' for n in names)};")
        parts.append("    for (p = 0; p < N_MEAN; p++) {")
        parts.append(f"      const {'double' if array == 'COEF0' else 'real'} *c = "
                     f"{array} + (long)p * {width} + {j0};")  # fmt: skip
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
