"""A gradient-based MPC through CasADi's ``Opti`` and IPOPT on the exported surrogate
(:func:`gpg.export.to_casadi`), the controller ``casadi`` of ``python -m experiments.mpc``.

It governs the same inner loop as gpg's MPPI: an acceleration offset ``u`` (3,) added to the
reference the geometric controller tracks. Its prediction model is that loop reduced to its
translational part, with the surrogate in it: the position loop's force command
``F = m (a_ref + u − g e_z) − K_p e_p − K_v e_v`` (without the tilt limit, which is not smooth),
the attitude that points the thrust along ``−F`` at the reference heading (assumed reached),
the rotor speeds ``M`` needs for ``|F|`` (no moment), and the vehicle's acceleration
``F_sur(rpm, euler, v − wind)/m + g e_z`` with the surrogate's world-frame force ``F_sur``
(``M`` plus the GP's residual, which the inner loop designed on ``M`` does not know about).
The offsets are linear between ``knots`` over the horizon; the states are eliminated (single
shooting, explicit Euler at the MPC's step); cost as MPPI's (position and velocity errors,
offset and its rate), plus, with ``caution`` > 0, ``β`` times the predicted standard deviation
of the force at ``caution_points`` steps. That term is either the exported variance in the NLP,
differentiated by CasADi (``caution_linearised: false``), or, by default, its first-order
model about the previous plan, as gpg's cautious MPPI takes it: before each solve the inputs
``z = (rpm, euler, v − wind)`` at those steps are rolled out from the warm start, and
``σ(z₀)`` and ``∇σ(z₀)`` come from :meth:`Surrogate.predict` through JAX, so the NLP holds
``σ(z₀) + ∇σ(z₀)ᵀ(z − z₀)``. The exact term costs CasADi's virtual machine a walk through
the variance's bins at every evaluation (1.4 s a solve at data=default in
``python -m experiments.mpc``, against 0.1 s linearised); the linearised one costs one JAX
call a solve.
IPOPT with a limited-memory Hessian, warm-started from the previous plan.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


# Long by design: the NLP in the order it is stated (model, cost, bounds, solver) and the
# solve that fills its parameters; split, the symbols would pass between the pieces.
def make_casadi_solver(sur, vehicle, ctrl, plan, c: dict[str, Any], beta: float):
    """``solve(key, x0, u_nom, t0, wind0) -> (u (H, 3), info)`` as :func:`make_solver`'s,
    with ``c`` the ``casadi`` options (dt, horizon, knots, caution_points, max_offset, the
    weights, max_iter; tol, IPOPT's tolerance, 1e-4 if absent; caution_linearised, true if
    absent)."""
    import casadi as ca

    from gpg import export

    H, dt, K = int(c["horizon"]), float(c["dt"]), int(c["knots"])
    aero = export.to_casadi(sur, variance=False, name="aero")  # the dynamics read the mean
    linear = beta > 0 and bool(c.get("caution_linearised", True))
    aero_var = export.to_casadi(sur, name="aero_var") if beta > 0 and not linear else None
    m, g = float(vehicle.mass), float(vehicle.gravity)
    kp, kv = np.asarray(ctrl.kp, float), np.asarray(ctrl.kv, float)
    a_inv = np.asarray(ctrl.alloc_inv, float)[:, 0]  # r² per newton of collective thrust
    # knots -> steps: each step's offset is a linear blend of two knots
    pos = np.linspace(0, K - 1, H)
    blend = np.zeros((H, K))
    lo = np.minimum(np.floor(pos).astype(int), K - 2)
    blend[np.arange(H), lo] = 1 - (pos - lo)
    blend[np.arange(H), lo + 1] = pos - lo
    opti = ca.Opti()
    U = opti.variable(K, 3)
    x0, wind = opti.parameter(6), opti.parameter(3)
    refs = opti.parameter(H + 1, 10)  # p, v, a, yaw at each step
    u_prev = opti.parameter(3)
    w = {k: float(c[k]) for k in ("w_position", "w_velocity", "w_control", "w_rate")}
    caution_at = sorted(set(np.linspace(1, H, int(c["caution_points"])).round().astype(int)))
    n_c = len(caution_at)
    zs = []  # the linearised caution's inputs z, and z₀, σ(z₀), ∇σ(z₀) set before each solve
    if linear:
        z0, s0, g0 = opti.parameter(10, n_c), opti.parameter(n_c), opti.parameter(10, n_c)
    p, v = x0[0:3], x0[3:6]
    cost = 0
    steps = ca.mtimes(ca.DM(blend), U)  # (H, 3)
    for k in range(H):
        r = refs[k, :].T
        u = steps[k, :].T
        F = m * (r[6:9] + u) - m * g * ca.DM([0, 0, 1]) - kp * (p - r[0:3]) - kv * (v - r[3:6])
        T = ca.sqrt(ca.sumsqr(F) + 1e-9)
        zb = -F / T
        xc = ca.vertcat(ca.cos(r[9]), ca.sin(r[9]), 0)
        yb = ca.cross(zb, xc)
        yb = yb / ca.sqrt(ca.sumsqr(yb) + 1e-12)
        xb = ca.cross(yb, zb)
        pitch = ca.atan2(-xb[2], ca.sqrt(xb[0] ** 2 + xb[1] ** 2))
        euler = ca.vertcat(ca.atan2(xb[1], xb[0]), pitch, ca.atan2(yb[2], zb[2]))
        rpm = ca.sqrt(ca.fmax(a_inv * T, 1e-6))
        out = aero(rpm, euler, v - wind)
        acc = out[0] / m + g * ca.DM([0, 0, 1])
        p, v = p + dt * v, v + dt * acc
        rn = refs[k + 1, :].T
        du = u - (u_prev if k == 0 else steps[k - 1, :].T)
        cost += w["w_position"] * ca.sumsqr(p - rn[0:3]) + w["w_velocity"] * ca.sumsqr(v - rn[3:6])
        cost += w["w_control"] * ca.sumsqr(u) + w["w_rate"] * ca.sumsqr(du)
        if beta > 0 and k + 1 in caution_at:
            if linear:
                j, z = len(zs), ca.vertcat(rpm, euler, v - wind)
                zs.append(z)
                std = s0[j] + ca.dot(g0[:, j], z - z0[:, j])
            else:
                std = ca.sqrt(ca.sum1(aero_var(rpm, euler, v - wind)[3][0:3]) + 1e-12)
            cost += beta * (H / n_c) * std
    opti.minimize(cost)
    limit = float(c["max_offset"])
    opti.subject_to(opti.bounded(-limit, ca.vec(U), limit))
    ipopt = {"print_level": 0, "max_iter": int(c["max_iter"]), "sb": "yes",
             "hessian_approximation": "limited-memory", "warm_start_init_point": "yes",
             "tol": float(c.get("tol", 1e-4))}  # fmt: skip
    opti.solver("ipopt", {"print_time": False}, ipopt)
    state = {"U": np.zeros((K, 3))}
    refs_at = jax.jit(jax.vmap(plan))
    if linear:  # the rollout's caution inputs, and σ with its gradient by JAX
        rollout = ca.Function("caution_inputs", [U, x0, wind, refs, u_prev], [ca.horzcat(*zs)])

        def sigma(z):
            var = sur.predict(z[:4], z[4:7], z[7:10]).variance[:3]
            return jnp.sqrt(jnp.sum(var) + 1e-12)

        sigma_grad = jax.jit(jax.vmap(jax.value_and_grad(sigma)))

    def solve(key, x0_flat, u_nom, t0, wind0):
        del key
        x = np.asarray(x0_flat, float)
        r = refs_at(jnp.asarray(float(t0) + dt * np.arange(H + 1)))
        rows = np.c_[np.asarray(r.p), np.asarray(r.v), np.asarray(r.a), np.asarray(r.yaw)]
        opti.set_value(x0, x[:6])
        opti.set_value(wind, np.asarray(wind0, float))
        opti.set_value(refs, np.array(rows))
        opti.set_value(u_prev, np.asarray(u_nom, float)[0])
        opti.set_initial(U, state["U"])
        if linear:
            z = np.asarray(rollout(state["U"], x[:6], np.asarray(wind0, float), rows,
                                   np.asarray(u_nom, float)[0]))  # fmt: skip
            s, g = sigma_grad(jnp.asarray(z.T))
            opti.set_value(z0, z)
            opti.set_value(s0, np.asarray(s))
            opti.set_value(g0, np.asarray(g).T)
        try:
            sol = opti.solve()
            Uk, ok = np.asarray(sol.value(U)).reshape(K, 3), True
        except RuntimeError:  # not converged in max_iter: IPOPT's last iterate, flagged
            Uk, ok = np.asarray(opti.debug.value(U)).reshape(K, 3), False
        state["U"] = Uk
        return blend @ Uk, {"converged": ok}

    return solve
