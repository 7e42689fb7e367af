"""A fitted surrogate as a CasADi function (:func:`to_casadi`): the prediction in CasADi MX
symbolics with the trained arrays as constants, so that CasADi's own AD gives exact Jacobians
and Hessians to a gradient-based MPC (IPOPT, acados, do-mpc) and its code generator gives C.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from gpg.export.layout import Layout, refuse_wind, spec
from gpg.quadrotor.frames import TINY_SPEED
from gpg.surrogate import MAX_FRAME_RATE, Surrogate

if TYPE_CHECKING:
    import casadi

__all__ = ["to_casadi"]


def to_casadi(
    sur: Surrogate, *, frame: str = "world", name: str = "gpg", variance: bool = True
) -> casadi.Function:
    """``sur`` as a ``casadi.Function``: :meth:`Surrogate.predict` in CasADi.

    ``frame="body"`` returns force and torque (and their variances) in the body frame (FRD)
    for the same inputs (``v_air`` in the world frame). A body-frame surrogate (fitted on
    ``frame: body`` data) takes the same inputs: its GP reads ``(rpm, R_WBᵀ v_air)`` and its
    ``in_domain`` is the rotor box and the ball ``|R_WBᵀ v_air| <= V``. The query's bin is a
    ``casadi.conditional`` over the bins' closed forms (its derivative is the bin's own, as in
    JAX); ``in_domain`` uses CasADi's own Jacobian of the airflow frame for the frame-rate
    test, as the library uses autodiff, and does not test the outputs for being finite.
    ``casadi.Function.save`` stores the function, ``generate`` writes its C. Needs the
    ``casadi`` extra; the kinds of :func:`gpg.export.layout.spec`.

    Args:
        sur: the fitted surrogate, airflow or body frame.
        frame: ``"world"`` or ``"body"`` (FRD): the frame of the force and torque returned.
        name: the function's name.
        variance: whether to return the variance (for a model that has one).

    Returns:
        The function of ``(rpm[4], euler[3], v_air[3])`` returning ``force[3]``,
        ``torque[3]``, ``levels[K]``, with ``variance`` ``variance[6+K]``, then
        ``in_domain`` (1.0 or 0.0).

    Raises:
        ValueError: for a ``frame`` other than world or body, or a model
            :func:`gpg.export.layout.spec` refuses.
    """
    import casadi as ca

    if frame not in ("world", "body"):
        raise ValueError(f"frame must be 'world' or 'body', got {frame!r}")
    s = spec(sur, variance=variance)
    refuse_wind(s, "CasADi")
    rpm, euler, v = ca.MX.sym("rpm", 4), ca.MX.sym("euler", 3), ca.MX.sym("v_air", 3)
    if s.frame == "body":  # the GP's frame is the body's: no frame of its own, no turn rate
        rwh = _ca_rot(ca, euler[0], euler[1], euler[2])
        x = ca.vertcat(rpm, ca.mtimes(rwh.T, v))
        steady = ca.sumsqr(x[4:7]) <= (s.ball_radius * (1.0 + 1e-9)) ** 2
        n_box = 4
    else:
        x, rwh, rate = _ca_gp_frame(ca, rpm, euler, v, s.hover_speed)
        if s.half_turn:  # from behind, the state's half-turn image (frames.half_turn)
            turned = ca.vertcat(euler[0] + np.pi, -euler[1], -euler[2])
            image = _ca_gp_frame(ca, rpm[[2, 3, 0, 1]], turned, v, s.hover_speed)
            back = ca.cos(x[4]) < 0
            pairs = zip(image, (x, rwh, rate), strict=True)
            x, rwh, rate = (ca.if_else(back, a, b) for a, b in pairs)
        steady = rate <= MAX_FRAME_RATE
        n_box = 8
    lo, hi = s.box_lo, s.box_hi
    tol = 1e-9 * np.maximum(hi - lo, 1.0)
    inside = ca.MX(1)
    for i in range(n_box):
        inside = ca.logic_and(inside, ca.logic_and(x[i] >= lo[i] - tol[i], x[i] <= hi[i] + tol[i]))
    for i in range(4):
        inside = ca.logic_and(inside, rpm[i] >= 0)
    in_domain = ca.logic_and(inside, steady)
    xn = (x - ca.DM(s.x_lo)) / ca.DM(s.half) - 1
    yn, latent = _ca_gp(ca, s, xn)
    pvn = None
    if s.correction is not None:
        yn, pvn = _ca_correction(ca, s, x, xn, yn, latent)
    y = yn * ca.DM(s.y_std) + ca.DM(s.y_mean)
    R_out = ca.mtimes(_ca_rot(ca, euler[0], euler[1], euler[2]).T, rwh) if frame == "body" else rwh
    force, torque = ca.mtimes(R_out, y[0:3]), ca.mtimes(R_out, y[3:6])
    if s.allocation is not None:
        u = ca.mtimes(ca.DM(s.allocation), rpm**2)
        f_b, t_b = ca.vertcat(0, 0, -u[0]), u[1:4]
        if frame == "body":
            force, torque = force + f_b, torque + t_b
        else:
            rwb = _ca_rot(ca, euler[0], euler[1], euler[2])
            force, torque = force + ca.mtimes(rwb, f_b), torque + ca.mtimes(rwb, t_b)
    outs, names = [force, torque, y[6:]], ["force", "torque", "levels"]
    if latent is not None:
        w = ca.DM(s.output_scale * s.y_std**2)
        pv = w * (ca.fmax(latent, 0) + s.noise) if pvn is None else pvn * ca.DM(s.y_std**2)
        R2 = R_out**2
        outs.append(ca.vertcat(ca.mtimes(R2, pv[0:3]), ca.mtimes(R2, pv[3:6]), pv[6:]))
        names.append("variance")
    return ca.Function(
        name, [rpm, euler, v], outs + [in_domain], ["rpm", "euler", "v_air"], names + ["in_domain"]
    )


def _ca_gp(ca, s: Layout, xn):
    """Normalised mean (M,) and latent variance (or None) at ``xn`` (D,), MX."""
    bins = s.bins
    b = None if bins is None else _ca_lookup(ca, bins, xn)
    rows = None if bins is None else [_ca_kernel_row(ca, s, xn, i) for i in range(bins.n_bins)]
    if s.global_mean is not None:
        mean = _ca_global_mean(ca, s, xn)
    else:
        branches = [ca.mtimes(ca.DM(c), k) for c, k in zip(bins.coef, rows, strict=True)]
        mean = _ca_select(ca, b, branches)
    if not s.has_variance:
        return mean, None
    quads = [
        ca.sumsqr(ca.mtimes(ca.sparsify(ca.DM(F)), k))
        for F, k in zip(bins.factor, rows, strict=True)
    ]
    return mean, s.sigma - _ca_select(ca, b, quads)


def _ca_correction(ca, s: Layout, x, xn, yn, latent):
    """A model corrected by flights (:class:`gpg.export.layout.Correction`): its normalised mean
    and, with ``latent``, its normalised predictive variance per output (else None)."""
    c = s.correction
    prior = yn
    mean = ca.DM(c.scale) * prior
    ms = h = None
    if c.kappa is not None:
        ms = _ca_simple(ca, s, x)
        mean = mean + ca.vertcat(ca.DM(c.kappa) * ms, ca.DM.zeros(s.n_outputs - 6))
    if c.beta is not None:
        h = _ca_physical(ca, s, x)  # (6, T)
        mean = mean + ca.vertcat(ca.sum2(ca.DM(c.beta) * h), ca.DM.zeros(s.n_outputs - 6))
    var = None
    if latent is not None:
        var = ca.fmax(latent, 0) * ca.DM(s.output_scale * c.scale**2)
    loads, extra = [ca.MX(0)] * 6, [ca.MX(0)] * 6
    dl = [ca.MX(0)] * 6  # each δ's latent variance times its scale: in a tracked band
    for j, d in enumerate(c.deltas):
        m = d.points.shape[0]
        diff = (ca.repmat(xn.T, m, 1) - ca.DM(d.points)) / ca.repmat(ca.DM(d.lengthscale).T, m, 1)
        k = d.sigma * ca.exp(-0.5 * ca.sum2(diff**2))
        loads[j] = ca.dot(k, ca.DM(d.weights))
        if var is None:
            continue
        v = d.sigma - ca.sumsqr(ca.mtimes(ca.DM(d.whiten), k))
        if d.post is not None:
            v = v + ca.sumsqr(ca.mtimes(ca.DM(d.post), k))
        dl[j] = d.output_scale * ca.fmax(v, 0)
        e = dl[j] + d.output_scale * d.noise
        if c.G is not None:
            cols = ([prior[j]] if c.with_prior else []) + ([ms[j]] if c.with_simple else [])
            hb = ca.vertcat(*cols, h[j, :].T)
            r = hb - ca.mtimes(ca.DM(c.G[j]).T, k)
            e = e + ca.sumsqr(ca.mtimes(ca.DM(c.cov_chol[j]).T, r))
        extra[j] = e
    shared = [] if c.online is None else _ca_online(ca, c.online, xn, loads, extra)
    bank = None if c.bank is None else _ca_bank(ca, c.bank, xn, loads)
    if c.tracked is not None:  # the tracked drift at the exported state (TrackedTerm)
        r, w = c.tracked, np.exp(c.tracked.log_weight)
        for j in range(6):
            cols = [prior[j]] + ([ms[j]] if r.with_simple else []) + [h[j, :].T, r.bias[j]]
            hj = ca.vertcat(*cols)
            mk = [ca.dot(hj, ca.DM(r.mean[k, j])) for k in range(len(w))]
            vk = [ca.dot(hj, ca.mtimes(ca.DM(r.cov[k, j]), hj)) for k in range(len(w))]
            mix = sum(w[k] * mk[k] for k in range(len(w)))
            loads[j] = loads[j] + mix
            second = sum(w[k] * (vk[k] + mk[k] ** 2) for k in range(len(w)))
            # the loads' band: the filter's, v, the labels' offset, δ's latent (predictive_variance)
            extra[j] = ca.fmax(second - mix**2, 0) + (r.noise[j] + r.offset[j]) + dl[j]
    mean = mean + ca.vertcat(*loads, ca.DM.zeros(s.n_outputs - 6))
    if var is not None and c.tracked is not None:
        var = ca.vertcat(*extra, var[6:])
    elif var is not None:
        var = var + ca.vertcat(*extra, ca.DM.zeros(s.n_outputs - 6))
        if shared:  # after every offline part (Corrected.predictive_variance)
            band = [ca.fmax(var[j] - q0, 0) + post for j, (post, q0) in enumerate(shared)]
            var = ca.vertcat(*band, var[6:])
        if bank is not None:  # the mixture's band, from the complete offline one
            band = [bank(j, var[j]) for j in range(6)]
            var = ca.vertcat(*band, var[6:])
    return mean, var


def _ca_moments(ca, o, xn, j: int):
    """One online term's (:class:`gpg.export.layout.OnlineTerm`) mean, ``max(ψᵀΣψ, 0)`` and
    ``ψᵀψ`` for load output ``j`` at ``xn``, at its exported state."""
    m = o.Z.shape[0]
    diff = (ca.repmat(xn.T, m, 1) - ca.DM(o.Z)) / ca.repmat(ca.DM(o.lengthscale[j]).T, m, 1)
    psi = ca.mtimes(ca.DM(o.whiten[j]), o.variance[j] * ca.exp(-0.5 * ca.sum2(diff**2)))
    post = ca.fmax(ca.dot(psi, ca.mtimes(ca.DM(o.cov[j]), psi)), 0)
    return ca.dot(psi, ca.DM(o.mean[j])), post, ca.dot(psi, psi)


def _ca_online(ca, o, xn, loads: list, extra: list) -> list:
    """``η`` at the exported state (:class:`gpg.export.layout.OnlineTerm`): its mean added to
    ``loads``, its ``ψᵀΣψ`` to ``extra`` (in place); with a shared band, ``(ψᵀΣψ, ψᵀψ)`` per
    load output returned instead, to be applied after every offline part."""
    shared = []
    for j in range(6):
        mean, post, q0 = _ca_moments(ca, o, xn, j)
        loads[j] = loads[j] + mean
        if o.shared:
            shared.append((post, q0))
        else:
            extra[j] = extra[j] + post
    return shared


def _ca_bank(ca, b, xn, loads: list):
    """A bank (:class:`gpg.export.layout.BankTerm`) at its exported state: the mixture's mean
    ``Σ_k w_k η̄_k`` added to ``loads`` (in place, the weights fixed at their exported
    values); returns ``band(j, offline)``, load output ``j``'s band from the complete offline
    one: ``Σ_k w_k band_k`` plus the spread of the members' means (``gpg.flight.Bank.band``)."""
    w = b.weights  # (K, 6)
    parts = []
    for j in range(6):
        mk, post, q0 = zip(*(_ca_moments(ca, o, xn, j) for o in b.members), strict=True)
        mix = sum(w[k, j] * mk[k] for k in range(len(mk)))
        spread = ca.fmax(sum(w[k, j] * mk[k] ** 2 for k in range(len(mk))) - mix**2, 0)
        loads[j] = loads[j] + mix
        parts.append((post, q0, spread))
    shared = b.members[0].shared

    def band(j, offline):
        post, q0, spread = parts[j]
        each = [(ca.fmax(offline - q0[k], 0) if shared else offline) + post[k]
                for k in range(len(post))]  # fmt: skip
        return sum(w[k, j] * each[k] for k in range(len(each))) + spread

    return band


