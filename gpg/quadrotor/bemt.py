"""Blade-element momentum theory for the four rotors, their interference, and airframe drag.

A reduced-order stand-in for CHARM (paper, Section "Aerodynamic and Acoustic Simulation"),
differentiable end to end. Per rotor:

* **Blade elements** on an (r, ψ) grid: local velocities ``U_T = Ωr − V·e_t`` (in-plane, normal
  to the blade) and ``U_P = V_z + v_i(r, ψ)`` (through the disk, positive down), inflow angle
  ``φ = atan2(U_P, U_T)``, angle of attack ``α = θ(r) − φ``, a smooth lift/drag polar that
  blends attached flow into flat-plate post-stall behaviour (so reversed flow on the retreating
  side is handled), Prandtl–Glauert compressibility on lift, and Prandtl's tip loss.
* **Inflow**: Glauert's momentum theory for oblique flight,
  ``T = 2ρA v₀ √(V_xy² + (V_z + v₀)² + κ² v₀²)``, solved for the mean induced velocity ``v₀``
  by a fixed number of safeguarded Newton steps (unrolled, hence differentiable), with the
  Drees linear distribution ``v_i = v₀ (1 + k_x x cos ψ_w + k_y x sin ψ_w)`` over the disk.
  The ``κ² v₀²`` term (κ² > 1/8) makes the momentum thrust strictly increasing in ``v₀``, so
  the inflow has one root also in the vortex-ring region where plain momentum theory has none
  or several: a documented regularisation, not physics; it lowers hover induced velocity by
  ``(1+κ²)^(-1/4)`` (3.4 % for κ² = 0.15).
* **Loads**: thrust, torque, in-plane H-force (along the airflow) and side force, hub roll and
  pitch moments, all from integrating the element forces; per-blade azimuthal loads for the
  unsteady-loading noise.

Between rotors: a rotor downstream of another ingests its wake. The upstream wake moves with the
in-plane airflow and sinks with the through-flow ``V_z + v₀``; where it meets the downstream
disk it adds ``κ_w · v₀,upstream · overlap`` of inflow (Gaussian overlap in the lateral and
vertical offsets, in units of R). One isolated pass gives every ``v₀``; a second pass re-solves
each rotor with the wake it ingests. Airframe drag ``−½ ρ |v| R diag(f) Rᵀ v`` acts at the
centre of mass with the drag areas ``f`` along the body axes.

Frames: body FRD; a rotor with ``spin = d`` turns about ``d·e_z``; blade azimuth ψ is measured
from body +x in the direction of rotation, ``e_r(ψ) = (cos ψ, d sin ψ, 0)``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from gpg._precision import highest
from gpg.quadrotor.vehicle import Airfoil, Rotor, Vehicle

__all__ = ["AeroResult", "BEMTConfig", "RotorLoads", "aero"]

RPM_TO_RAD_S = 2.0 * jnp.pi / 60.0
# Velocity floor (m/s) inside square roots and normalisations: keeps every expression and its
# gradient finite at zero rpm and zero airspeed; far below any physical velocity here.
_EPS_V = 1e-6


class BEMTConfig(eqx.Module):
    """Discretisation and model constants (static: changing one recompiles)."""

    n_radial: int = eqx.field(static=True, default=14)
    n_azimuth: int = eqx.field(static=True, default=24)
    # Inflow solve: Newton steps on a coarse grid, then on the full grid (see solve_inflow).
    coarse_radial: int = eqx.field(static=True, default=6)
    coarse_azimuth: int = eqx.field(static=True, default=8)
    coarse_steps: int = eqx.field(static=True, default=20)
    fine_steps: int = eqx.field(static=True, default=4)
    kappa2: float = eqx.field(static=True, default=0.15)
    mu_max: float = eqx.field(static=True, default=0.6)
    wake_gain: float = eqx.field(static=True, default=1.0)
    interference: bool = eqx.field(static=True, default=True)


class RotorLoads(eqx.Module):
    """Time-averaged loads of one rotor (body axes, about its hub) and its blade loading.

    ``thrust`` acts along −z_B; ``torque`` is the aerodynamic torque opposing rotation (> 0 when
    driven); ``force``/``moment`` are the full vectors; ``h_force`` is the in-plane force along
    the in-plane airflow (downstream), ``side_force`` the in-plane force normal to it;
    ``blade_thrust``/``blade_torque`` are one blade's loads versus azimuth ψ.
    """

    thrust: Float[Array, ""]
    torque: Float[Array, ""]
    force: Float[Array, " 3"]
    moment: Float[Array, " 3"]
    h_force: Float[Array, ""]
    side_force: Float[Array, ""]
    induced_velocity: Float[Array, ""]
    blade_thrust: Float[Array, " P"]
    blade_torque: Float[Array, " P"]


class AeroResult(eqx.Module):
    """Total aerodynamic wrench about the centre of mass and the per-rotor loads.

    ``force_B``/``torque_B`` in body axes, ``force_W``/``torque_W`` in the world (dataset) frame;
    ``rotors`` has a leading axis of 4; ``omega`` is rotor speed in rad/s.
    """

    force_B: Float[Array, " 3"]
    torque_B: Float[Array, " 3"]
    force_W: Float[Array, " 3"]
    torque_W: Float[Array, " 3"]
    rotors: RotorLoads
    omega: Float[Array, " 4"]


def polar(
    foil: Airfoil,
    sin_a: Float[Array, "..."],
    cos_a: Float[Array, "..."],
    mach: Float[Array, "..."],
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Lift and drag coefficients for any angle of attack α, given as ``(sin α, cos α)``.

    Attached flow ``C_l = a(α − α₀)/√(1 − M²)``, ``C_d = c_d0 + c_d2 (α − α_md)²``, blended by
    logistic weights centred on ±α_stall into the flat plate ``C_l = sin 2α``,
    ``C_d = c_d0 + 2 sin² α``. Working from ``(sin α, cos α)`` avoids computing ``θ − φ`` and
    its sine and cosine per blade element (the dominant cost on the CPU); α itself comes from
    the half-angle form ``α = 2 atan2(sin α, 1 + cos α)``.
    """
    alpha = 2.0 * jnp.arctan2(sin_a, 1.0 + cos_a)  # exact on (−π, π], also in reversed flow
    pg = 1.0 / jnp.sqrt(1.0 - jnp.minimum(mach**2, 0.64))
    cl_att = foil.lift_slope * (alpha - foil.alpha_zero_lift) * pg
    cd_att = foil.cd0 + foil.cd2 * (alpha - foil.alpha_min_drag) ** 2
    k = foil.stall_sharpness
    w = jax.nn.sigmoid(k * (alpha - foil.stall)) + jax.nn.sigmoid(-k * (alpha + foil.stall))
    cl_fp = 2.0 * sin_a * cos_a
    cd_fp = foil.cd0 + 2.0 * sin_a**2
    return (1.0 - w) * cl_att + w * cl_fp, (1.0 - w) * cd_att + w * cd_fp


