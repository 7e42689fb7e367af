"""Model-predictive control with the surrogate: flat dynamics, linearisation with the variance,
and a sampling-based MPPI solver in JAX.

**Flat dynamics** in the convention of trajax and JAX MPPI codes, ``x_next = dynamics(x, u, t)``:
``x`` (17,) packs :class:`gpg.quadrotor.dynamics.State` as ``[p (3), v (3), q (4, w x y z),
ω (3), rpm (4)]`` (world NED, body FRD; :func:`pack`, :func:`unpack`), ``u`` (4,) are rotor-speed
commands (rpm), ``t`` the time (s); one RK4 step of ``dt`` with the aerodynamic model (a
:class:`gpg.Surrogate`'s mean, or ``M``) held over the step, as in
:class:`gpg.quadrotor.dynamics.Quadrotor`.

**Linearisation** (:meth:`Dynamics.linearize`): the next state, ``A = ∂x_next/∂x`` and
``B = ∂x_next/∂u`` (forward-mode autodiff through the surrogate), the surrogate's predictive
variance of the aerodynamic force and moment at ``(x, u)`` (body frame) and its Jacobian in
``x`` and ``u``, and the variance this adds to the next state (velocity and body rates, in a
diagonal approximation): what cautious MPC propagates, ``Σ_{k+1} = A Σ_k Aᵀ + diag(q_k)``
(:func:`propagate`).

**MPPI** (:class:`MPPI`, Williams et al. 2017): ``samples`` perturbed control sequences are
rolled out with any flat dynamics, weighted by ``exp(−cost/temperature)``, and averaged into
the next nominal sequence; one jitted call per control step, warm-started from the previous
solution. The cost is any function of the rolled-out states and controls, so a variance term
(caution) enters through the cost (see ``experiments.runs.mpc`` for the example).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from gpg._identity import ByIdentity
from gpg._precision import highest
from gpg.quadrotor.dynamics import AeroModel, Quadrotor, SimpleAero, State, Wind
from gpg.quadrotor.frames import euler_from_R, matvec
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle
from gpg.surrogate import Surrogate, SurrogateAero, predict_state

__all__ = ["STATE_SIZE", "MPPI", "Dynamics", "Linearization", "pack", "propagate", "unpack"]

STATE_SIZE = 17


def pack(s: State) -> Float[Array, " 17"]:
    """A :class:`State` as the flat vector ``[p, v, q, ω, rpm]``.

    Args:
        s: the vehicle's state.

    Returns:
        The (17,) flat state.
    """
    return jnp.concatenate([s.p, s.v, s.q, s.w, s.rpm])


def unpack(x: Float[Array, " 17"]) -> State:
    """The flat vector ``[p, v, q, ω, rpm]`` as a :class:`State`.

    The quaternion is normalised, so that a state moved by an optimiser off the unit sphere
    still reads as a rotation.

    Args:
        x: the (17,) flat state.

    Returns:
        The vehicle's state, ``q`` normalised.

    Raises:
        ValueError: if the last axis of ``x`` is not of size 17.
    """
    x = jnp.asarray(x)
    if x.shape[-1:] != (STATE_SIZE,):
        raise ValueError(f"a flat state has {STATE_SIZE} entries, got shape {x.shape}")
    q = x[6:10]
    return State(p=x[:3], v=x[3:6], q=q / jnp.linalg.norm(q), w=x[10:13], rpm=x[13:17])


class Linearization(eqx.Module):
    """:meth:`Dynamics.linearize`'s result at one ``(x, u, t)``."""

    x_next: Float[Array, " 17"]
    A: Float[Array, "17 17"]
    B: Float[Array, "17 4"]
    variance: Float[Array, " 6"]  # force (N²) and moment (N²·m²) in the body frame
    dvariance_dx: Float[Array, "6 17"]
    dvariance_du: Float[Array, "6 4"]
    state_variance: Float[Array, " 17"]  # added to x_next's variance by the model's uncertainty


