"""A fitted surrogate as an ONNX model (:func:`to_onnx`) for ONNX Runtime's C, C++, C#, Rust
and Java APIs: the batched world-frame prediction built node by node with ``onnx.helper``.

The graph computes what :meth:`Surrogate.predict` does, for a batch of N states at once, in
float32 (ONNX Runtime's CPU kernels have no float64 ``Atan``): the airflow frame with its
hover blend (``atan2`` from ``Atan`` and ``Where``), the attitude in it, the normalisation,
the GP, the rotation back and ``M``. A partitioned model evaluates every bin for every state
and keeps each state's own through the one-hot of its bin's box (B small products batch better
than a gather of every state's factor). ``in_domain`` is the box, finite inputs and outputs,
rotor speeds ≥ 0 and the airflow frame's turn rate by central differences (a step of
1e-3 m/s: float32 leaves no finer one), so a state within about 1e-3 of a threshold may be
flagged differently from the library. A body-frame surrogate's graph has no airflow frame:
the GP reads ``(rpm, R_WBᵀ v_air)`` and ``in_domain`` is the rotor box and the ball.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gpg._io import atomic_write
from gpg.export.layout import MAX_BYTES, Layout, refuse_wind, spec
from gpg.quadrotor.frames import TINY_SPEED
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

__all__ = ["to_onnx"]

FLOAT, DOUBLE = 1, 11  # onnx.TensorProto's element types
OPSET = 17  # ONNX Runtime 1.14 (2023) on: what C#, Rust and Java bindings in use still ship
RATE_STEP = 1e-3  # m/s: the central-difference step of the frame rate in float32


def to_onnx(
    sur: Surrogate,
    path: str | Path,
    *,
    variance: bool = True,
    batch: bool = True,
    max_bytes: int = MAX_BYTES,
) -> dict[str, Any]:
    """Write ``sur`` as an ONNX model to ``path``, checked by ``onnx.checker``.

    Inputs ``rpm`` (N, 4) rpm, ``euler`` (N, 3) rad (yaw, pitch, roll; ``R_WB = Rz Ry Rx``),
    ``v_air`` (N, 3) m/s world frame (vehicle velocity minus wind), float32, any N. Outputs
    ``force`` (N, 3) N, ``torque`` (N, 3) N·m (world frame), ``levels`` (N, K) dB, with
    ``variance`` (and a model that has one) ``variance`` (N, 6+K), and ``in_domain`` (N,) bool;
    zeros where an input is not finite. ``batch=False`` writes the graph for one state a run
    (``N = 1``, what a simulator calls once per step): the partitioned kinds' bin is then found
    by ``If`` nodes along the partition's tree and only that bin is evaluated, where the
    batched graph evaluates every bin for every state. Needs the ``onnx`` extra.

    Args:
        sur: the fitted surrogate, airflow or body frame.
        path: the file to write (its directory made if missing).
        variance: whether to output the variance (for a model that has one).
        batch: a graph for any N states (True) or for one state a run (False).
        max_bytes: the most bytes of constants written.

    Returns:
        What was written: ``onnx`` (the path), ``bytes`` (of the file), ``constant_bytes``,
        ``variance`` (whether the graph outputs it) and ``record`` (gpg version, model,
        arrays' SHA-256, units; also in the model's ``metadata_props``).

    Raises:
        ValueError: nothing written, for a model :func:`gpg.export.layout.spec` refuses or
            constants over ``max_bytes``.
    """
    import onnx

    s = spec(sur, variance=variance, max_bytes=max_bytes)
    refuse_wind(s, "ONNX")
    n_const = s.constant_bytes(8, variance=s.has_variance)  # float64 but the float32 factors
    if n_const > max_bytes:
        raise ValueError(
            f"the export of {s.model!r} holds {n_const / 2**20:.1f} MiB of constants, over "
            f"max_bytes={max_bytes / 2**20:.1f} MiB (variance=False keeps the mean only)"
        )
    model = _build(onnx, s, bool(batch))
    onnx.checker.check_model(model)
    data = model.SerializeToString()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data)
    return {"onnx": path, "bytes": len(data), "constant_bytes": n_const, "variance": s.has_variance,
            "record": _record(s, batch)}  # fmt: skip


def _record(s: Layout, batch: bool) -> dict[str, Any]:
    return {**s.record, "dtype": "float", "batch": bool(batch)}


class _Graph:
    """Nodes, initialisers and fresh names; ``op`` returns its output's name."""

    def __init__(self, onnx):
        self.onnx, self.h = onnx, onnx.helper
        self.nodes, self.inits, self.n, self.small = [], [], 0, {}

    def name(self, hint: str) -> str:
        self.n += 1
        return f"{hint}_{self.n}"

    def const(self, a, hint: str = "c", dtype=np.float32) -> str:
        arr = np.asarray(a, dtype=dtype)
        # the frame repeats the same scalars and indices hundreds of times: one each
        key = (arr.dtype.str, arr.shape, arr.tobytes()) if arr.size <= 8 else None
        if key in self.small:
            return self.small[key]
        name = self.name(hint)
        self.inits.append(self.onnx.numpy_helper.from_array(arr, name))
        if key is not None:
            self.small[key] = name
        return name

    def op(self, kind: str, *inputs: str, hint: str | None = None, **attrs) -> str:
        out = self.name(hint or kind.lower())
        self.nodes.append(self.h.make_node(kind, list(inputs), [out], **attrs))
        return out

    # elementwise helpers on names (all float32 unless said)
    def add(self, a, b):
        return self.op("Add", a, b)

    def sub(self, a, b):
        return self.op("Sub", a, b)

    def mul(self, a, b):
        return self.op("Mul", a, b)

    def div(self, a, b):
        return self.op("Div", a, b)

    def num(self, v: float) -> str:
        return self.const(np.float32(v), "k")

    def where(self, c, a, b):
        return self.op("Where", c, a, b)

    def col(self, x, j: int):
        """Column ``j`` of (N, C) as (N, 1)."""
        return self.op("Gather", x, self.const(np.array([j]), "i", np.int64), axis=1)

    def cat(self, cols, axis: int = 1):
        return self.op("Concat", *cols, axis=axis)

    def sq(self, a):
        return self.mul(a, a)

    def sqrt0(self, s):
        """``sqrt(s)``, 0 where ``s <= 0`` (no NaN from a rounding below zero)."""
        pos = self.op("Greater", s, self.num(0.0))
        return self.where(pos, self.op("Sqrt", self.where(pos, s, self.num(1.0))), self.num(0.0))

    def atan2(self, y, x, tiny: float = 0.0):
        """``atan2(y, x)``, 0 where ``|x|, |y| <= tiny``, from ``Atan`` and the quadrants."""
        zero, pi = self.num(0.0), self.num(np.pi)
        x_pos, x_neg = self.op("Greater", x, zero), self.op("Less", x, zero)
        safe_x = self.where(self.op("Equal", x, zero), self.num(1.0), x)
        a = self.op("Atan", self.div(y, safe_x))
        y_nonneg = self.op("GreaterOrEqual", y, zero)
        left = self.where(y_nonneg, self.add(a, pi), self.sub(a, pi))
        on_axis = self.where(
            self.op("Greater", y, zero),
            self.num(np.pi / 2),
            self.where(self.op("Less", y, zero), self.num(-np.pi / 2), zero),
        )
        out = self.where(x_pos, a, self.where(x_neg, left, on_axis))
        t = self.num(tiny)
        small = self.op(
            "And",
            self.op("LessOrEqual", self.op("Abs", x), t),
            self.op("LessOrEqual", self.op("Abs", y), t),
        )
        return self.where(small, zero, out)