class _Grid(eqx.Module):
    x: Float[Array, " R"]  # r/R at element midpoints
    dr: Float[Array, " R"]  # element widths (m)
    chord: Float[Array, " R"]
    sin_twist: Float[Array, " R"]
    cos_twist: Float[Array, " R"]
    cos_psi: Float[Array, " P"]
    sin_psi: Float[Array, " P"]


def radial_elements(
    rot: Rotor, n: int
) -> tuple[Float[Array, " R"], Float[Array, " R"], Float[Array, " R"]]:
    """``n`` equal blade elements from the root cut-out to the tip: midpoints ``r/R``, widths
    (m) and chords (m). Shared by the BEMT grid and the acoustics' thickness integral."""
    edges = jnp.linspace(rot.root_cutout, 1.0, n + 1)
    x = 0.5 * (edges[1:] + edges[:-1])
    return x, jnp.diff(edges) * rot.radius, jnp.interp(x, rot.stations, rot.chord)


def _grid(vehicle: Vehicle, n_radial: int, n_azimuth: int) -> _Grid:
    rot = vehicle.rotor
    x, dr, chord = radial_elements(rot, n_radial)
    psi = 2.0 * jnp.pi * jnp.arange(n_azimuth) / n_azimuth
    twist = jnp.interp(x, rot.stations, rot.twist)
    return _Grid(
        x=x,
        dr=dr,
        chord=chord,
        sin_twist=jnp.sin(twist),
        cos_twist=jnp.cos(twist),
        cos_psi=jnp.cos(psi),
        sin_psi=jnp.sin(psi),
    )


