"""A functional quadrotor environment in gymnax's conventions, pure JAX.

``env.reset(key, params) -> (obs, state)`` and
``env.step(key, state, action, params) -> (obs, state, reward, done, info)`` with automatic
reset (a finished episode's step returns the first observation of the next one, as in gymnax;
``info["final_obs"]`` keeps the last observation of the finished one). Both are pure
functions of arrays: ``jax.jit`` them, ``jax.vmap`` them over thousands of environments (and
over ``params``), ``lax.scan`` them over time and differentiate through them (the surrogate's
derivatives are defined everywhere, :mod:`gpg.gp.binned`).

Aerodynamics: the simplified model ``M`` or a :class:`gpg.Surrogate` (any model; its mean),
behind :class:`gpg.quadrotor.dynamics.AeroModel`; the rigid body, motors and RK4 are
:class:`gpg.quadrotor.dynamics.Quadrotor`'s.

**Parameters** (:class:`EnvParams`, arrays, so a batch of environments may differ): the task
(``hover`` a random target, ``waypoints`` minimum-jerk legs through random waypoints,
``trajectory`` a random Lissajous curve), the wind (a constant mean, a sinusoidal gust and
Dryden turbulence, :mod:`gpg.envs.wind`), mass and inertia perturbations, the control rate, the
reward weights and the policy outside the surrogate's domain. Random quantities (target, wind,
gust, turbulence, mass, inertia, initial state) are drawn at every reset from the ranges in
``params`` and kept in :class:`EnvState`.

**Actions** (4,), in [−1, 1] (clipped): ``rotor_speeds`` maps each linearly onto the motor range
``[rpm_min, rpm_max]``; ``ctbr`` is a collective thrust (−1 none, +1 ``thrust_to_weight`` times
the nominal weight) and body rates (±``max_rate`` rad/s, FRD), tracked by a proportional
body-rate loop through ``M``'s allocation at every simulation step. A non-finite action is
replaced by zero, flagged ``info["bad_action"]`` and ends the episode.

**Observation** (25,), float, frames of gpg (world x forward, y right, z down; body FRD):
``[0:3]`` position error ``p − p_ref`` (m, world), ``[3:6]`` velocity error ``v − v_ref``
(m/s, world), ``[6:15]`` the attitude ``R_WB`` row by row, ``[15:18]`` body rates (rad/s, FRD),
``[18:22]`` rotor speeds relative to ``M``'s nominal hover, ``rpm / rpm_hover − 1``,
``[22:25]`` the reference acceleration (m/s², world). A vehicle hovering at its reference,
level, heading north, gives ``[0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, r, r, r, r,
0, 0, 0]`` with ``r`` the hover rotor speed's offset from ``M``'s (0 for ``M`` itself).

**Reward** per step: ``alive_bonus − w_position ‖e_p‖ − w_velocity ‖e_v‖ − w_rate ‖ω‖ −
w_action ‖a‖² − w_yaw (1 − cos ψ) − w_tilt (1 − cos tilt)``, minus ``crash_penalty`` at a
crash and ``ood_penalty`` while out of domain (norms smoothed at zero, so the reward is
differentiable everywhere).

**Termination** (``info["terminated"]``): position error beyond ``crash_distance``, tilt beyond
``max_tilt``, a non-finite state or action, or, with ``ood_terminate``, leaving the surrogate's
training domain. **Truncation** (``info["truncated"]``): ``max_steps`` steps. ``done`` is either.

**The training domain** (``info["in_domain"]``): False when any simulation step of the control
step queried the surrogate outside its training box (flying backwards into the wind, or beyond
its airspeed or attitude range): there its mean is an extrapolation. The flag is always
reported; ``ood_penalty`` and ``ood_terminate`` (off by default) turn it into a cost or an end.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from gpg._identity import ByIdentity
from gpg._precision import highest
from gpg.envs.wind import Dryden
from gpg.quadrotor.control import GeometricController, Reference, WaypointPlan, vee
from gpg.quadrotor.dynamics import (
    AeroModel,
    Quadrotor,
    SimpleAero,
    State,
    Wind,
    body_parameters,
    quat_from_euler,
)
from gpg.quadrotor.frames import matmul, safe_atan2
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle
from gpg.surrogate import Surrogate, SurrogateAero

__all__ = ["ACTIONS", "OBS_SIZE", "TASKS", "EnvParams", "EnvState", "QuadrotorEnv"]

TASKS = ("hover", "waypoints", "trajectory")
ACTIONS = ("rotor_speeds", "ctbr")
N_WAYPOINTS = 4  # the start and three random waypoints
OBS_SIZE = 25

# name: (default, lower bound, upper bound, what) of every number in EnvParams.
_PARAMS: dict[str, tuple[float, float, float, str]] = {
    "control_dt": (0.01, 1e-4, 1.0, "s per environment step"),
    "max_steps": (500, 1, 1e9, "steps per episode (truncation)"),
    "start_spread": (0.5, 0.0, 1e3, "m, largest random offset of the start from `start`"),
    "start_tilt": (0.1, 0.0, 1.0, "rad, largest initial roll and pitch"),
    "start_speed": (0.5, 0.0, 50.0, "m/s, largest initial speed per axis"),
    "target_range": (5.0, 0.0, 1e3, "m, target offset / waypoint spread / curve amplitude"),
    "leg_time": (3.0, 0.1, 1e3, "s per waypoint leg (minimum jerk)"),
    "trajectory_period": (8.0, 0.5, 1e3, "s, base period of the Lissajous curve"),
    "wind_max": (3.0, 0.0, 50.0, "m/s, largest horizontal mean wind"),
    "wind_heading": (0.0, -3.1416, 3.1416, "rad, direction the mean wind blows toward (0: +x)"),
    "wind_spread": (3.1416, 0.0, 3.1416, "rad, half-width of its random direction (π: any)"),
    "gust_max": (1.0, 0.0, 50.0, "m/s, largest sinusoidal gust amplitude"),
    "turbulence": (0.5, 0.0, 20.0, "m/s, Dryden vertical intensity σ_w (0: none)"),
    "altitude": (10.0, 1.0, 300.0, "m, altitude of Dryden's length scales"),
    "mass_spread": (0.1, 0.0, 0.9, "relative: mass times U(1 − s, 1 + s)"),
    "inertia_spread": (0.1, 0.0, 0.9, "relative: each principal moment times U(1 − s, 1 + s)"),
    "thrust_to_weight": (2.0, 1.0, 10.0, "ctbr: full-scale thrust over the nominal weight"),
    "max_rate": (3.0, 0.1, 50.0, "ctbr: full-scale body rate, rad/s"),
    "rate_gain": (8.0, 0.1, 200.0, "ctbr: body-rate loop gain, 1/s"),
    "w_position": (1.0, 0.0, 1e6, "reward weight of the position error (per m)"),
    "w_velocity": (0.1, 0.0, 1e6, "reward weight of the velocity error (per m/s)"),
    "w_rate": (0.02, 0.0, 1e6, "reward weight of the body rates (per rad/s)"),
    "w_action": (0.01, 0.0, 1e6, "reward weight of the squared action"),
    "w_yaw": (0.1, 0.0, 1e6, "reward weight of 1 − cos(yaw)"),
    "w_tilt": (0.5, 0.0, 1e6, "reward weight of 1 − cos(tilt)"),
    "alive_bonus": (1.0, -1e6, 1e6, "reward per step survived"),
    "crash_distance": (10.0, 0.01, 1e4, "m, position error that ends the episode"),
    "max_tilt": (1.2, 0.05, 3.1416, "rad, tilt that ends the episode"),
    "crash_penalty": (50.0, 0.0, 1e9, "reward lost at a crash"),
    "ood_penalty": (0.0, 0.0, 1e9, "reward lost per step outside the training domain"),
}


class EnvParams(eqx.Module):
    """The environment's parameters (see the module docstring and :data:`_PARAMS` for units):
    every field is an array, so that ``jax.vmap`` can give each environment its own. Make them
    with :meth:`create`, which checks names and ranges."""

    task: Int[Array, ""]
    start: Float[Array, " 3"]
    ood_terminate: Bool[Array, ""]
    values: dict[str, Float[Array, ""]]

    @classmethod
    def create(
        cls,
        task: str = "hover",
        *,
        start: Float[ArrayLike, " 3"] = (0.0, 0.0, -10.0),
        ood_terminate: bool = False,
        dtype: Any = jnp.float32,
        **values: float,
    ) -> EnvParams:
        """Parameters with the defaults of :data:`_PARAMS`, changed by ``values`` and checked.

        Every number becomes an array (``max_steps`` int32, the others ``dtype``), so that a
        batch of environments can be given a batch of parameters under ``jax.vmap``.

        Args:
            task: one of :data:`TASKS`: ``hover``, ``waypoints`` or ``trajectory``.
            start: the start position (m, world frame, z down): three finite numbers.
            ood_terminate: whether leaving the surrogate's training domain ends the episode.
            dtype: the floating dtype of every parameter but ``max_steps``.
            **values: parameters by their names in :data:`_PARAMS` (units and ranges there),
                e.g. ``control_dt=0.02``, ``wind_max=5.0``; the others keep their defaults.

        Returns:
            The parameters, one array per field.

        Raises:
            ValueError: for an unknown task or parameter name, a value that is not a number or
                lies outside its range, a ``max_steps`` that is not an integer, a ``start`` that
                is not three finite numbers or an ``ood_terminate`` that is not a bool, naming
                it.
        """
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; valid: {list(TASKS)}")
        unknown = sorted(set(values) - set(_PARAMS))
        if unknown:
            raise ValueError(f"unknown environment parameters {unknown}; valid: {sorted(_PARAMS)}")
        out = {}
        for name, (default, lo, hi, _) in _PARAMS.items():
            v = values.get(name, default)
            if isinstance(v, bool) or not isinstance(v, int | float | np.number):
                raise ValueError(f"{name} must be a number, got {v!r}")
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{name} must be in [{lo}, {hi}], got {v!r}")
            if name == "max_steps":
                if int(v) != v:
                    raise ValueError(f"max_steps must be an integer, got {v!r}")
                out[name] = jnp.asarray(int(v), dtype=jnp.int32)
            else:
                out[name] = jnp.asarray(v, dtype=dtype)
        s = np.asarray(start, dtype=float)
        if s.shape != (3,) or not np.all(np.isfinite(s)):
            raise ValueError(f"start must be three finite numbers (m), got {start!r}")
        if not isinstance(ood_terminate, bool | np.bool_):
            raise ValueError(f"ood_terminate must be true or false, got {ood_terminate!r}")
        return cls(
            task=jnp.asarray(TASKS.index(task), dtype=jnp.int32),
            start=jnp.asarray(s, dtype=dtype),
            ood_terminate=jnp.asarray(bool(ood_terminate)),
            values=out,
        )

    def __getattr__(self, name: str):
        values = self.__dict__.get("values", {})
        if name in values:
            return values[name]
        raise AttributeError(name)


class EnvState(eqx.Module):
    """One environment's state: the vehicle (``quad``), time and step count, what was drawn at
    reset (mass, inertia, wind, turbulence, the task's reference), the previous action and
    whether the last step stayed in the training domain."""

    quad: State
    time: Float[Array, ""]
    steps: Int[Array, ""]
    mass: Float[Array, ""]
    inertia: Float[Array, " 3"]
    wind: Wind
    turbulence: Dryden
    waypoints: Float[Array, "W 3"]  # hover: the start then the target; waypoints: the legs
    curve: Float[Array, "4 3"]  # trajectory: centre, amplitude, angular frequency, phase
    action: Float[Array, " 4"]
    in_domain: Bool[Array, ""]


class Box(eqx.Module):
    """A box space, as gymnax's ``spaces.Box``: ``low``, ``high``, ``shape``, ``dtype``."""

    low: float = eqx.field(static=True)
    high: float = eqx.field(static=True)
    shape: tuple[int, ...] = eqx.field(static=True)
    dtype: Any = eqx.field(static=True)

    def sample(self, key: PRNGKeyArray) -> Array:
        lo = max(self.low, -1e6)
        hi = min(self.high, 1e6)
        return jax.random.uniform(key, self.shape, self.dtype, lo, hi)

    def contains(self, x) -> Bool[Array, ""]:
        x = jnp.asarray(x)
        return jnp.all((x >= self.low) & (x <= self.high)) & (x.shape == self.shape)


class QuadrotorEnv(ByIdentity):
    """The environment (see the module docstring). Build with :meth:`create`."""

    aero: AeroModel
    controller: GeometricController
    mass: Float[Array, ""]
    inertia: Float[Array, " 3"]
    gravity: Float[Array, ""]
    motor_time_constant: Float[Array, ""]
    rpm_min: Float[Array, ""]
    rpm_max: Float[Array, ""]
    rpm_hover: Float[Array, ""]
    action_mode: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    dtype: str = eqx.field(static=True)

    @classmethod
    def create(
        cls,
        vehicle: Vehicle,
        aero: Surrogate | SimpleModel | AeroModel,
        *,
        simple: SimpleModel | None = None,
        action: str = "ctbr",
        substeps: int = 1,
        dtype: Any = jnp.float32,
        gains: dict[str, Any] | None = None,
    ) -> QuadrotorEnv:
        """An environment for ``vehicle`` flown on ``aero``.

        A surrogate is cast to ``dtype`` together with its ``M``: a float64 ``M`` read inside a
        float32 program would warn at every step.

        Args:
            vehicle: the rigid body, motors and rotor geometry flown.
            aero: a :class:`gpg.Surrogate` (its mean), ``M`` (a :class:`SimpleModel`) or any
                ``AeroModel``.
            simple: ``M`` for the rotor allocation and the hover speed; default the
                surrogate's own, or ``aero`` itself when it is ``M``.
            action: the action mode, one of :data:`ACTIONS`.
            substeps: RK4 steps per control step (the simulation step is
                ``control_dt / substeps``).
            dtype: the floating dtype of every array (float32 by default, the RL setting).
            gains: the gains of the geometric controller behind :meth:`geometric_action`
                (:meth:`GeometricController.create`); None for its defaults.

        Returns:
            The environment, every array in ``dtype``.

        Raises:
            ValueError: for an unknown ``action``, a ``substeps`` that is not a positive
                integer, a ``dtype`` that is not floating, an ``aero`` of another type, or no
                ``M`` to take the allocation from.
        """
        if action not in ACTIONS:
            raise ValueError(f"unknown action mode {action!r}; valid: {list(ACTIONS)}")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        dt = jnp.dtype(dtype)
        if not jnp.issubdtype(dt, jnp.floating):
            raise ValueError(f"dtype must be a floating type, got {dtype!r}")
        if isinstance(aero, Surrogate):
            aero = aero.astype(dt)  # M with it: a float64 M read in a float32 program warns
            simple = simple if simple is not None else aero.simple
            aero = SurrogateAero(aero)
        elif isinstance(aero, SimpleModel):
            simple = simple if simple is not None else aero
            aero = SimpleAero(aero)
        elif not isinstance(aero, AeroModel):
            raise ValueError(
                f"aero must be a gpg.Surrogate, a SimpleModel or an AeroModel, got "
                f"{type(aero).__name__}"
            )
        if simple is None:
            raise ValueError("pass simple= (the simplified model M): the allocation needs it")
        ctrl = GeometricController.create(vehicle, simple, gains)
        env = cls(
            aero=aero,
            controller=ctrl,
            **body_parameters(vehicle),
            rpm_hover=simple.hover_rpm(float(vehicle.weight)),
            action_mode=action,
            substeps=substeps,
            dtype=dt.name,
        )
        return _cast(env, dt)

    # -- gymnax's interface -----------------------------------------------------------------

    @property
    def default_params(self) -> EnvParams:
        """:meth:`EnvParams.create`'s defaults in the environment's dtype."""
        return EnvParams.create(dtype=self.dtype)

    @property
    def num_actions(self) -> int:
        """4: the action's size in either mode."""
        return 4

    def observation_space(self, params: EnvParams | None = None) -> Box:
        """The observation's space, as gymnax's ``observation_space``.

        Args:
            params: unused (gymnax's signature): the space is the same for all parameters.

        Returns:
            A box of shape ``(OBS_SIZE,)`` in the environment's dtype, bounds ±1e4.
        """
        return Box(-1e4, 1e4, (OBS_SIZE,), jnp.dtype(self.dtype))

    def action_space(self, params: EnvParams | None = None) -> Box:
        """The action's space, as gymnax's ``action_space``.

        Args:
            params: unused (gymnax's signature): the space is the same for all parameters.

        Returns:
            A box of shape (4,) in the environment's dtype, bounds ±1.
        """
        return Box(-1.0, 1.0, (4,), jnp.dtype(self.dtype))

    @highest
    def reset(
        self, key: PRNGKeyArray, params: EnvParams | None = None
    ) -> tuple[Float[Array, " 25"], EnvState]:
        """A new episode: everything random drawn from ``params``' ranges.

        Args:
            key: the episode's randomness (start, target or curve, wind, turbulence, mass and
                inertia).
            params: the environment's parameters; None for :attr:`default_params`.

        Returns:
            The first observation (25,) and the episode's state.

        Raises:
            ValueError: if ``params`` is neither None nor an :class:`EnvParams`.
        """
        params = self._params(params)
        return self.reset_env(key, params)

    @highest
    def step(
        self,
        key: PRNGKeyArray,
        state: EnvState,
        action: Float[Array, " 4"],
        params: EnvParams | None = None,
    ) -> tuple[Float[Array, " 25"], EnvState, Float[Array, ""], Bool[Array, ""], dict]:
        """One control step with automatic reset, as gymnax's ``step``.

        When the step ends the episode, the returned observation and state are a fresh reset's
        (drawn with a key split from ``key``), and ``info["final_obs"]`` keeps the finished
        episode's last observation.

        Args:
            key: the step's randomness (turbulence, and the reset's should the episode end).
            state: the environment's state.
            action: (4,) the action in [−1, 1] (clipped), as the action mode reads it.
            params: the environment's parameters; None for :attr:`default_params`.

        Returns:
            The observation (25,), the state, the reward, ``done`` (terminated or truncated)
            and ``info``: ``in_domain``, ``terminated``, ``truncated``, ``bad_action``,
            ``position_error``, ``discount`` and ``final_obs``.

        Raises:
            ValueError: if ``params`` is neither None nor an :class:`EnvParams`, or the action
                is not a (4,) float array.
        """
        params = self._params(params)
        key, key_reset = jax.random.split(key)
        obs_st, state_st, reward, done, info = self.step_env(key, state, action, params)
        obs_re, state_re = self.reset_env(key_reset, params)
        state = jax.tree.map(lambda a, b: jnp.where(done, a, b), state_re, state_st)
        obs = jnp.where(done, obs_re, obs_st)
        return obs, state, reward, done, {**info, "final_obs": obs_st}

    # -- the environment itself ---------------------------------------------------------------

    @highest
    def reset_env(self, key: PRNGKeyArray, params: EnvParams) -> tuple[Array, EnvState]:
        """A new episode, as gymnax's ``reset_env``: :meth:`reset` with ``params`` given.

        Start, targets and curves spread less in altitude (0.3 times the horizontal range);
        the mean wind's speed is drawn uniformly over the disc of radius ``wind_max``.

        Args:
            key: the episode's randomness.
            params: the environment's parameters.

        Returns:
            The first observation (25,) and the episode's state.
        """
        dt = jnp.dtype(self.dtype)
        ks = jax.random.split(key, 13)

        def u(k, shape=(), lo=-1.0, hi=1.0):
            return jax.random.uniform(k, shape, dt, lo, hi)

        vertical = jnp.array([1.0, 1.0, 0.3], dt)  # targets spread less in altitude
        start = params.start + params.start_spread * u(ks[0], (3,)) * vertical
        tilt = params.start_tilt * u(ks[1], (2,))
        euler = jnp.concatenate([jnp.zeros(1, dt), tilt])
        quad = State(
            p=start,
            v=params.start_speed * u(ks[2], (3,)),
            q=quat_from_euler(euler),
            w=jnp.zeros(3, dt),
            rpm=jnp.full(4, self.rpm_hover, dt),
        )
        spread = params.target_range * u(ks[3], (N_WAYPOINTS - 1, 3)) * vertical
        waypoints = jnp.concatenate([start[None], start[None] + jnp.cumsum(spread, axis=0)])
        hover = jnp.concatenate([start[None], start[None] + spread[:1]])
        waypoints = jnp.where(params.task == 0, jnp.repeat(hover[1:], N_WAYPOINTS, 0), waypoints)
        amp = params.target_range * jnp.abs(u(ks[4], (3,))) * vertical
        omega = 2.0 * jnp.pi / params.trajectory_period * jnp.array([1.0, 2.0, 1.0], dt)
        phase = u(ks[5], (3,), 0.0, 2.0 * jnp.pi)
        curve = jnp.stack([start - amp * jnp.sin(phase), amp, omega, phase])
        heading = params.wind_heading + params.wind_spread * u(ks[6], ())
        speed = params.wind_max * jnp.sqrt(u(ks[7], (), 0.0, 1.0))  # uniform over the disc
        mean = speed * jnp.stack([jnp.cos(heading), jnp.sin(heading), jnp.zeros((), dt)])
        wind = Wind(
            mean=mean,
            gust_amplitude=params.gust_max * u(ks[8], (3,), 0.0, 1.0) * vertical,
            gust_period=u(ks[9], (), 2.0, 8.0),
            gust_phase=u(ks[12], (), 0.0, 2.0 * jnp.pi),
        )
        turb = Dryden.create(ks[10], params.turbulence, params.altitude, mean, params.control_dt)
        scale = 1.0 + u(ks[11], (4,))
        state = EnvState(
            quad=quad,
            time=jnp.zeros((), dt),
            steps=jnp.zeros((), jnp.int32),
            mass=self.mass * (1.0 + params.mass_spread * (scale[0] - 1.0)),
            inertia=self.inertia * (1.0 + params.inertia_spread * (scale[1:] - 1.0)),
            wind=wind,
            turbulence=turb,
            waypoints=waypoints,
            curve=curve,
            action=jnp.zeros(4, dt),
            in_domain=jnp.asarray(True),
        )
        state = _cast(state, dt)
        return self.observation(state, params), state

    # Long by design: one environment step in the order the physics happens (wind, actions,
    # dynamics, observation, reward, termination); the state threads through every line.
    @highest
    def step_env(
        self,
        key: PRNGKeyArray,
        state: EnvState,
        action: Float[ArrayLike, " 4"],
        params: EnvParams,
    ) -> tuple[Array, EnvState, Array, Array, dict]:
        """One control step without the automatic reset, as gymnax's ``step_env``.

        The turbulence steps once, then ``substeps`` RK4 steps fly the action; the reward,
        termination and truncation are those of the module docstring. A non-finite action is
        replaced by zero and ends the episode.

        Args:
            key: the turbulence's noise for this step.
            state: the environment's state.
            action: (4,) the action in [−1, 1] (clipped), as the action mode reads it.
            params: the environment's parameters.

        Returns:
            The observation (25,), the state, the reward, ``done`` and ``info``
            (``in_domain``, ``terminated``, ``truncated``, ``bad_action``, ``position_error``,
            ``discount``).

        Raises:
            ValueError: if the action is not a (4,) float array (checked before tracing).
        """
        dt = jnp.dtype(self.dtype)
        action = self._check_action(action)
        bad = ~jnp.all(jnp.isfinite(action))
        a = jnp.where(bad, 0.0, jnp.clip(action, -1.0, 1.0)).astype(dt)
        turb = state.turbulence.step(key)
        wind = eqx.tree_at(lambda w: w.mean, state.wind, state.wind.mean + turb.velocity())
        quad = Quadrotor(
            aero=self.aero,
            mass=state.mass,
            inertia=state.inertia,
            gravity=self.gravity,
            motor_time_constant=self.motor_time_constant,
            rpm_min=self.rpm_min,
            rpm_max=self.rpm_max,
        )
        h = params.control_dt / self.substeps

        def sub(carry, i):
            s, ok = carry
            t = state.time + i.astype(dt) * h
            new, wr = quad.step(s, self.rpm_command(a, s, params), t, h, wind)
            return (new, ok & wr.in_domain), None

        (q, ok), _ = jax.lax.scan(sub, (state.quad, jnp.asarray(True)), jnp.arange(self.substeps))
        new = eqx.tree_at(
            lambda s: (s.quad, s.time, s.steps, s.turbulence, s.action, s.in_domain),
            state,
            (q, state.time + params.control_dt, state.steps + 1, turb, a, ok),
        )
        new = _cast(new, dt)
        ref = self.reference(new, params)
        e_p, e_v = q.p - ref.p, q.v - ref.v
        R = q.R
        finite = (
            jnp.all(jnp.isfinite(q.p)) & jnp.all(jnp.isfinite(q.v)) & jnp.all(jnp.isfinite(q.q))
        )
        dist = _smooth_norm(e_p)
        crash = (dist > params.crash_distance) | (R[2, 2] < jnp.cos(params.max_tilt)) | ~finite
        terminated = crash | bad | (params.ood_terminate & ~ok)
        truncated = (new.steps >= params.max_steps) & ~terminated
        yaw = safe_atan2(R[1, 0], R[0, 0])
        reward = (
            params.alive_bonus
            - params.w_position * dist
            - params.w_velocity * _smooth_norm(e_v)
            - params.w_rate * _smooth_norm(q.w)
            - params.w_action * jnp.sum(a * a)
            - params.w_yaw * (1.0 - jnp.cos(yaw))
            - params.w_tilt * (1.0 - R[2, 2])
            - params.crash_penalty * (crash | bad).astype(dt)
            - params.ood_penalty * (~ok).astype(dt)
        )
        reward = jnp.where(jnp.isfinite(reward), reward, -params.crash_penalty).astype(dt)
        done = terminated | truncated
        info = {
            "in_domain": ok,
            "terminated": terminated,
            "truncated": truncated,
            "bad_action": bad,
            "position_error": dist,
            "discount": 1.0 - terminated.astype(dt),
        }
        return self.observation(new, params), new, reward, done, info

    def reference(self, state: EnvState, params: EnvParams) -> Reference:
        """The task's reference at the state's time.

        ``hover``: the target at rest; ``waypoints``: the minimum-jerk legs through the
        waypoints, the first starting half a second in; ``trajectory``: the Lissajous curve.
        The yaw is always 0.

        Args:
            state: the environment's state (its time, waypoints and curve).
            params: the environment's parameters (the task and the leg time).

        Returns:
            The reference position, velocity, acceleration and yaw.
        """
        dt = jnp.dtype(self.dtype)
        t = state.time
        plan = WaypointPlan(
            waypoints=state.waypoints,
            start_time=jnp.asarray(0.5, dt),
            leg_time=params.leg_time,
            yaw=jnp.zeros(N_WAYPOINTS - 1, dt),
            yaw0=jnp.zeros((), dt),
        )
        legs = plan(t)
        c, amp, om, ph = state.curve
        arg = om * t + ph
        curve = Reference(
            p=c + amp * jnp.sin(arg),
            v=amp * om * jnp.cos(arg),
            a=-amp * om**2 * jnp.sin(arg),
            yaw=jnp.zeros((), dt),
        )
        hover = Reference(
            p=state.waypoints[-1], v=jnp.zeros(3, dt), a=jnp.zeros(3, dt), yaw=jnp.zeros((), dt)
        )
        pick = lambda *xs: jnp.select([params.task == 0, params.task == 1], xs[:2], xs[2])  # noqa: E731
        return jax.tree.map(pick, hover, legs, curve)

    def observation(self, state: EnvState, params: EnvParams) -> Float[Array, " 25"]:
        """The observation of ``state`` (layout and frames in the module docstring).

        Args:
            state: the environment's state.
            params: the environment's parameters (the task's reference).

        Returns:
            The (25,) observation in the environment's dtype.
        """
        ref = self.reference(state, params)
        q = state.quad
        obs = jnp.concatenate(
            [q.p - ref.p, q.v - ref.v, q.R.reshape(9), q.w, q.rpm / self.rpm_hover - 1.0, ref.a]
        )
        return obs.astype(self.dtype)

    def rpm_command(self, a: Float[Array, " 4"], s: State, params: EnvParams) -> Float[Array, " 4"]:
        """Rotor-speed commands for the action ``a`` in state ``s``.

        ``rotor_speeds`` maps each action linearly onto ``[rpm_min, rpm_max]``; ``ctbr`` turns
        the collective thrust and the body-rate command into thrust and torque (a proportional
        rate loop plus the gyroscopic term ``ω × Jω``) and allocates them through ``M``.

        Args:
            a: (4,) the clipped action.
            s: the vehicle's state (its body rates, for ``ctbr``).
            params: the environment's parameters (``thrust_to_weight``, ``max_rate``,
                ``rate_gain``).

        Returns:
            The (4,) rotor-speed commands (rpm).
        """
        if self.action_mode == "rotor_speeds":
            return self.rpm_min + 0.5 * (a + 1.0) * (self.rpm_max - self.rpm_min)
        c = self.controller
        thrust = 0.5 * (a[0] + 1.0) * self._max_thrust(params)
        w_cmd = a[1:] * params.max_rate
        tau = c.inertia * params.rate_gain * (w_cmd - s.w) + jnp.cross(s.w, c.inertia * s.w)
        return c.mix(thrust, tau)

    def geometric_action(self, state: EnvState, params: EnvParams) -> Float[Array, " 4"]:
        """The action of gpg's geometric controller (designed on ``M``) for the task's reference.

        The baseline a learned policy is compared with. ``rotor_speeds``: its rotor speeds;
        ``ctbr``: its collective thrust and the rate command ``−(K_R/K_ω) e_R`` of its attitude
        loop.

        Args:
            state: the environment's state.
            params: the environment's parameters (the task's reference and the action scales).

        Returns:
            The (4,) action in [−1, 1], in the environment's dtype.
        """
        ref = self.reference(state, params)
        c = self.controller
        s = state.quad
        if self.action_mode == "rotor_speeds":
            rpm = c(s, ref)
            return (2.0 * (rpm - self.rpm_min) / (self.rpm_max - self.rpm_min) - 1.0).astype(
                self.dtype
            )
        thrust, R_d = c.thrust_and_attitude(s, ref)
        R = s.R
        e_R = 0.5 * vee(matmul(R_d.T, R) - matmul(R.T, R_d))
        w_cmd = -(c.kR / c.kw) * e_R
        a = jnp.concatenate(
            [2.0 * thrust / self._max_thrust(params) - 1.0, w_cmd / params.max_rate]
        )
        return jnp.clip(a, -1.0, 1.0).astype(self.dtype)

    # -- helpers ---------------------------------------------------------------------------

    def _max_thrust(self, params: EnvParams):
        return params.thrust_to_weight * self.mass * self.gravity

    def _params(self, params) -> EnvParams:
        if params is None:
            return self.default_params
        if not isinstance(params, EnvParams):
            raise ValueError(f"params must be gpg.envs.EnvParams, got {type(params).__name__}")
        return params

    def _check_action(self, action) -> Array:
        """Shape and dtype are checked before tracing (they are static): ``ValueError``."""
        a = jnp.asarray(action)
        if a.shape != (4,):
            raise ValueError(
                f"action must have shape (4,) for one environment, got {a.shape}; "
                "jax.vmap the step over environments"
            )
        if not jnp.issubdtype(a.dtype, jnp.floating):
            raise ValueError(f"action must be a float array, got dtype {a.dtype}")
        return a


def _smooth_norm(v: Array, eps: float = 1e-3) -> Array:
    """``‖v‖``, smoothed at 0 so that its gradient exists there."""
    return jnp.sqrt(jnp.sum(v * v) + eps * eps) - eps


def _cast(tree, dtype):
    """Every float array of ``tree`` in ``dtype`` (the vehicle and ``M`` are float64)."""

    def cast(x):
        if isinstance(x, jax.Array | np.ndarray) and jnp.issubdtype(x.dtype, jnp.floating):
            return jnp.asarray(x, dtype=dtype)
        return x

    return jax.tree.map(cast, tree)