def _rot(g: _Graph, yaw, pitch, roll):
    """``Rz(yaw) Ry(pitch) Rx(roll)`` as a 3x3 list of (N, 1) names."""
    cy, sy = g.op("Cos", yaw), g.op("Sin", yaw)
    cp, sp = g.op("Cos", pitch), g.op("Sin", pitch)
    cr, sr = g.op("Cos", roll), g.op("Sin", roll)
    m = g.mul
    return [
        [m(cy, cp), g.sub(m(m(cy, sp), sr), m(sy, cr)), g.add(m(m(cy, sp), cr), m(sy, sr))],
        [m(sy, cp), g.add(m(m(sy, sp), sr), m(cy, cr)), g.sub(m(m(sy, sp), cr), m(cy, sr))],
        [g.op("Neg", sp), m(cp, sr), m(cp, cr)],
    ]


def _wind_axes(g: _Graph, d):
    heading = g.atan2(d[1], d[0], TINY_SPEED)
    climb = g.atan2(g.op("Neg", d[2]), g.sqrt0(g.add(g.sq(d[0]), g.sq(d[1]))), TINY_SPEED)
    return _rot(g, heading, climb, g.mul(d[0], g.num(0.0)))


def _airflow_frame(g: _Graph, v, yaw, h: float):
    """``R_WH`` of :func:`gpg.quadrotor.frames.airflow_frame` (columns x, y, z of H)."""
    if h <= 0.0:
        return _wind_axes(g, v)
    one, hh = g.num(1.0), g.num(h * h)

    def bump(s2):  # h max(1 - s2/h^2, 0)^2
        c = g.op("Max", g.sub(one, g.div(s2, hh)), g.num(0.0))
        return g.mul(g.num(h), g.sq(c))

    cy, sy = g.op("Cos", yaw), g.op("Sin", yaw)
    c = bump(g.add(g.add(g.sq(v[0]), g.sq(v[1])), g.sq(v[2])))
    d = [g.add(v[0], g.mul(c, cy)), g.add(v[1], g.mul(c, sy)), v[2]]
    dxy2 = g.add(g.sq(d[0]), g.sq(d[1]))
    n = g.sqrt0(g.add(dxy2, g.sq(d[2])))
    n = g.where(g.op("Greater", n, g.num(0.0)), n, one)
    x = [g.div(di, n) for di in d]
    c2 = bump(dxy2)
    y = [
        g.sub(g.op("Neg", d[1]), g.mul(c2, sy)),
        g.add(d[0], g.mul(c2, cy)),
        g.mul(v[2], g.num(0.0)),
    ]
    yx = g.add(g.add(g.mul(y[0], x[0]), g.mul(y[1], x[1])), g.mul(y[2], x[2]))
    y = [g.sub(yi, g.mul(yx, xi)) for yi, xi in zip(y, x, strict=True)]
    ny = g.sqrt0(g.add(g.add(g.sq(y[0]), g.sq(y[1])), g.sq(y[2])))
    ny = g.where(g.op("Greater", ny, g.num(0.0)), ny, one)
    y = [g.div(yi, ny) for yi in y]
    z = [
        g.sub(g.mul(x[1], y[2]), g.mul(x[2], y[1])),
        g.sub(g.mul(x[2], y[0]), g.mul(x[0], y[2])),
        g.sub(g.mul(x[0], y[1]), g.mul(x[1], y[0])),
    ]
    blended = [[x[i], y[i], z[i]] for i in range(3)]
    wind = _wind_axes(g, d)
    far = g.op("GreaterOrEqual", dxy2, hh)
    return [[g.where(far, wind[i][j], blended[i][j]) for j in range(3)] for i in range(3)]