class _Elements(eqx.Module):
    """Per-element forces per unit span (N/m), shape (R, P)."""

    dT: Float[Array, "R P"]
    dFt: Float[Array, "R P"]


def _elements(
    vehicle: Vehicle,
    cfg: BEMTConfig,
    g: _Grid,
    omega: Float[Array, ""],
    spin: Float[Array, ""],
    v_in: Float[Array, " 2"],
    v_z: Float[Array, ""],
    v0: Float[Array, ""],
) -> _Elements:
    rot, rho = vehicle.rotor, vehicle.air_density
    R = rot.radius
    r = g.x * R
    # e_t = (−sin ψ, d cos ψ), e_r = (cos ψ, d sin ψ): blade motion and span directions.
    v_t = -v_in[0] * g.sin_psi + spin * v_in[1] * g.cos_psi
    v_r = v_in[0] * g.cos_psi + spin * v_in[1] * g.sin_psi
    speed_in = jnp.sqrt(v_in[0] ** 2 + v_in[1] ** 2 + _EPS_V**2)

    # Drees linear inflow. Advance and inflow ratios share a saturated reference speed so that
    # they stay bounded at low rpm (μ <= mu_max) and defined at zero rpm.
    ref = jnp.sqrt((omega * R) ** 2 + (speed_in / cfg.mu_max) ** 2)
    mu = speed_in / ref
    lam = (v_z + v0) / ref
    lam_abs = jnp.sqrt(lam**2 + _EPS_V**2)
    hyp = jnp.sqrt(mu**2 + lam**2 + _EPS_V**2)
    kx = (4.0 / 3.0) * (mu / (hyp + lam_abs) - 1.8 * mu * hyp)  # tan(χ/2) − 1.8 μ²/sin χ
    ky = -2.0 * mu
    cos_w = v_r / speed_in  # cos of the azimuth from downstream
    sin_w = -v_t / speed_in  # +1 on the advancing side
    v_i = v0 * (1.0 + kx * g.x[:, None] * cos_w[None] + ky * g.x[:, None] * sin_w[None])

    u_t = omega * r[:, None] - v_t[None, :]
    u_p = v_z + v_i
    u2 = u_t**2 + u_p**2
    u = jnp.sqrt(u2 + _EPS_V**2)
    cos_phi, sin_phi = u_t / u, u_p / u  # inflow angle φ = atan2(U_P, U_T)
    st, ct = g.sin_twist[:, None], g.cos_twist[:, None]
    cl, cd = polar(
        vehicle.airfoil,
        st * cos_phi - ct * sin_phi,  # sin(θ − φ)
        ct * cos_phi + st * sin_phi,  # cos(θ − φ)
        u / vehicle.speed_of_sound,
    )
    # Prandtl tip loss in its small-angle form f = B(1 − x)/(2λ), with the rotor's mean inflow
    # ratio floored at 0.04: from the local inflow angle it would switch off abruptly wherever
    # the through-flow changes sign, and make the inflow equation rough.
    lam_tip = jnp.sqrt(lam**2 + 0.04**2)
    f = 0.5 * rot.n_blades * (1.0 - g.x) / lam_tip
    tip = ((2.0 / jnp.pi) * jnp.arccos(jnp.exp(-f)))[:, None]
    q = 0.5 * rho * u2 * g.chord[:, None]
    lift, drag = q * cl * tip, q * cd
    return _Elements(dT=lift * cos_phi - drag * sin_phi, dFt=lift * sin_phi + drag * cos_phi)


