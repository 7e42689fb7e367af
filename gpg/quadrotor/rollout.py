"""Closed-loop simulation in ``lax.scan``, single and batched (RL-style) rollouts.

:func:`simulate` flies one vehicle through a :class:`~gpg.quadrotor.control.WaypointPlan`
with the geometric controller and returns the trajectory; :func:`batched_rollouts` vmaps it
over environments with randomised wind and waypoints, the way an RL training loop would roll
out many environments at once.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from gpg._deprecated import deprecated
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import Quadrotor, State, Wind
from gpg.quadrotor.frames import euler_from_R

__all__ = ["Trace", "batched_rollouts", "random_scenario", "simulate"]


class Trace(eqx.Module):
    """Per-step records of a rollout (leading axis: time; batched rollouts add one in front)."""

    t: Float[Array, " T"]
    p: Float[Array, "T 3"]
    v: Float[Array, "T 3"]
    euler: Float[Array, "T 3"]
    rpm: Float[Array, "T 4"]
    rpm_cmd: Float[Array, "T 4"]
    ref_p: Float[Array, "T 3"]
    force: Float[Array, "T 3"]
    levels: Float[Array, "T K"]
    in_domain: Bool[Array, " T"]

    @property
    def noise(self) -> Float[Array, "T K"]:
        """Deprecated name of :attr:`levels`."""
        deprecated("Trace.noise", "Trace.levels")
        return self.levels


def simulate(
    quad: Quadrotor,
    ctrl: GeometricController,
    plan: WaypointPlan,
    wind: Wind,
    s0: State,
    dt: float,
    n_steps: int,
) -> tuple[State, Trace]:
    """Fly ``n_steps`` steps of ``dt`` seconds from ``s0``; jittable and vmappable.

    Each step asks the plan for the reference at ``t = k dt``, the controller for the rotor
    commands, and advances the quadrotor by one RK4 step (:meth:`Quadrotor.step`).

    Args:
        quad: the rigid body, motors and aerodynamics.
        ctrl: the controller.
        plan: the reference trajectory.
        wind: the wind.
        s0: the initial state.
        dt: the step (s).
        n_steps: the number of steps (static).

    Returns:
        The final state, and the :class:`Trace` of every step (the state at the step's start,
        the command and the wrench it met).
    """

    def step(s: State, k):
        t = k * dt
        ref = plan(t)
        cmd = ctrl(s, ref)
        new, wr = quad.step(s, cmd, t, dt, wind)
        rec = Trace(
            t=t,
            p=s.p,
            v=s.v,
            euler=euler_from_R(s.R),
            rpm=s.rpm,
            rpm_cmd=cmd,
            ref_p=ref.p,
            force=wr.force,
            levels=wr.levels,
            in_domain=wr.in_domain,
        )
        return new, rec

    return jax.lax.scan(step, s0, jnp.arange(n_steps, dtype=float))


def random_scenario(
    key: PRNGKeyArray,
    start: Float[Array, " 3"],
    *,
    target_range: float = 10.0,
    wind_max: float = 5.0,
    gust_max: float = 2.0,
    leg_time: float = 5.0,
) -> tuple[WaypointPlan, Wind]:
    """One randomised environment: a target, a wind and a gust drawn from ``key``.

    A target within ``target_range`` m horizontally (±30 % of it vertically) reached in one
    minimum-jerk leg, a horizontal wind up to ``wind_max`` m/s and a gust up to ``gust_max``
    m/s with a 2–8 s period.

    Args:
        key: the random key.
        start: (3,) the start position (m, world frame); the plan starts there.
        target_range: the largest horizontal offset of the target per axis (m).
        wind_max: the largest horizontal mean wind per axis (m/s).
        gust_max: the largest gust amplitude per axis (m/s; the vertical one scaled by 0.3).
        leg_time: the duration of the leg (s).

    Returns:
        The plan (one leg, the nose along it) and the wind.
    """
    k1, k2, k3, k4, k5 = jax.random.split(key, 5)
    horiz = jax.random.uniform(k1, (2,), minval=-target_range, maxval=target_range)
    vert = jax.random.uniform(k2, (), minval=-0.3 * target_range, maxval=0.3 * target_range)
    target = start + jnp.concatenate([horiz, vert[None]])
    d = target - start
    plan = WaypointPlan(
        waypoints=jnp.stack([start, target]),
        start_time=jnp.asarray(0.5),
        leg_time=jnp.asarray(leg_time),
        yaw=jnp.arctan2(d[1], d[0])[None],
        yaw0=jnp.asarray(0.0),
    )
    wind = Wind(
        mean=jnp.concatenate(
            [jax.random.uniform(k3, (2,), minval=-wind_max, maxval=wind_max), jnp.zeros(1)]
        ),
        gust_amplitude=jax.random.uniform(k4, (3,), minval=0.0, maxval=gust_max)
        * jnp.array([1.0, 1.0, 0.3]),
        gust_period=jax.random.uniform(k5, (), minval=2.0, maxval=8.0),
        gust_phase=jnp.asarray(0.0),
    )
    return plan, wind


def batched_rollouts(
    quad: Quadrotor,
    ctrl: GeometricController,
    key: PRNGKeyArray,
    s0: State,
    *,
    n_envs: int,
    n_steps: int,
    dt: float,
    **scenario: float,
) -> tuple[State, Trace]:
    """``n_envs`` environments with randomised targets and wind, vmapped.

    Args:
        quad: the rigid body, motors and aerodynamics, shared by every environment.
        ctrl: the controller, shared.
        key: the random key, split into one per environment.
        s0: the initial state, shared; the targets are drawn around its position.
        n_envs: the number of environments.
        n_steps: the number of steps of each.
        dt: the step (s).
        **scenario: options of :func:`random_scenario` (``target_range``, ``wind_max``,
            ``gust_max``, ``leg_time``).

    Returns:
        The final states and the traces, each with a leading axis of ``n_envs``.
    """
    keys = jax.random.split(key, n_envs)

    def one(k):
        plan, wind = random_scenario(k, s0.p, **scenario)
        return simulate(quad, ctrl, plan, wind, s0, dt, n_steps)

    return jax.vmap(one)(keys)
