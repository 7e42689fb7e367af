"""A fitted surrogate outside JAX: its mean as self-contained C source (:func:`to_c`) and as a
CasADi function with exact derivatives (:func:`to_casadi`); the variance and ONNX are open work.

``to_c(sur, directory)`` writes ``<name>.c`` and ``<name>.h``: the world-frame prediction
``(rpm, euler, v_air) -> (force, torque, levels, in_domain)`` of :meth:`Surrogate.predict_mean`,
with the trained arrays as constants and no dependency but libm. It is the same computation:
the airflow frame (with its hover blend), the attitude in it, the normalisation, the folded
exact GP-G mean ``Σ_p k(x, x_p) c_p`` of :mod:`gpg.gp.mean`, the rotation back and the
simplified model ``M``; ``in_domain`` is the data's box, finite inputs, rotor speeds ≥ 0 and
the airflow frame's turn rate (:func:`gpg.quadrotor.frames.airflow_frame_rate`, here by
central differences, so a query within rounding of the threshold may be flagged differently).

``dtype="float"`` stores the GP's arrays in float (half the bytes, for a flight controller's
flash) and evaluates the kernel in float; the frame, the normalisation and the sums stay in
double. Kinds with the global mean export (``gpg``, ``gp``, ``gpgs_hybrid``); the local kinds'
per-bin means and ``M_noise`` do not yet, and say so before anything is written.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from gpg._io import atomic_write
from gpg._version import __version__
from gpg.gp.mean import GlobalMean
from gpg.names import AERO, INPUTS
from gpg.quadrotor.frames import _TINY_SPEED
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

DTYPES = {"double": (np.float64, "double", "exp"), "float": (np.float32, "float", "expf")}


def to_c(
    sur: Surrogate, directory: str | Path, *, name: str = "gpg_model", dtype: str = "double"
) -> dict[str, Any]:
    """Write ``<directory>/<name>.c`` and ``.h`` for ``sur``'s mean; returns what was written
    (paths, bytes of constants, the record of gpg version, model, arrays' SHA-256, units).

    The header documents the call: ``int <name>_mean(const double rpm[4], const double
    euler[3], const double v_air[3], double force[3], double torque[3], double *levels)``
    returns ``in_domain`` (1 or 0); units rpm, rad (yaw, pitch, roll: ``R_WB = Rz Ry Rx``),
    m/s, N, N·m, dB; world frame x forward, y right, z down. A non-finite input gives 0 and
    zeros, never NaN. ``ValueError`` (nothing written) for a model without the global mean, a
    noise model, a non-finite array, a bad ``name`` or ``dtype``."""
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {list(DTYPES)}, got {dtype!r}")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    arrays, mean = _checked(sur)
    record = {
        "gpg_version": __version__,
        "model": sur.model_name,
        "arrays_sha256": _digest(arrays),
        "dtype": dtype,
        "inputs": "rpm[4] (rpm), euler[3] (rad, yaw pitch roll, R_WB = Rz Ry Rx), "
        "v_air[3] (m/s, vehicle velocity minus wind, world frame x forward y right z down)",
        "outputs": "force[3] (N), torque[3] (N*m), world frame; levels[K] (dB)",
        "levels": list(sur.output_names[len(AERO) :]),
        "hover_speed": sur.hover_speed,
        "max_frame_rate": MAX_FRAME_RATE,
    }
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    source, n_const = _source(name, dtype, arrays, sur, mean, record)
    header = _header(name, arrays, record)
    c_path, h_path = directory / f"{name}.c", directory / f"{name}.h"
    atomic_write(h_path, header.encode())
    atomic_write(c_path, source.encode())
    return {"c": c_path, "h": h_path, "constant_bytes": n_const, "record": record}


def _arrays(sur: Surrogate, mean: GlobalMean) -> dict[str, np.ndarray]:
    norm = sur.normalizer
    out = {
        "x_lo": np.asarray(norm.x_lo, float),
        "half": np.asarray(norm.half_range, float),
        "y_mean": np.asarray(norm.y_mean, float),
        "y_std": np.asarray(norm.y_std, float),
        "box_lo": np.asarray(sur.box_lo, float),
        "box_hi": np.asarray(sur.box_hi, float),
        "xs": np.asarray(mean.Xs, float),
        "coef": np.asarray(mean.coef, float),
        "inv_ls": np.asarray(mean.inv_ls, float),
        "sigma": np.asarray(mean.variance, float).reshape(1),
    }
    if sur.simple is not None:
        s = sur.simple
        out["allocation"] = np.asarray(s.allocation, float)
    return out


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(arrays[k], dtype=np.float64).tobytes())
    return h.hexdigest()


def _literal(a: np.ndarray, np_type) -> str:
    """A C initializer (rows in braces) whose values read back exactly in the C type (17 or 9
    significant digits)."""
    a = np.asarray(a, np_type)
    if a.ndim == 2:
        return "{\n" + ",\n".join(_literal(row, np_type) for row in a) + "\n}"
    digits = 17 if np_type is np.float64 else 9
    suffix = "" if np_type is np.float64 else "f"
    vals = [f"{float(v):.{digits}g}{suffix}" for v in a.ravel()]
    lines = [", ".join(vals[i : i + 6]) for i in range(0, len(vals), 6)]
    return "{" + ",\n  ".join(lines) + "}"


def _header(name: str, arrays: dict[str, np.ndarray], record: dict[str, Any]) -> str:
    guard = name.upper() + "_H"
    n_levels = len(record["levels"])
    meta = json.dumps(record, indent=1, sort_keys=True).replace("*/", "* /")
    lo, hi = arrays["box_lo"], arrays["box_hi"]
    box = "\n".join(f" *   {INPUTS[i]:9s} [{lo[i]:.17g}, {hi[i]:.17g}]" for i in range(len(INPUTS)))
    return f"""/* {name}: a gpg surrogate's mean prediction, generated by gpg.export.to_c.
 *
 * {meta}
 *
 * int {name}_mean(rpm, euler, v_air, force, torque, levels)
 *   rpm[4]    rotor speeds, rpm (r1 rear-right, r2 rear-left, r3 front-left, r4 front-right)
 *   euler[3]  yaw, pitch, roll in rad: R_WB = Rz(yaw) Ry(pitch) Rx(roll), body FRD
 *   v_air[3]  air velocity of the vehicle, m/s, world frame (x forward, y right, z down):
 *             vehicle velocity minus wind
 *   force[3], torque[3]  out: aerodynamic force (N) and torque (N*m), world frame
 *   levels[{n_levels}]  out: tonal noise levels, dB ({", ".join(record["levels"]) or "none"})
 * returns in_domain: 1 inside the training data's box (x_H = rpm, attitude in the airflow
 * frame, airspeed), rotor speeds >= 0, finite inputs and a well-conditioned airflow frame;
 * 0 otherwise (an extrapolation: the values are returned all the same, zeros for non-finite
 * input). The box of x_H (rpm, rad, m/s):
{box}
 */
#ifndef {guard}
#define {guard}

#define {name.upper()}_N_LEVELS {n_levels}

extern const double {name}_box_lo[8];
extern const double {name}_box_hi[8];

int {name}_mean(const double rpm[4], const double euler[3], const double v_air[3],
                double force[3], double torque[3], double *levels);

#endif
"""


_FRAMES = r"""
static double safe_atan2(double y, double x, double tiny) {
  if (fabs(x) <= tiny && fabs(y) <= tiny) return 0.0;
  return atan2(y, x);
}

static double norm3(const double v[3]) {
  double s = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  return s <= 0.0 ? 0.0 : sqrt(s);
}

/* R = Rz(yaw) Ry(pitch) Rx(roll) */
static void rot_wb(double yaw, double pitch, double roll, double R[3][3]) {
  double cy = cos(yaw), sy = sin(yaw), cp = cos(pitch), sp = sin(pitch);
  double cr = cos(roll), sr = sin(roll);
  R[0][0] = cy * cp; R[0][1] = cy * sp * sr - sy * cr; R[0][2] = cy * sp * cr + sy * sr;
  R[1][0] = sy * cp; R[1][1] = sy * sp * sr + cy * cr; R[1][2] = sy * sp * cr - cy * sr;
  R[2][0] = -sp;     R[2][1] = cp * sr;                R[2][2] = cp * cr;
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
"""


# Long by design: mostly the C function's template, read top to bottom like the code it
# writes; split, its sizes and names would pass between a handful of pieces.
def _source(name, dtype, arrays, sur, mean, record) -> tuple[str, int]:
    np_type, ctype, exp = DTYPES[dtype]
    n, d = arrays["xs"].shape
    cols = arrays["coef"].shape[1]
    g = len(mean.grad_dims)
    m = cols // (1 + g)
    n_levels = m - len(AERO)
    gp_bytes = (arrays["xs"].size + arrays["coef"].size) * np.dtype(np_type).itemsize
    consts = [f"#define TINY_SPEED {_TINY_SPEED!r}", f"#define HOVER_SPEED {sur.hover_speed!r}"]
    consts.append(f"#define MAX_FRAME_RATE {MAX_FRAME_RATE!r}")
    consts.append(f"typedef {ctype} real;")
    for key in ("x_lo", "half", "y_mean", "y_std", "inv_ls", "sigma"):
        a = arrays[key]
        consts.append(f"static const double {key.upper()}[{a.size}] = {_literal(a, np.float64)};")
    for key in ("box_lo", "box_hi"):
        a = arrays[key]
        consts.append(f"const double {name}_{key}[{a.size}] = {_literal(a, np.float64)};")
    consts.append(f"static const real XS[{n}][{d}] = {_literal(arrays['xs'], np_type)};")
    consts.append(f"static const real COEF[{n}][{cols}] = {_literal(arrays['coef'], np_type)};")
    grad = ", ".join(str(i) for i in mean.grad_dims) or "0"
    consts.append(f"static const int GRAD_DIMS[{max(g, 1)}] = {{{grad}}};")
    has_simple = "allocation" in arrays
    if has_simple:
        a = arrays["allocation"]
        consts.append(f"static const double ALLOCATION[4][4] = {_literal(a, np.float64)};")
    simple = (
        """
  /* M at the world attitude: A r^2 = (sum T, tau_x, tau_y, tau_z), thrust along -z_B */
  {
    double u[4] = {0.0, 0.0, 0.0, 0.0}, fb[3], rwb[3][3];
    for (i = 0; i < 4; i++)
      for (j = 0; j < 4; j++) u[i] += ALLOCATION[i][j] * rpm[j] * rpm[j];
    fb[0] = 0.0; fb[1] = 0.0; fb[2] = -u[0];
    rot_wb(euler[0], euler[1], euler[2], rwb);
    for (i = 0; i < 3; i++)
      for (j = 0; j < 3; j++) { force[i] += rwb[i][j] * fb[j]; torque[i] += rwb[i][j] * u[1 + j]; }
  }"""
        if has_simple
        else ""
    )
    body = f"""
int {name}_mean(const double rpm[4], const double euler[3], const double v_air[3],
                double force[3], double torque[3], double *levels) {{
  double eh[3], rwh[3][3], x[8], xn[8], xl[8], acc[{cols}], y[{m}], speed, span, tol;
  int i, j, p, in_domain = 1;
  for (i = 0; i < 3; i++) {{ force[i] = 0.0; torque[i] = 0.0; }}
  for (i = 0; i < {n_levels}; i++) levels[i] = 0.0;
  for (i = 0; i < 4; i++) if (!isfinite(rpm[i])) return 0;
  for (i = 0; i < 3; i++) if (!isfinite(euler[i]) || !isfinite(v_air[i])) return 0;
  to_airflow(euler, v_air, eh, rwh);
  speed = norm3(v_air);
  for (i = 0; i < 4; i++) x[i] = rpm[i];
  for (i = 0; i < 3; i++) x[4 + i] = eh[i];
  x[7] = speed;
  for (i = 0; i < 8; i++) {{
    span = {name}_box_hi[i] - {name}_box_lo[i];
    tol = 1e-9 * (span > 1.0 ? span : 1.0);
    if (x[i] < {name}_box_lo[i] - tol || x[i] > {name}_box_hi[i] + tol) in_domain = 0;
  }}
  for (i = 0; i < 4; i++) if (rpm[i] < 0.0) in_domain = 0;
  if (in_domain && !(frame_rate(euler, v_air) <= MAX_FRAME_RATE)) in_domain = 0;
  /* the folded exact mean of gpg.gp.mean: sum_p k(x, x_p) c_p */
  for (i = 0; i < 8; i++) {{ xn[i] = (x[i] - X_LO[i]) / HALF[i] - 1.0; xl[i] = xn[i] * INV_LS[i]; }}
  for (j = 0; j < {cols}; j++) acc[j] = 0.0;
  for (p = 0; p < {n}; p++) {{
    real r2 = 0, t, k;
    for (i = 0; i < {d}; i++) {{ t = (real)xl[i] - XS[p][i]; r2 += t * t; }}
    k = {exp}(-0.5{"f" if dtype == "float" else ""} * r2);
    for (j = 0; j < {cols}; j++) acc[j] += (double)k * (double)COEF[p][j];
  }}
  for (j = 0; j < {m}; j++) {{
    double mu = acc[j];
    for (i = 0; i < {g}; i++) {{
      int a = GRAD_DIMS[i];
      mu += xn[a] * INV_LS[a] * INV_LS[a] * acc[(1 + i) * {m} + j];
    }}
    y[j] = SIGMA[0] * mu * Y_STD[j] + Y_MEAN[j];
  }}
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) {{ force[i] += rwh[i][j] * y[j]; torque[i] += rwh[i][j] * y[3 + j]; }}
  for (i = 0; i < {n_levels}; i++) levels[i] = y[6 + i];{simple}
  return in_domain;
}}
"""
    head = (
        f"/* {name}.c: generated by gpg.export.to_c (gpg {record['gpg_version']}, model "
        f"{record['model']}, arrays sha256 {record['arrays_sha256']}). See {name}.h. */\n"
        f'#include <math.h>\n#include "{name}.h"\n\n'
    )
    return head + "\n".join(consts) + "\n" + _FRAMES + body, gp_bytes


def to_casadi(sur: Surrogate, *, frame: str = "world", name: str = "gpg_mean"):
    """``sur``'s mean as a ``casadi.Function`` of ``(rpm[4], euler[3], v_air[3])`` returning
    ``force[3], torque[3], levels[K], in_domain`` (1.0 or 0.0): the computation of
    :meth:`Surrogate.predict_mean` in CasADi MX symbolics with the trained arrays as constants,
    so that CasADi's own AD gives exact Jacobians and Hessians to a gradient-based MPC
    (IPOPT, acados, do-mpc) and its code generator gives C. ``frame="body"`` returns force and
    torque in the body frame (FRD) for the same inputs (``v_air`` in the world frame).
    ``in_domain`` uses CasADi's own Jacobian of the airflow frame for the frame-rate test, as
    the library uses autodiff. Needs the ``casadi`` extra; the same kinds as :func:`to_c`."""
    import casadi as ca

    if frame not in ("world", "body"):
        raise ValueError(f"frame must be 'world' or 'body', got {frame!r}")
    arrays, mean = _checked(sur)
    rpm, euler, v = ca.MX.sym("rpm", 4), ca.MX.sym("euler", 3), ca.MX.sym("v_air", 3)
    euler_h, rwh = _ca_airflow(ca, euler, v, sur.hover_speed)
    d_euler = ca.jacobian(euler_h, v)
    d_frame = ca.jacobian(ca.vec(rwh), v)
    rate = ca.fmax(ca.norm_fro(d_euler), ca.norm_fro(d_frame) / np.sqrt(2.0))
    if sur.hover_speed <= 0.0:
        rate = ca.if_else(v[0] ** 2 + v[1] ** 2 <= _TINY_SPEED**2, ca.inf, rate)
    speed = _ca_norm(ca, v)
    x = ca.vertcat(rpm, euler_h, speed)
    lo, hi = arrays["box_lo"], arrays["box_hi"]
    tol = 1e-9 * np.maximum(hi - lo, 1.0)
    inside = ca.MX(1)
    for i in range(8):
        inside = ca.logic_and(inside, ca.logic_and(x[i] >= lo[i] - tol[i], x[i] <= hi[i] + tol[i]))
    for i in range(4):
        inside = ca.logic_and(inside, rpm[i] >= 0)
    in_domain = ca.logic_and(inside, rate <= MAX_FRAME_RATE)
    y = _ca_mean(ca, x, arrays, mean)
    R_out = ca.mtimes(_ca_rot(ca, euler[0], euler[1], euler[2]).T, rwh) if frame == "body" else rwh
    force, torque = ca.mtimes(R_out, y[0:3]), ca.mtimes(R_out, y[3:6])
    if "allocation" in arrays:
        u = ca.mtimes(ca.DM(arrays["allocation"]), rpm**2)
        f_b, t_b = ca.vertcat(0, 0, -u[0]), u[1:4]
        if frame == "body":
            force, torque = force + f_b, torque + t_b
        else:
            rwb = _ca_rot(ca, euler[0], euler[1], euler[2])
            force, torque = force + ca.mtimes(rwb, f_b), torque + ca.mtimes(rwb, t_b)
    levels = y[6:]
    return ca.Function(
        name,
        [rpm, euler, v],
        [force, torque, levels, in_domain],
        ["rpm", "euler", "v_air"],
        ["force", "torque", "levels", "in_domain"],
    )


def _checked(sur: Surrogate) -> tuple[dict[str, np.ndarray], GlobalMean]:
    """The arrays of an exportable surrogate, or ``ValueError`` saying why it is not."""
    if not isinstance(sur, Surrogate):
        raise ValueError(f"export takes a gpg.Surrogate, got {type(sur).__name__}")
    mean = getattr(sur.model, "mean", None)
    if not isinstance(mean, GlobalMean):
        raise ValueError(
            f"model {sur.model_name!r} ({type(sur.model).__name__}) has no global mean to "
            "export; export covers gpg, gp and gpgs_hybrid (the local kinds' per-bin means "
            "are not exported yet)"
        )
    if sur.noise_model is not None:
        raise ValueError("a surrogate with M_noise cannot be exported yet (fit without it)")
    arrays = _arrays(sur, mean)
    bad = sorted(k for k, a in arrays.items() if not np.all(np.isfinite(a)))
    if bad:
        raise ValueError(f"the surrogate holds non-finite arrays {bad}: nothing exported")
    return arrays, mean


def _ca_safe_atan2(ca, y, x, tiny):
    at_origin = ca.logic_and(ca.fabs(x) <= tiny, ca.fabs(y) <= tiny)
    return ca.if_else(
        at_origin, 0, ca.atan2(ca.if_else(at_origin, 0, y), ca.if_else(at_origin, 1, x))
    )


def _ca_norm(ca, v):
    s = ca.sumsqr(v)
    return ca.if_else(s <= 0, 0, ca.sqrt(ca.if_else(s <= 0, 1, s)))


def _ca_rot(ca, yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (ca.cos, ca.sin))
    return ca.vertcat(
        ca.horzcat(cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        ca.horzcat(sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        ca.horzcat(-sp, cp * sr, cp * cr),
    )


def _ca_wind_axes(ca, d):
    heading = _ca_safe_atan2(ca, d[1], d[0], _TINY_SPEED)
    climb = _ca_safe_atan2(ca, -d[2], _ca_norm(ca, d[0:2]), _TINY_SPEED)
    return _ca_rot(ca, heading, climb, 0)


def _ca_airflow(ca, euler, v, h):
    """``(euler_H, R_WH)``: :func:`gpg.quadrotor.frames.to_airflow_frame` in CasADi."""
    yaw = euler[0]
    if h <= 0.0:
        rwh = _ca_wind_axes(ca, v)
    else:
        c = h * ca.fmax(1 - ca.sumsqr(v) / h**2, 0) ** 2
        d = v + c * ca.vertcat(ca.cos(yaw), ca.sin(yaw), 0)
        dxy2 = d[0] ** 2 + d[1] ** 2
        x = d / ca.if_else(ca.sumsqr(d) > 0, _ca_norm(ca, d), 1)
        c2 = h * ca.fmax(1 - dxy2 / h**2, 0) ** 2
        y_ref = ca.vertcat(-d[1], d[0], 0) + c2 * ca.vertcat(-ca.sin(yaw), ca.cos(yaw), 0)
        y = y_ref - ca.dot(y_ref, x) * x
        y = y / ca.if_else(ca.sumsqr(y) > 0, _ca_norm(ca, y), 1)
        blended = ca.horzcat(x, y, ca.cross(x, y))
        rwh = ca.if_else(dxy2 >= h**2, _ca_wind_axes(ca, d), blended)
    R = ca.mtimes(rwh.T, _ca_rot(ca, euler[0], euler[1], euler[2]))
    cp = ca.sqrt(R[0, 0] ** 2 + R[1, 0] ** 2)
    pitch = _ca_safe_atan2(ca, -R[2, 0], cp, 0.0)
    locked = cp < 1e-12
    yaw_h = ca.if_else(
        locked,
        _ca_safe_atan2(ca, -R[0, 1], R[1, 1], 0.0),
        _ca_safe_atan2(ca, R[1, 0], R[0, 0], 0.0),
    )
    roll = ca.if_else(locked, 0, _ca_safe_atan2(ca, R[2, 1], R[2, 2], 0.0))
    return ca.vertcat(yaw_h, pitch, roll), rwh


def _ca_mean(ca, x, arrays, mean: GlobalMean):
    """The de-normalised folded exact mean (M,) at ``x_H`` (8,), in MX with DM constants."""
    xn = (x - ca.DM(arrays["x_lo"])) / ca.DM(arrays["half"]) - 1
    inv_ls = arrays["inv_ls"]
    xl = xn * ca.DM(inv_ls)
    XS = ca.DM(arrays["xs"])
    n = arrays["xs"].shape[0]
    r2 = ca.sum2((ca.repmat(xl.T, n, 1) - XS) ** 2)
    acc = ca.mtimes(ca.DM(arrays["coef"]).T, ca.exp(-0.5 * r2))
    g = len(mean.grad_dims)
    m = arrays["coef"].shape[1] // (1 + g)
    mu = acc[0:m]
    for i, a in enumerate(mean.grad_dims):
        mu = mu + xn[a] * inv_ls[a] ** 2 * acc[(1 + i) * m : (2 + i) * m]
    return float(arrays["sigma"][0]) * mu * ca.DM(arrays["y_std"]) + ca.DM(arrays["y_mean"])