def _bet_thrust(vehicle, cfg, g, omega, spin, v_in, v_z, v0) -> Float[Array, ""]:
    e = _elements(vehicle, cfg, g, omega, spin, v_in, v_z, v0)
    return vehicle.rotor.n_blades * jnp.mean(jnp.sum(e.dT * g.dr[:, None], axis=0))


def _momentum_thrust(vehicle, cfg, v_in, v_z, v0) -> Float[Array, ""]:
    flow = jnp.sqrt(v_in[0] ** 2 + v_in[1] ** 2 + (v_z + v0) ** 2 + cfg.kappa2 * v0**2 + _EPS_V**2)
    return 2.0 * vehicle.air_density * vehicle.rotor.disk_area * v0 * flow


def _bracketed_newton(resid, v, lo, hi, steps: int):
    """Newton steps kept inside a bracket ``[lo, hi]`` with ``resid(lo) > 0 > resid(hi)``.

    A step that would leave the bracket, or that follows a non-negative slope, is replaced by
    bisection, so the iteration cannot cycle; the bracket shrinks with the sign of every residual.
    """

    def step(carry, _):
        v, lo, hi = carry
        r, dr = jax.jvp(resid, (v,), (jnp.ones_like(v),))
        lo = jnp.where(r > 0, v, lo)
        hi = jnp.where(r > 0, hi, v)
        newton = v - r / jnp.where(dr < 0, dr, -1.0)
        ok = (dr < 0) & (newton > lo) & (newton < hi)
        return (jnp.where(ok, newton, 0.5 * (lo + hi)), lo, hi), None

    (v, lo, hi), _ = jax.lax.scan(step, (v, lo, hi), None, length=steps)
    return v, lo, hi


def _polish(resid, momentum, v, cfg: BEMTConfig):
    """Full-grid Newton steps from the coarse root, each limited to ``0.1|v₀| + 0.5`` m/s.

    Where the full-grid residual is not falling (stall), the slope of momentum thrust alone is
    used, which still points the step at the root.
    """

    def step(v, _):
        one = jnp.ones_like(v)
        r, dr = jax.jvp(resid, (v,), (one,))
        dmom = jax.jvp(momentum, (v,), (one,))[1]
        slope = jnp.where(dr < -0.1 * dmom, dr, -dmom)
        limit = 0.1 * jnp.abs(v) + 0.5
        return v + jnp.clip(-r / slope, -limit, limit), None

    v, _ = jax.lax.scan(step, v, None, length=cfg.fine_steps)
    return v


def solve_inflow(
    vehicle: Vehicle,
    cfg: BEMTConfig,
    omega: Float[Array, ""],
    spin: Float[Array, ""],
    v_in: Float[Array, " 2"],
    v_z: Float[Array, ""],
) -> Float[Array, ""]:
    """Mean induced velocity ``v₀`` (m/s, positive down) where blade-element and momentum
    thrust agree.

    A momentum-theory guess from the blade thrust at zero induced velocity, then
    ``cfg.coarse_steps`` bracketed Newton steps with the blade elements on a coarse grid, then
    ``cfg.fine_steps`` Newton steps on the full grid (the coarse grid only supplies the start;
    the answer satisfies the full-grid balance). The derivative with respect to every input is
    the implicit one of the final root.
    """
    fine = _grid(vehicle, cfg.n_radial, cfg.n_azimuth)

    def resid(grid):
        def g(v0):
            return _bet_thrust(vehicle, cfg, grid, omega, spin, v_in, v_z, v0) - _momentum_thrust(
                vehicle, cfg, v_in, v_z, v0
            )

        return g

    # The residual is positive for very negative v₀ and negative for very positive v₀ (momentum
    # thrust grows like 2ρA v₀|v₀|, blade thrust like the much smaller blade area times v₀²), so
    # ±span brackets a root; bisection keeps the cheap coarse-grid iteration from cycling.
    span = omega * vehicle.rotor.radius + jnp.sqrt(jnp.sum(v_in**2) + v_z**2) + 20.0
    coarse = _grid(vehicle, cfg.coarse_radial, cfg.coarse_azimuth)
    rho_a = 2.0 * vehicle.air_density * vehicle.rotor.disk_area
    t0 = _bet_thrust(vehicle, cfg, coarse, omega, spin, v_in, v_z, jnp.zeros(()))
    v = jnp.sign(t0) * jnp.sqrt(jnp.abs(t0) / rho_a + _EPS_V**2)
    v, _, _ = _bracketed_newton(resid(coarse), v, -span, span, cfg.coarse_steps)
    v = _polish(resid(fine), lambda w: _momentum_thrust(vehicle, cfg, v_in, v_z, w), v, cfg)
    # The iterations carry no derivative; one last Newton step does, and gives the implicit-
    # function derivative dv₀/dθ = −(∂g/∂θ)/(∂g/∂v₀) at the converged root.
    v = jax.lax.stop_gradient(v)
    r, dr = jax.jvp(resid(fine), (v,), (jnp.ones_like(v),))
    dr = jax.lax.stop_gradient(jnp.where(dr < 0, dr, -1.0))
    return v - r / dr