def _to_airflow(g: _Graph, euler, v, h: float):
    """``(euler_H, R_WH)``: the attitude in the airflow frame and the frame, as columns."""
    rwh = _airflow_frame(g, v, euler[0], h)
    rwb = _rot(g, *euler)
    R = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(3):
            terms = [g.mul(rwh[k][i], rwb[k][j]) for k in range(3)]
            R[i][j] = g.add(g.add(terms[0], terms[1]), terms[2])
    cp = g.sqrt0(g.add(g.sq(R[0][0]), g.sq(R[1][0])))
    pitch = g.atan2(g.op("Neg", R[2][0]), cp)
    locked = g.op("Less", cp, g.num(1e-12))
    yaw = g.where(locked, g.atan2(g.op("Neg", R[0][1]), R[1][1]), g.atan2(R[1][0], R[0][0]))
    roll = g.where(locked, g.num(0.0), g.atan2(R[2][1], R[2][2]))
    return [yaw, pitch, roll], rwh


def _half_turn(g: _Graph, rpm, euler, v, eh, rwh, h: float):
    """Where the airflow comes from behind (``cos ψ_H < 0``), the state's half-turn image
    (:func:`gpg.quadrotor.frames.half_turn`): its rotor speeds, attitude, ``euler_H``, ``R_WH``."""
    back = g.op("Less", g.op("Cos", eh[0]), g.num(0.0))
    turned = [g.add(euler[0], g.num(np.pi)), g.op("Neg", euler[1]), g.op("Neg", euler[2])]
    eh_t, rwh_t = _to_airflow(g, turned, v, h)
    pick = lambda a, b: g.where(back, a, b)  # noqa: E731
    return ([pick(rpm[(i + 2) % 4], rpm[i]) for i in range(4)],
            [pick(a, b) for a, b in zip(turned, euler, strict=True)],
            [pick(a, b) for a, b in zip(eh_t, eh, strict=True)],
            [[pick(rwh_t[i][j], rwh[i][j]) for j in range(3)] for i in range(3)])  # fmt: skip


def _frame_rate(g: _Graph, euler, v, h: float):
    """:func:`gpg.quadrotor.frames.airflow_frame_rate` by central differences (N, 1)."""
    step = RATE_STEP
    # The six perturbed states stacked along the batch axis and put through one copy of the
    # frame's nodes (ONNX Runtime's cost for one state is per node, not per row), then split.
    moves = [(j, sign) for j in range(3) for sign in (1.0, -1.0)]
    v6 = [g.cat([g.add(v[a], g.num(sign * step)) if a == j else v[a] for j, sign in moves], axis=0)
          for a in range(3)]  # fmt: skip
    e6 = [g.cat([e] * len(moves), axis=0) for e in euler]
    e_all, r_all = _to_airflow(g, e6, v6, h)

    def parts(name):  # (6N, 1) -> six (N, 1), one per move
        outs = [g.name("part") for _ in moves]
        g.nodes.append(g.h.make_node("Split", [name], outs, axis=0))
        return outs

    e_parts = [parts(e) for e in e_all]
    r_parts = [[parts(r_all[a][b]) for b in range(3)] for a in range(3)]
    eh = [[e_parts[a][m] for a in range(3)] for m in range(len(moves))]
    R = [[[r_parts[a][b][m] for b in range(3)] for a in range(3)] for m in range(len(moves))]
    se, sr = g.num(0.0), g.num(0.0)
    two_pi = g.num(2 * np.pi)
    for j in range(3):
        ep, em, rp, rm = eh[2 * j], eh[2 * j + 1], R[2 * j], R[2 * j + 1]
        for a in range(3):
            t = g.sub(ep[a], em[a])
            wraps = g.op("Floor", g.div(g.add(t, g.num(np.pi)), two_pi))
            t = g.sub(t, g.mul(two_pi, wraps))
            se = g.add(se, g.sq(t))
            for b in range(3):
                sr = g.add(sr, g.sq(g.sub(rp[a][b], rm[a][b])))
    se = g.div(g.sqrt0(se), g.num(2 * step))
    sr = g.div(g.sqrt0(g.div(sr, g.num(2.0))), g.num(2 * step))
    rate = g.op("Max", se, sr)
    if h <= 0.0:
        vertical = g.op("LessOrEqual", g.add(g.sq(v[0]), g.sq(v[1])), g.num(TINY_SPEED**2))
        rate = g.where(vertical, g.num(np.inf), rate)
    return rate


def _rows(g: _Graph, s: Layout, xn, X: np.ndarray):
    """``k̄(x̂, X)`` (N, p(1+G)) in float64: values then one block per gradient dimension."""
    f64 = np.float64
    x3 = g.op("Unsqueeze", xn, g.const([1], "ax", np.int64))
    diff = g.sub(x3, g.const(X, "pts", f64))  # (N, p, D)
    scaled = g.div(diff, g.const(s.lengthscale, "ls", f64))
    r2 = g.op("ReduceSum", g.sq(scaled), g.const([2], "ax", np.int64), keepdims=0)
    k = g.mul(g.const(s.sigma, "k", f64), g.op("Exp", g.mul(g.const(-0.5, "k", f64), r2)))
    blocks = [k]
    for a in s.grad_dims:
        da = g.op("Gather", diff, g.const(np.array(a), "i", np.int64), axis=2)  # (N, p)
        blocks.append(g.mul(k, g.div(da, g.const(s.lengthscale[a] ** 2, "k", f64))))
    return g.cat(blocks)