def _ca_simple(ca, s: Layout, x):
    """``M``'s loads in the GP's frame, normalised (:class:`gpg.flight.correction.SimpleBasis`)."""
    u = ca.mtimes(ca.DM(s.allocation), x[0:4] ** 2)
    f, t = ca.vertcat(0, 0, -u[0]), u[1:4]
    if s.frame != "body":
        R = _ca_rot(ca, x[4], x[5], x[6])
        f, t = ca.mtimes(R, f), ca.mtimes(R, t)
    return ca.vertcat(f, t) / ca.DM(s.y_std[:6])


def _ca_physical(ca, s: Layout, x):
    """The physical columns (6, T) in the GP's frame, normalised
    (:class:`gpg.flight.basis.PhysicalBasis`)."""
    c = s.correction
    if s.frame == "body":
        R, vb = ca.DM.eye(3), x[4:7]
    else:
        R = _ca_rot(ca, x[4], x[5], x[6])
        vb = R[0, :].T * x[7]
    speed = ca.sqrt(ca.sumsqr(vb) + 1e-12)
    w = x[0:4] / c.rpm_ref
    zero = ca.MX.zeros(3, 1)
    cols = []
    for a in range(3):
        e = ca.DM.zeros(3, 1)
        e[a] = 1.0
        cols.append(ca.vertcat(-0.5 * c.air_density * speed * vb[a] * e, zero))
    e2 = vb[0] ** 2 + vb[1] ** 2
    for term in range(3):
        f_tot, t_tot = zero, zero
        for i in range(4):
            if term == 0:
                f = ca.vertcat(-w[i] * vb[0], -w[i] * vb[1], 0)
            elif term == 1:
                f = ca.vertcat(0, 0, w[i] * vb[2])
            else:
                f = ca.vertcat(0, 0, -e2)
            f_tot = f_tot + f
            t_tot = t_tot + ca.cross(ca.DM(c.hubs[i]), f)
        cols.append(ca.vertcat(f_tot, t_tot))
    out = ca.horzcat(*cols)  # (6, T), body frame
    out = ca.vertcat(ca.mtimes(R, out[0:3, :]), ca.mtimes(R, out[3:6, :]))
    return out / ca.repmat(ca.DM(s.y_std[:6]), 1, len(cols))