def rotor_loads(
    vehicle: Vehicle,
    cfg: BEMTConfig,
    omega: Float[Array, ""],
    spin: Float[Array, ""],
    v_rel: Float[Array, " 3"],
    extra_inflow: Float[ArrayLike, ""] = 0.0,
) -> RotorLoads:
    """Loads of one rotor turning at ``omega`` (rad/s) with spin ``spin`` (±1).

    ``v_rel`` is the air velocity relative to the hub in body axes; ``extra_inflow`` (m/s, down
    through the disk) is ingested wake from other rotors.
    """
    g = _grid(vehicle, cfg.n_radial, cfg.n_azimuth)
    v_in = v_rel[:2]
    v_z = v_rel[2] + extra_inflow
    v0 = solve_inflow(vehicle, cfg, omega, spin, v_in, v_z)
    e = _elements(vehicle, cfg, g, omega, spin, v_in, v_z, v0)
    B = vehicle.rotor.n_blades
    r = g.x * vehicle.rotor.radius
    dT = e.dT * g.dr[:, None]
    dFt = e.dFt * g.dr[:, None]
    blade_thrust = jnp.sum(dT, axis=0)
    blade_torque = jnp.sum(dFt * r[:, None], axis=0)
    c, s = g.cos_psi, g.sin_psi
    # Element force −dT e_z − dFt e_t; moment r e_r × force (see module docstring for axes).
    fx = jnp.sum(dFt, 0) * s
    fy = -spin * jnp.sum(dFt, 0) * c
    rt = jnp.sum(dT * r[:, None], 0)
    mx = -spin * rt * s
    my = rt * c
    force = B * jnp.stack([jnp.mean(fx), jnp.mean(fy), -jnp.mean(blade_thrust)])
    moment = B * jnp.stack([jnp.mean(mx), jnp.mean(my), -spin * jnp.mean(blade_torque)])
    speed_in = jnp.sqrt(v_in[0] ** 2 + v_in[1] ** 2 + _EPS_V**2)
    along = v_in / speed_in
    return RotorLoads(
        thrust=B * jnp.mean(blade_thrust),
        torque=B * jnp.mean(blade_torque),
        force=force,
        moment=moment,
        h_force=force[0] * along[0] + force[1] * along[1],
        side_force=-force[0] * along[1] + force[1] * along[0],
        induced_velocity=v0,
        blade_thrust=blade_thrust,
        blade_torque=blade_torque,
    )