def _onehot(g: _Graph, s: Layout, xn):
    """(N, B) 1.0 in each state's bin (:meth:`gpg.export.layout.Bins.boxes`), float64."""
    if s.bins.n_bins == 1:
        return None
    lo, hi = s.bins.boxes()
    # xn (N, D) against every box (B, D): inside where lo < x <= hi in every dimension.
    x3 = g.op("Unsqueeze", xn, g.const([1], "ax", np.int64))  # (N, 1, D)
    big = 1e300
    above = g.op("Greater", x3, g.const(np.clip(lo, -big, big), "lo", np.float64))
    below = g.op("LessOrEqual", x3, g.const(np.clip(hi, -big, big), "hi", np.float64))
    inside = g.op("Cast", g.op("And", above, below), to=DOUBLE)
    return g.op("ReduceProd", inside, axes=[2], keepdims=0)  # (N, B)


def _bin(g: _Graph, s: Layout, xn, b: int) -> list[str]:
    """Bin ``b``'s binned mean (N, M) (kinds without a global mean) and its ``‖F_b k̄‖²``
    (N, 1) (with the variance), float64, in that order."""
    bins = s.bins
    own = _rows(g, s, xn, bins.points[b])
    row = own if bins.shared is None else g.cat([_rows(g, s, xn, bins.shared), own])
    out = []
    if s.global_mean is None:
        out.append(g.op("MatMul", row, g.const(bins.coef[b].T, "bcoef", np.float64)))
    if s.has_variance:  # the product in float32, as the default model stores its factors
        fk = g.op("MatMul", g.op("Cast", row, to=FLOAT), g.const(bins.factor[b].T, "factor"))
        quad = g.op("ReduceSumSquare", fk, axes=[1], keepdims=1)
        out.append(g.op("Cast", quad, to=DOUBLE))
    return out


def _tree(g: _Graph, s: Layout, xn) -> list[str]:
    """One state's bin outputs (:func:`_bin`) through ``If`` nodes that walk the partition
    as :meth:`gpg.export.layout.Bins.lookup` does (a slab's cuts as a balanced tree): only the
    state's own bin is evaluated."""
    bins = s.bins

    def coord(d: int):  # xn[0, d] as a one-element tensor, If's condition
        return g.op("Gather", xn, g.const(np.array([d]), "i", np.int64), axis=1)

    def branch(build) -> Any:
        outer, g.nodes = g.nodes, []
        outs = build()
        nodes, g.nodes = g.nodes, outer
        info = [g.h.make_tensor_value_info(o, DOUBLE, None) for o in outs]
        return g.h.make_graph(nodes, g.name("branch"), [], info), len(outs)

    def split(d: int, value: float, left, right) -> list[str]:
        then, n = branch(left)
        other, _ = branch(right)
        names = [g.name("bin_out") for _ in range(n)]
        cond = g.op("LessOrEqual", coord(d), g.const(np.float64(value), "k", np.float64))
        g.nodes.append(g.h.make_node("If", [cond], names, then_branch=then, else_branch=other))
        return names

    if bins.n_bins == 1:
        return _bin(g, s, xn, 0)
    if bins.scheme == "slab":  # bin = number of cuts below x: x <= cut[mid] keeps bins <= mid
        d0 = int(bins.split_dim[0])

        def slab(lo: int, hi: int) -> list[str]:
            if lo == hi:
                return _bin(g, s, xn, lo)
            mid = (lo + hi) // 2
            return split(d0, float(bins.split_value[mid]),
                         lambda: slab(lo, mid), lambda: slab(mid + 1, hi))  # fmt: skip

        return slab(0, bins.n_bins - 1)

    def node(k: int) -> list[str]:
        if k < 0:
            return _bin(g, s, xn, -k - 1)
        left, right = int(bins.left[k]), int(bins.right[k])
        return split(int(bins.split_dim[k]), float(bins.split_value[k]),
                     lambda: node(left), lambda: node(right))  # fmt: skip

    return node(0)