class Dynamics(ByIdentity):
    """One RK4 step of a vehicle flown on an aerodynamic model, flat (see the module docstring).

    ``quad`` the rigid body with its aerodynamics, ``wind`` the wind it flies in (known to the
    model: a measured or forecast wind), ``dt`` the step (s), ``surrogate`` the surrogate whose
    variance :meth:`linearize` reports (None for ``M``: variance zero).
    """

    quad: Quadrotor
    wind: Wind
    dt: float = eqx.field(static=True)
    surrogate: Surrogate | None = None

    @classmethod
    def create(
        cls,
        vehicle: Vehicle,
        aero: Surrogate | SimpleModel | AeroModel,
        dt: float,
        *,
        wind: Wind | None = None,
    ) -> Dynamics:
        """Dynamics of ``vehicle`` flown on ``aero``, one RK4 step of ``dt`` per call.

        Args:
            vehicle: the rigid body and motors.
            aero: a :class:`gpg.Surrogate` (its mean; its variance for :meth:`variance`),
                ``M`` or any ``AeroModel`` (variance zero).
            dt: the step (s), a positive number.
            wind: the wind the vehicle flies in, known to the model; None for calm air.

        Returns:
            The flat dynamics.

        Raises:
            ValueError: if ``dt`` is not a positive number or ``aero`` is of another type.
        """
        if not (isinstance(dt, int | float) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        sur = aero if isinstance(aero, Surrogate) else None
        if isinstance(aero, Surrogate):
            aero = SurrogateAero(aero)
        elif isinstance(aero, SimpleModel):
            aero = SimpleAero(aero)
        elif not isinstance(aero, AeroModel):
            raise ValueError(f"aero must be a Surrogate, SimpleModel or AeroModel, got {aero!r}")
        quad = Quadrotor.from_vehicle(vehicle, aero)
        return cls(
            quad=quad, wind=Wind.calm() if wind is None else wind, dt=float(dt), surrogate=sur
        )

    @highest
    def __call__(
        self, x: Float[Array, " 17"], u: Float[Array, " 4"], t: Float[Array, ""]
    ) -> Float[Array, " 17"]:
        """``x_next`` after one step of ``dt`` from ``x`` under rotor commands ``u`` at ``t``.

        Args:
            x: the (17,) flat state.
            u: (4,) rotor-speed commands (rpm).
            t: the time (s) at the start of the step.

        Returns:
            The (17,) flat state one step later.

        Raises:
            ValueError: if ``x`` or ``u`` is not a float array of its shape.
        """
        x, u = _check(x, u)
        new, _ = self.quad.step(unpack(x), u, jnp.asarray(t, x.dtype), self.dt, self.wind)
        return pack(new)

    @highest
    def variance(
        self, x: Float[Array, " 17"], u: Float[Array, " 4"], t: Float[ArrayLike, ""]
    ) -> Float[Array, " 6"]:
        """The surrogate's predictive variance of the aerodynamic force and moment.

        Evaluated where the step from ``(x, u)`` starts: the state's rotor speeds, attitude
        and airspeed (``u`` is checked but not read: the motors lag the command).

        Args:
            x: the (17,) flat state.
            u: (4,) rotor-speed commands (rpm).
            t: the time (s), for the wind.

        Returns:
            (6,) the variance of force (N²) and moment (N²·m²), body frame; zeros without a
            surrogate.

        Raises:
            ValueError: if ``x`` or ``u`` is not a float array of its shape.
        """
        x, u = _check(x, u)
        if self.surrogate is None:
            return jnp.zeros(6, x.dtype)
        s = unpack(x)
        v_air = s.v - self.wind(jnp.asarray(t, x.dtype))
        p = predict_state(self.surrogate, s.rpm, euler_from_R(s.R), v_air, True, body=True)
        return p.variance[:6]

    @highest
    def linearize(
        self, x: Float[Array, " 17"], u: Float[Array, " 4"], t: Float[Array, ""]
    ) -> Linearization:
        """The step linearised at ``(x, u, t)``, with the model's variance and its Jacobians.

        Forward-mode autodiff (jit it, vmap it over a horizon). The variance added to the next
        state is a diagonal approximation: the velocity's is the world-frame diagonal of
        ``R diag(σ_F²) Rᵀ`` over ``m²``, the body rates' ``σ_τ²/J²``, each times ``dt²``.

        Args:
            x: the (17,) flat state.
            u: (4,) rotor-speed commands (rpm).
            t: the time (s).

        Returns:
            The next state, ``A``, ``B``, the variance, its Jacobians in ``x`` and ``u`` and
            the state variance it adds.

        Raises:
            ValueError: if ``x`` or ``u`` is not a float array of its shape.
        """
        x, u = _check(x, u)
        x_next, (A, B) = _value_and_jacfwd(lambda a, b: self(a, b, t), x, u)
        var, (dvx, dvu) = _value_and_jacfwd(lambda a, b: self.variance(a, b, t), x, u)
        s = unpack(x)
        R = s.R
        dt2 = self.dt**2
        # Velocity: the world-frame diagonal of R diag(σ_F²) Rᵀ over m²; rates: σ_τ²/J².
        var_v = matvec(R * R, var[:3]) / self.quad.mass**2
        var_w = var[3:6] / self.quad.inertia**2
        zeros = jnp.zeros
        q = jnp.concatenate([zeros(3), dt2 * var_v, zeros(4), dt2 * var_w, zeros(4)])
        return Linearization(x_next, A, B, var, dvx, dvu, q.astype(x.dtype))


@highest
def propagate(
    lin: Linearization, sigma0: Float[Array, "17 17"] | None = None
) -> Float[Array, "H 17 17"]:
    """State covariances along a horizon: ``Σ_{k+1} = A_k Σ_k A_kᵀ + diag(q_k)``.

    The tube that cautious MPC tightens its constraints with (Hewing et al. 2020).

    Args:
        lin: linearisations with a leading axis H (:meth:`Dynamics.linearize` vmapped over
            the horizon); ``q_k`` is their ``state_variance``.
        sigma0: the (17, 17) initial covariance; None for zero.

    Returns:
        (H, 17, 17) the covariances after each step.
    """
    n = lin.A.shape[-1]
    s0 = jnp.zeros((n, n), lin.A.dtype) if sigma0 is None else sigma0

    def step(S, k):
        A, q = k
        S = A @ S @ A.T + jnp.diag(q)
        return S, S

    return jax.lax.scan(step, s0, (lin.A, lin.state_variance))[1]


class MPPI(ByIdentity):
    """Model-predictive path integral control over any flat dynamics.

    ``dynamics(x, u, t) -> x_next``; ``cost(xs, us, ts) -> ()`` of one rolled-out sequence
    (states after each control, (H, n); controls (H, m); times (H,)); ``horizon`` H and
    ``samples`` K (static); ``noise_std`` (m,) of the control perturbations; ``temperature``
    λ of the weights ``exp(−(S − min S)/λ)``; ``u_min``/``u_max`` the control box; ``dt`` the
    time per control; ``knots`` (static): perturbations drawn at that many evenly spaced
    controls and interpolated linearly between them (smooth samples, a smaller search space;
    None: independent at every control).
    """

    dynamics: Callable
    cost: Callable
    noise_std: Float[Array, " m"]
    u_min: Float[Array, " m"]
    u_max: Float[Array, " m"]
    temperature: float = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    horizon: int = eqx.field(static=True)
    samples: int = eqx.field(static=True)
    knots: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.knots is not None and not 2 <= self.knots <= self.horizon:
            raise ValueError(f"knots must be in [2, horizon], got {self.knots}")
        if self.horizon < 1 or self.samples < 2:
            raise ValueError(
                f"MPPI needs horizon >= 1 and samples >= 2, got {self.horizon}, {self.samples}"
            )
        if not self.temperature > 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}")

    @highest
    def rollout(
        self, x0: Float[Array, " n"], us: Float[Array, "H m"], t0: Float[ArrayLike, ""]
    ) -> tuple[Float[Array, "H n"], Float[Array, " H"]]:
        """One control sequence rolled out through the dynamics.

        Args:
            x0: (n,) the initial state.
            us: (H, m) the controls, one per ``dt``.
            t0: the initial time (s).

        Returns:
            The states after each control (H, n) and the times of the controls (H,).
        """
        ts = t0 + self.dt * jnp.arange(self.horizon, dtype=x0.dtype)

        def step(x, ut):
            u, t = ut
            x = self.dynamics(x, u, t)
            return x, x

        return jax.lax.scan(step, x0, (us, ts))[1], ts

    @highest
    def solve(
        self,
        key: PRNGKeyArray,
        x0: Float[Array, " n"],
        u_nominal: Float[Array, "H m"],
        t0: Float[ArrayLike, ""],
    ) -> tuple[Float[Array, "H m"], dict]:
        """One MPPI update of ``u_nominal``: apply the first control, :meth:`shift` the rest.

        The first sample is the nominal itself, unperturbed; non-finite costs get weight
        zero; the perturbed sequences are clipped to the control box.

        Args:
            key: the perturbations' randomness.
            x0: (n,) the state.
            u_nominal: (H, m) the nominal sequence (the previous solution, shifted).
            t0: the time (s) of ``x0``.

        Returns:
            The new sequence (H, m) and the sampled costs' summary: ``cost_min``,
            ``cost_nominal`` and ``effective_samples`` (``1/Σ w²``).
        """
        m = u_nominal.shape[-1]
        eps = self._noise(key, m, x0.dtype)
        eps = eps.at[0].set(0.0)  # the nominal itself is always a candidate
        us = jnp.clip(u_nominal[None] + eps, self.u_min, self.u_max)

        def total(u):
            xs, ts = self.rollout(x0, u, t0)
            return self.cost(xs, u, ts)

        costs = jax.vmap(total)(us)
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
        w = jax.nn.softmax(-(costs - jnp.min(costs)) / self.temperature)
        u_new = jnp.clip(
            u_nominal + jnp.einsum("k,khm->hm", w, us - u_nominal[None]), self.u_min, self.u_max
        )
        info = {
            "cost_min": jnp.min(costs),
            "cost_nominal": costs[0],
            "effective_samples": 1.0 / jnp.sum(w * w),
        }
        return u_new, info

    def _noise(self, key, m, dtype):
        if self.knots is None:
            return jax.random.normal(key, (self.samples, self.horizon, m), dtype) * self.noise_std
        z = jax.random.normal(key, (self.samples, self.knots, m), dtype) * self.noise_std
        pos = jnp.linspace(0.0, self.knots - 1.0, self.horizon, dtype=dtype)
        lo = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, self.knots - 2)
        f = (pos - lo)[None, :, None]
        return (1.0 - f) * z[:, lo] + f * z[:, lo + 1]

    @staticmethod
    def shift(us: Float[Array, "H m"]) -> Float[Array, "H m"]:
        """The sequence one control later, its last control repeated (the warm start).

        Args:
            us: (H, m) the controls.

        Returns:
            (H, m) the controls from the second on, the last one repeated.
        """
        return jnp.concatenate([us[1:], us[-1:]])


def _check(x, u):
    x, u = jnp.asarray(x), jnp.asarray(u)
    if x.shape != (STATE_SIZE,):
        raise ValueError(f"x must be a flat state of shape ({STATE_SIZE},), got {x.shape}")
    if u.shape != (4,):
        raise ValueError(f"u must be four rotor-speed commands, shape (4,), got {u.shape}")
    for name, a in (("x", x), ("u", u)):
        if not jnp.issubdtype(a.dtype, jnp.floating):
            raise ValueError(f"{name} must be a float array, got dtype {a.dtype}")
    return x, u.astype(x.dtype)


def _value_and_jacfwd(f, x, u):
    """``f(x, u)`` and its Jacobians in ``x`` and ``u``, by one forward-mode pass."""
    jac, out = jax.jacfwd(lambda a, b: (f(a, b), f(a, b)), argnums=(0, 1), has_aux=True)(x, u)
    return out, jac