@highest
def wake_overlap(
    vehicle: Vehicle, v_rel: Float[Array, " 3"], v0: Float[Array, " 4"]
) -> Float[Array, "4 4"]:
    """``W[i, j]``: fraction of rotor i's wake that meets rotor j's disk, in [0, 1)."""
    R = vehicle.rotor.radius
    speed_in = jnp.sqrt(v_rel[0] ** 2 + v_rel[1] ** 2 + _EPS_V**2)
    along = v_rel[:2] / speed_in
    delta = vehicle.positions[None, :, :2] - vehicle.positions[:, None, :2]  # p_j − p_i
    s = delta @ along  # downstream distance from i to j
    q2 = jnp.sum(delta**2, -1) - s**2  # squared lateral offset
    sink = s * (v_rel[2] + v0[:, None]) / speed_in  # wake centreline below the rotor plane
    w = jax.nn.sigmoid(s / (0.25 * R)) * jnp.exp(-jnp.maximum(q2, 0.0) / R**2 - (sink / R) ** 2)
    return w * (1.0 - jnp.eye(4))


@highest
def aero(
    vehicle: Vehicle,
    cfg: BEMTConfig,
    rpm: Float[ArrayLike, " 4"],
    R_WB: Float[ArrayLike, "3 3"],
    v_air_W: Float[ArrayLike, " 3"],
    omega_B: Float[ArrayLike, " 3"] | None = None,
    wake_gain: Float[ArrayLike, ""] | None = None,
) -> AeroResult:
    """Total aerodynamic wrench about the centre of mass (no gravity), and per-rotor loads.

    Each rotor is solved in isolation first; with ``cfg.interference`` each is solved again
    with the wake it ingests from the others (:func:`wake_overlap`, scaled by
    ``cfg.wake_gain``). Airframe drag ``−½ ρ |v| diag(f) v`` (body axes) is added at the centre
    of mass.

    Args:
        vehicle: the (full) vehicle: layout, rotor, airfoil, drag areas, air properties.
        cfg: the blade-element grid and the inflow solver's settings (static).
        rpm: rotor speeds r1..r4 (rpm, >= 0).
        R_WB: body-to-world rotation.
        v_air_W: airspeed vector ``v_vehicle − v_wind`` in the world frame (m/s).
        omega_B: body angular rate (rad/s); adds ``ω × p`` to each hub's velocity. None: zero.
        wake_gain: the ingested wake's gain as a (traceable) value in place of
            ``cfg.wake_gain``, for its derivative (:func:`gpg.flight.identify`). None: the
            config's.

    Returns:
        The wrench in body and world axes, the four rotors' loads (leading axis 4) and the
        rotor speeds in rad/s.
    """
    rpm = jnp.asarray(rpm)
    R_WB = jnp.asarray(R_WB)
    v_air_B = R_WB.T @ jnp.asarray(v_air_W)
    w_b = jnp.zeros(3) if omega_B is None else jnp.asarray(omega_B)
    hub_v = v_air_B[None, :] + jnp.cross(w_b[None, :], vehicle.positions)  # (4, 3)
    v_rel = -hub_v  # air relative to each hub
    omega = rpm * RPM_TO_RAD_S

    loads = jax.vmap(lambda o, d, v: rotor_loads(vehicle, cfg, o, d, v))
    rot = loads(omega, vehicle.spin, v_rel)
    if cfg.interference:
        W = wake_overlap(vehicle, -v_air_B, rot.induced_velocity)
        gain = cfg.wake_gain if wake_gain is None else wake_gain
        extra = gain * (rot.induced_velocity @ W)  # inflow ingested by each rotor j
        rot = jax.vmap(lambda o, d, v, x: rotor_loads(vehicle, cfg, o, d, v, x))(
            omega, vehicle.spin, v_rel, extra
        )

    speed = jnp.sqrt(jnp.sum(v_air_B**2) + _EPS_V**2)
    drag_B = -0.5 * vehicle.air_density * speed * vehicle.drag_area * v_air_B
    force_B = jnp.sum(rot.force, 0) + drag_B
    torque_B = jnp.sum(rot.moment + jnp.cross(vehicle.positions, rot.force), 0)
    return AeroResult(
        force_B=force_B,
        torque_B=torque_B,
        force_W=R_WB @ force_B,
        torque_W=R_WB @ torque_B,
        rotors=rot,
        omega=omega,
    )