def _gp(g: _Graph, s: Layout, xn, single: bool = False):
    """Normalised mean (N, M) and latent variance (N, 1) or None; ``single``: N = 1, the bin
    found by ``If`` nodes (:func:`_tree`) instead of every bin kept by a one-hot."""
    m = s.n_outputs
    bins = s.bins
    f64 = np.float64
    if s.global_mean is not None:  # in float64, unfolded (gpg.export.layout._global)
        gm = s.global_mean
        xl = g.mul(xn, g.const(gm["inv_ls"], "inv_ls", f64))
        xs = g.const(gm["xs"], "xs", f64)
        diff = g.sub(g.op("Unsqueeze", xl, g.const([1], "ax", np.int64)), xs)
        r2 = g.op("ReduceSum", g.sq(diff), g.const([2], "ax", np.int64), keepdims=0)
        k = g.op("Exp", g.mul(g.const(-0.5, "k", f64), r2))
        alpha = gm["alpha"]
        mean = g.op("MatMul", k, g.const(alpha[:, :m], "alpha", f64))
        for i, a in enumerate(s.grad_dims):
            da = g.op("Gather", diff, g.const(np.array(a), "i", np.int64), axis=2)  # (N, P)
            w = g.mul(k, g.mul(da, g.const(gm["inv_ls"][a], "k", f64)))
            blk = g.const(alpha[:, (1 + i) * m : (2 + i) * m], "alpha", f64)
            mean = g.add(mean, g.op("MatMul", w, blk))
        mean = g.mul(mean, g.const(gm["sigma"][0], "k", f64))
    if bins is None:
        return mean, None
    if single:
        outs = _tree(g, s, xn)
        if s.global_mean is None:
            mean, outs = outs[0], outs[1:]
        if not s.has_variance:
            return mean, None
        return mean, g.op("Cast", g.sub(g.const(s.sigma, "k", np.float64), outs[0]), to=FLOAT)
    onehot = _onehot(g, s, xn)
    means, quads = [], []
    for b in range(bins.n_bins):
        outs = _bin(g, s, xn, b)
        if s.global_mean is None:
            means.append(outs.pop(0))
        if s.has_variance:
            quads.append(outs[0])

    def select(vals):
        if onehot is None:
            return vals[0]
        out = None
        for b, v in enumerate(vals):
            term = g.mul(g.col(onehot, b), v)
            out = term if out is None else g.add(out, term)
        return out

    if s.global_mean is None:
        mean = select(means)
    if not s.has_variance:
        return mean, None
    return mean, g.op("Cast", g.sub(g.const(s.sigma, "k", np.float64), select(quads)), to=FLOAT)


# Long by design: the correction's terms in the order of gpg.export.c/correction.c, in one
# place (each a few nodes; split, the columns would travel between helpers as lists).
def _correction(g: _Graph, s: Layout, x64, xn, yn, latent):
    """A model corrected by flights (:class:`gpg.export.layout.Correction`), in float64: its
    normalised mean (N, M) and, with ``latent``, its normalised predictive variance (N, M)."""
    c = s.correction
    f64 = np.float64
    m_out = s.n_outputs

    def k64(v):
        return g.const(v, "k", f64)

    def pad(cols):  # six (N, 1) load columns, then zeros for the levels: (N, M)
        zero = g.mul(g.col(yn, 0), k64(0.0))
        return g.cat(list(cols) + [zero] * (m_out - 6))

    xc = [g.col(x64, i) for i in range(s.dim)]
    prior = [g.col(yn, j) for j in range(6)]
    mean = g.mul(yn, g.const(c.scale, "rho", f64))
    R = None if s.frame == "body" else _rot(g, xc[4], xc[5], xc[6])

    def rotate(vec):
        if R is None:
            return vec
        return [g.add(g.add(g.mul(R[i][0], vec[0]), g.mul(R[i][1], vec[1])), g.mul(R[i][2], vec[2]))
                for i in range(3)]  # fmt: skip

    ms = h = None
    if c.kappa is not None:
        u = g.op("MatMul", g.sq(g.cat(xc[:4])), g.const(s.allocation.T, "alloc", f64))
        zero = g.mul(xc[0], k64(0.0))
        f = rotate([zero, zero, g.op("Neg", g.col(u, 0))])
        t = rotate([g.col(u, j) for j in (1, 2, 3)])
        ms = [g.div(a, k64(s.y_std[i])) for i, a in enumerate(f + t)]
        mean = g.add(mean, pad(g.mul(ms[j], k64(c.kappa[j])) for j in range(6)))
    if c.beta is not None:
        if R is None:
            vb = xc[4:7]
        else:
            vb = [g.mul(R[0][i], xc[7]) for i in range(3)]
        e2 = g.add(g.sq(vb[0]), g.sq(vb[1]))
        speed = g.op("Sqrt", g.add(g.add(e2, g.sq(vb[2])), k64(1e-12)))
        zero = g.mul(xc[0], k64(0.0))
        w = [g.div(xc[i], k64(c.rpm_ref)) for i in range(4)]
        cols = []
        for a in range(3):
            f = [zero] * 3
            f[a] = g.mul(k64(-0.5 * c.air_density), g.mul(speed, vb[a]))
            cols.append(f + [zero] * 3)
        for term in range(3):
            ft, tt = [zero] * 3, [zero] * 3
            for i in range(4):
                if term == 0:
                    f = [g.op("Neg", g.mul(w[i], vb[0])), g.op("Neg", g.mul(w[i], vb[1])), zero]
                elif term == 1:
                    f = [zero, zero, g.mul(w[i], vb[2])]
                else:
                    f = [zero, zero, g.op("Neg", e2)]
                p = c.hubs[i]
                cr = [g.sub(g.mul(k64(p[1]), f[2]), g.mul(k64(p[2]), f[1])),
                      g.sub(g.mul(k64(p[2]), f[0]), g.mul(k64(p[0]), f[2])),
                      g.sub(g.mul(k64(p[0]), f[1]), g.mul(k64(p[1]), f[0]))]  # fmt: skip
                ft = [g.add(ft[a], f[a]) for a in range(3)]
                tt = [g.add(tt[a], cr[a]) for a in range(3)]
            cols.append(ft + tt)
        # h[j][t]: column t's output j, rotated to the GP's frame, normalised
        h = [[None] * len(cols) for _ in range(6)]
        for t, col in enumerate(cols):
            rot = rotate(col[:3]) + rotate(col[3:])
            for j in range(6):
                h[j][t] = g.div(rot[j], k64(s.y_std[j]))
        terms = []
        for j in range(6):
            acc = None
            for t in range(len(cols)):
                term = g.mul(h[j][t], k64(c.beta[j, t]))
                acc = term if acc is None else g.add(acc, term)
            terms.append(acc)
        mean = g.add(mean, pad(terms))
    var = None
    if latent is not None:
        lat = g.op("Max", g.op("Cast", latent, to=DOUBLE), k64(0.0))
        var = g.mul(lat, g.const(s.output_scale * c.scale**2, "w", f64))
    loads, extra, dl = [], [], []  # dl: each δ's latent variance, scaled (a tracked band's)
    for j, d in enumerate(c.deltas):
        x3 = g.op("Unsqueeze", xn, g.const([1], "ax", np.int64))
        diff = g.div(g.sub(x3, g.const(d.points, "pts", f64)), g.const(d.lengthscale, "ls", f64))
        r2 = g.op("ReduceSum", g.sq(diff), g.const([2], "ax", np.int64), keepdims=0)
        k = g.mul(k64(d.sigma), g.op("Exp", g.mul(k64(-0.5), r2)))  # (N, m)
        loads.append(g.op("MatMul", k, g.const(d.weights[:, None], "w", f64)))
        if var is None:
            continue

        def sq_norm(a):  # (N, q) -> (N, 1)
            return g.op("ReduceSum", g.sq(a), g.const([1], "ax", np.int64), keepdims=1)

        v = g.sub(k64(d.sigma), sq_norm(g.op("MatMul", k, g.const(d.whiten.T, "W", f64))))
        if d.post is not None:
            v = g.add(v, sq_norm(g.op("MatMul", k, g.const(d.post.T, "P", f64))))
        dl.append(g.mul(k64(d.output_scale), g.op("Max", v, k64(0.0))))
        e = g.add(dl[j], k64(d.output_scale * d.noise))
        if c.G is not None:
            hb = ([prior[j]] if c.with_prior else []) + ([ms[j]] if c.with_simple else [])
            r = g.sub(g.cat(hb + h[j]), g.op("MatMul", k, g.const(c.G[j], "G", f64)))
            e = g.add(e, sq_norm(g.op("MatMul", r, g.const(c.cov_chol[j], "C", f64))))
        extra.append(e)
    q0s = []  # ψᵀψ per load output where η's prior is a share of the band
    x3 = g.op("Unsqueeze", xn, g.const([1], "ax", np.int64))
    if c.online is not None:  # η at the exported state (gpg.export.layout.OnlineTerm)
        o = c.online
        etas, evs, q = zip(*(_onnx_moments(g, o, x3, j, k64) for j in range(6)), strict=True)
        q0s = list(q) if o.shared else []
        loads = [eta if not loads else g.add(loads[j], eta) for j, eta in enumerate(etas)]
        if var is not None and not o.shared:
            extra = [ev if not extra else g.add(extra[j], ev) for j, ev in enumerate(evs)]
    bank = None
    if c.bank is not None:  # the mixture at its exported state (gpg.export.layout.BankTerm)
        mixes, bank = _onnx_bank(g, c.bank, x3, k64)
        loads = [mx if not loads else g.add(loads[j], mx) for j, mx in enumerate(mixes)]
    if c.tracked is not None:  # the tracked drift at the exported state (TrackedTerm)
        loads, extra = _onnx_tracked(g, c, prior, ms, h, loads, k64, dl)
    if loads:
        mean = g.add(mean, pad(loads))
    if var is not None and c.tracked is not None:  # the loads' band: the filter's, v, δ's latent
        var = g.cat(extra + [g.col(var, i) for i in range(6, m_out)])
    elif var is not None and extra:
        var = g.add(var, pad(extra))
    if var is not None and q0s:  # after every offline part (Corrected.predictive_variance)
        band = [g.add(g.op("Max", g.sub(g.col(var, j), q0), k64(0.0)), evs[j])
                for j, q0 in enumerate(q0s)]  # fmt: skip
        var = g.cat(band + [g.col(var, i) for i in range(6, m_out)])
    if var is not None and bank is not None:  # the mixture's band, from the complete offline one
        var = g.cat([bank(j, g.col(var, j)) for j in range(6)] +
                    [g.col(var, i) for i in range(6, m_out)])  # fmt: skip
    return mean, var