def _ca_select(ca, b, branches):
    if len(branches) == 1:
        return branches[0]
    return ca.conditional(b, branches, branches[0], True)


def _ca_lookup(ca, bins, xn):
    """The bin index as MX: the sum of each bin's index times whether its box holds ``xn``."""
    if bins.n_bins == 1:
        return ca.MX(0)
    lo, hi = bins.boxes()
    out = 0
    for i in range(bins.n_bins):
        inside = ca.MX(1)
        for d in range(bins.dim):
            if np.isfinite(lo[i, d]):
                inside = ca.logic_and(inside, xn[d] > lo[i, d])
            if np.isfinite(hi[i, d]):
                inside = ca.logic_and(inside, xn[d] <= hi[i, d])
        out = out + i * inside
    return out


def _ca_rows(ca, s: Layout, xn, X: np.ndarray):
    p = X.shape[0]
    diff = ca.repmat(xn.T, p, 1) - ca.DM(X)  # (p, D)
    k = s.sigma * ca.exp(-0.5 * ca.sum2((diff / ca.repmat(ca.DM(s.lengthscale).T, p, 1)) ** 2))
    grads = [k * diff[:, a] / s.lengthscale[a] ** 2 for a in s.grad_dims]
    return ca.vertcat(k, *grads)


def _ca_kernel_row(ca, s: Layout, xn, b: int):
    """``k̄(x̂, X_b)``: shared rows, then bin ``b``'s own (:func:`gpg.export.layout.kernel_row`)."""
    own = _ca_rows(ca, s, xn, s.bins.points[b])
    return own if s.bins.shared is None else ca.vertcat(_ca_rows(ca, s, xn, s.bins.shared), own)