def _onnx_moments(g: _Graph, o, x3, j: int, k64):
    """One online term's (:class:`gpg.export.layout.OnlineTerm`) mean, ``max(ψᵀΣψ, 0)`` and
    ``ψᵀψ`` (None unless its band is shared) for load output ``j`` at the queries ``x3``
    (N, 1, D), at its exported state: (N, 1) columns."""
    f64 = np.float64
    diff = g.div(g.sub(x3, g.const(o.Z, "pts", f64)), g.const(o.lengthscale[j], "ls", f64))
    r2 = g.op("ReduceSum", g.sq(diff), g.const([2], "ax", np.int64), keepdims=0)
    k = g.mul(k64(o.variance[j]), g.op("Exp", g.mul(k64(-0.5), r2)))
    psi = g.op("MatMul", k, g.const(o.whiten[j].T, "W", f64))  # (N, m)
    eta = g.op("MatMul", psi, g.const(o.mean[j][:, None], "mu", f64))
    q = g.mul(psi, g.op("MatMul", psi, g.const(o.cov[j], "S", f64)))
    q = g.op("ReduceSum", q, g.const([1], "ax", np.int64), keepdims=1)
    q0 = None  # read only where η's prior is a share of the band
    if o.shared:
        q0 = g.op("ReduceSum", g.sq(psi), g.const([1], "ax", np.int64), keepdims=1)
    return eta, g.op("Max", q, k64(0.0)), q0


def _onnx_bank(g: _Graph, b, x3, k64):
    """A bank (:class:`gpg.export.layout.BankTerm`) at its exported state: the mixture's mean
    per load output (six (N, 1) columns, the weights fixed at their exported values) and
    ``band(j, offline)``, output ``j``'s band from the complete offline one: ``Σ_k w_k
    band_k`` plus the spread of the members' means (``gpg.flight.Bank.band``)."""
    w = b.weights  # (K, 6)
    parts, mixes = [], []
    for j in range(6):
        mk, post, q0 = zip(*(_onnx_moments(g, o, x3, j, k64) for o in b.members), strict=True)
        mix = second = None
        for k in range(len(mk)):
            a, s2 = g.mul(mk[k], k64(w[k, j])), g.mul(g.sq(mk[k]), k64(w[k, j]))
            mix, second = (a, s2) if mix is None else (g.add(mix, a), g.add(second, s2))
        mixes.append(mix)
        parts.append((post, q0, g.op("Max", g.sub(second, g.sq(mix)), k64(0.0))))
    shared = b.members[0].shared

    def band(j, offline):
        post, q0, out = parts[j]
        for k in range(len(post)):
            each = g.op("Max", g.sub(offline, q0[k]), k64(0.0)) if shared else offline
            out = g.add(out, g.mul(g.add(each, post[k]), k64(w[k, j])))
        return out

    return mixes, band


def _onnx_tracked(g: _Graph, c, prior, ms, h, loads, k64, dl):
    """The tracked drift at its exported state: each load's mean with the members' mixture of
    ``hᵀ w̄`` added, and its band ``hᵀ Σ h`` with the members' spread plus ``v``, the labels'
    offset ``σ_o²`` and each ``δ``'s latent variance ``dl`` (six (N, 1) columns each, or none
    without the variance; ``Corrected.predictive_variance`` with a tracker)."""
    f64 = np.float64
    r, w = c.tracked, np.exp(c.tracked.log_weight)
    one = g.mul(prior[0], k64(0.0))
    new_loads, band = [], []
    for j in range(6):
        cols = [prior[j]] + ([ms[j]] if r.with_simple else []) + list(h[j])
        hj = g.cat(cols + [g.add(one, k64(r.bias[j]))])  # (N, P)
        mix = second = None
        for k in range(len(w)):
            mk = g.op("MatMul", hj, g.const(r.mean[k, j][:, None], "mu", f64))
            q = g.mul(hj, g.op("MatMul", hj, g.const(r.cov[k, j], "S", f64)))
            vk = g.op("ReduceSum", q, g.const([1], "ax", np.int64), keepdims=1)
            a, b = g.mul(mk, k64(w[k])), g.mul(g.add(vk, g.sq(mk)), k64(w[k]))
            mix, second = (a, b) if mix is None else (g.add(mix, a), g.add(second, b))
        new_loads.append(mix if not loads else g.add(loads[j], mix))
        spread = g.op("Max", g.sub(second, g.sq(mix)), k64(0.0))
        b = g.add(spread, k64(r.noise[j] + r.offset[j]))
        band.append(g.add(b, dl[j]) if dl else b)
    return new_loads, band