def _ca_global_mean(ca, s: Layout, xn):
    """The folded global mean of :mod:`gpg.gp.mean` (normalised), in MX with DM constants."""
    gm = s.global_mean
    inv_ls = gm["inv_ls"]
    xl = xn * ca.DM(inv_ls)
    XS = ca.DM(gm["xs"])
    n = gm["xs"].shape[0]
    r2 = ca.sum2((ca.repmat(xl.T, n, 1) - XS) ** 2)
    acc = ca.mtimes(ca.DM(gm["coef"]).T, ca.exp(-0.5 * r2))
    m = s.n_outputs
    mu = acc[0:m]
    for i, a in enumerate(s.grad_dims):
        mu = mu + xn[a] * inv_ls[a] ** 2 * acc[(1 + i) * m : (2 + i) * m]
    return float(gm["sigma"][0]) * mu


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


def _ca_gp_frame(ca, rpm, euler, v, h):
    """The GP's input ``x_H``, ``R_WH`` and the airflow frame's turn rate (CasADi's Jacobian
    of the frame and the angles in the air velocity)."""
    euler_h, rwh = _ca_airflow(ca, euler, v, h)
    d_euler = ca.jacobian(euler_h, v)
    d_frame = ca.jacobian(ca.vec(rwh), v)
    rate = ca.fmax(ca.norm_fro(d_euler), ca.norm_fro(d_frame) / np.sqrt(2.0))
    if h <= 0.0:
        rate = ca.if_else(v[0] ** 2 + v[1] ** 2 <= TINY_SPEED**2, ca.inf, rate)
    return ca.vertcat(rpm, euler_h, _ca_norm(ca, v)), rwh, rate


def _ca_wind_axes(ca, d):
    heading = _ca_safe_atan2(ca, d[1], d[0], TINY_SPEED)
    climb = _ca_safe_atan2(ca, -d[2], _ca_norm(ca, d[0:2]), TINY_SPEED)
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