# Long by design: the graph from inputs to outputs in the order of Surrogate.predict's
# pipeline (clean inputs, frame, domain, GP, rotation, M, variance, outputs).
def _build(onnx, s: Layout, batch: bool = True):
    g = _Graph(onnx)
    n = "N" if batch else 1
    h = onnx.helper
    F = onnx.TensorProto.FLOAT
    inputs = {"rpm": 4, "euler": 3, "v_air": 3}
    # Non-finite inputs become zeros for the computation (outputs zero, in_domain 0 there).
    finite_in, clean = [], {}
    for name in inputs:
        ok = g.op("Not", g.op("Or", g.op("IsNaN", name), g.op("IsInf", name)))
        finite_in.append(g.op("ReduceMin", g.op("Cast", ok, to=1), axes=[1], keepdims=1))
        clean[name] = g.where(ok, name, g.num(0.0))
    finite = g.mul(g.mul(finite_in[0], finite_in[1]), finite_in[2])  # (N, 1) float 0/1
    rpm = [g.col(clean["rpm"], j) for j in range(4)]
    euler = [g.col(clean["euler"], j) for j in range(3)]
    v = [g.col(clean["v_air"], j) for j in range(3)]
    if s.frame == "body":  # the GP's frame is the body's: x = (rpm, R_WBᵀ v_air)
        rwh = _rot(g, *euler)
        v_b = [g.add(g.add(g.mul(rwh[0][i], v[0]), g.mul(rwh[1][i], v[1])), g.mul(rwh[2][i], v[2]))
               for i in range(3)]  # fmt: skip
        x = g.cat(rpm + v_b)  # (N, 7)
        # the ball |v_b| <= V, at float32's rounding of the rotation (about 1e-6 relative)
        r2 = g.add(g.add(g.sq(v_b[0]), g.sq(v_b[1])), g.sq(v_b[2]))
        steady = g.op("LessOrEqual", r2, g.num((s.ball_radius * (1.0 + 1e-9)) ** 2))
        n_box = 4  # the rotor speeds; the ball is the test of u, v, w
    else:
        eh, rwh = _to_airflow(g, euler, v, s.hover_speed)
        gp_rpm, gp_euler = rpm, euler
        if s.half_turn:
            gp_rpm, gp_euler, eh, rwh = _half_turn(g, rpm, euler, v, eh, rwh, s.hover_speed)
        speed = g.sqrt0(g.add(g.add(g.sq(v[0]), g.sq(v[1])), g.sq(v[2])))
        x = g.cat(gp_rpm + eh + [speed])  # (N, 8)
        rate = _frame_rate(g, gp_euler, v, s.hover_speed)
        steady = g.op("LessOrEqual", rate, g.num(MAX_FRAME_RATE))
        n_box = 8
    box_lo, box_hi = s.box_lo[:n_box], s.box_hi[:n_box]
    tol = 1e-9 * np.maximum(box_hi - box_lo, 1.0)
    boxed = x if n_box == s.dim else g.cat(rpm)
    inside = g.op("And", g.op("GreaterOrEqual", boxed, g.const(box_lo - tol, "box")),
                  g.op("LessOrEqual", boxed, g.const(box_hi + tol, "box")))  # fmt: skip
    ok = g.op("ReduceMin", g.op("Cast", inside, to=1), axes=[1], keepdims=1)
    spinning = g.op("Cast", g.op("GreaterOrEqual", clean["rpm"], g.num(0.0)), to=1)
    ok = g.mul(ok, g.op("ReduceMin", spinning, axes=[1], keepdims=1))
    ok = g.mul(g.mul(ok, g.op("Cast", steady, to=1)), finite)
    # The GP's mean in float64 from here (the states as given, exactly): its sum over the
    # training points cancels (|Σ k α| is a small fraction of Σ |k α|), so float32 kernel
    # values or coefficients would cost the force accuracy (see docs/measurements.md).
    x64 = g.op("Cast", x, to=DOUBLE)
    lo, half = g.const(s.x_lo, "x_lo", np.float64), g.const(s.half, "half", np.float64)
    xn = g.sub(g.div(g.sub(x64, lo), half), g.const(1.0, "k", np.float64))
    yn, latent = _gp(g, s, xn, single=not batch)
    pvn = None
    if s.correction is not None:
        yn, pvn = _correction(g, s, x64, xn, yn, latent)
    y64 = g.add(
        g.mul(yn, g.const(s.y_std, "y_std", np.float64)), g.const(s.y_mean, "y_mean", np.float64)
    )
    y = g.op("Cast", y64, to=FLOAT)
    ycol = [g.col(y, j) for j in range(s.n_outputs)]

    def rotate(R, vec):
        return [g.add(g.add(g.mul(R[i][0], vec[0]), g.mul(R[i][1], vec[1])), g.mul(R[i][2], vec[2]))
                for i in range(3)]  # fmt: skip

    force, torque = rotate(rwh, ycol[0:3]), rotate(rwh, ycol[3:6])
    if s.allocation is not None:
        u = g.op("MatMul", g.sq(clean["rpm"]), g.const(s.allocation.T, "alloc"))  # (N, 4)
        rwb = _rot(g, *euler)
        thrust = g.op("Neg", g.col(u, 0))
        force = [g.add(force[i], g.mul(rwb[i][2], thrust)) for i in range(3)]
        tb = rotate(rwb, [g.col(u, j) for j in (1, 2, 3)])
        torque = [g.add(torque[i], tb[i]) for i in range(3)]
    outs = {"force": g.cat(force), "torque": g.cat(torque)}
    outs["levels"] = g.op(
        "Slice", y, *(g.const([v_], "sl", np.int64) for v_ in (6, s.n_outputs, 1))
    )
    if latent is not None:
        w = g.const(s.output_scale * s.y_std**2, "w")
        pv = g.mul(w, g.add(g.op("Max", latent, g.num(0.0)), g.num(s.noise)))  # (N, M)
        if pvn is not None:
            pv = g.op("Cast", g.mul(pvn, g.const(s.y_std**2, "w", np.float64)), to=FLOAT)
        pc = [g.col(pv, j) for j in range(s.n_outputs)]
        R2 = [[g.sq(rwh[i][j]) for j in range(3)] for i in range(3)]
        lv = g.op("Slice", pv, *(g.const([v_], "sl", np.int64) for v_ in (6, s.n_outputs, 1)))
        outs["variance"] = g.cat(rotate(R2, pc[0:3]) + rotate(R2, pc[3:6]) + [lv])
    for val in outs.values():  # a non-finite output is not in domain
        good = g.op("Not", g.op("Or", g.op("IsNaN", val), g.op("IsInf", val)))
        ok = g.mul(ok, g.op("ReduceMin", g.op("Cast", good, to=1), axes=[1], keepdims=1))
    is_finite = g.op("Cast", finite, to=9)
    results = []
    for key, val in outs.items():
        g.nodes.append(h.make_node("Where", [is_finite, val, g.num(0.0)], [key]))
        results.append(h.make_tensor_value_info(key, F, [n, None]))
    flat = g.op("Squeeze", ok, g.const([1], "ax", np.int64))
    g.nodes.append(h.make_node("Cast", [g.op("Greater", flat, g.num(0.5))], ["in_domain"], to=9))
    results.append(h.make_tensor_value_info("in_domain", onnx.TensorProto.BOOL, [n]))
    graph = h.make_graph(
        g.nodes,
        f"gpg_{s.model}",
        [h.make_tensor_value_info(k, F, [n, d]) for k, d in inputs.items()],
        results,
        initializer=g.inits,
    )
    model = h.make_model(graph, opset_imports=[h.make_opsetid("", OPSET)], producer_name="gpg")
    model.ir_version = 8
    record = _record(s, batch)
    h.set_model_props(model, {k: str(v) for k, v in record.items()})
    model.doc_string = (
        f"gpg {record['gpg_version']} {s.model}: {record['inputs']} -> {record['outputs']}"
    )
    return model
