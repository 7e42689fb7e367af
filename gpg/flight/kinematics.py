"""Whether a flight's signals agree with each other: unit, order and frame mistakes caught by
the kinematics that tie the signals together.

A log's signals are not independent. Over a window ``[a, b]`` of the flight:

- the position moves by the velocity's integral: ``p_b − p_a = ∫ v dt``;
- the attitude turns by the body rates' integral: ``rotvec(R_aᵀ R_b) ≈ ∫ ω dt`` (exact to
  first order in the window's rotation, hence the short window);
- the velocity changes by the specific force and gravity: ``v_b − v_a − g e_z (t_b − t_a) =
  ∫ R f dt`` (NED, the accelerometer's specific force ``f`` turned into the world);
- without an accelerometer: the same change points along the thrust axis ``−R e_z``
  (the rotors' thrust dominates the aerodynamic force; a drag of a quarter of the weight
  tilts it by 14°).

Each check takes the left side ``D`` and the right side ``I`` per window and reports, per axis,
the median of ``D/I`` over the windows where the axis moves and carries at least
:data:`DOMINANCE` of the motion (1 for a consistent log; a
position in mm gives 1000, rates in deg/s 1/57, a specific force in g 9.8, a sign
flipped between frames −1), and the median relative error ``‖D − I‖/‖I‖`` (the thrust axis:
the median angle between the two directions, rad). A mistake in the quaternion's order turns
the attitude by a large angle and breaks both the attitude and the accelerometer checks.
A check that saw too little motion says so (``uninformative``) rather than pass.

Tolerances (:data:`RATIO`, :data:`ERROR`, :data:`ANGLE`): within the first bound the pair is
``consistent``; between the bounds ``doubtful`` (the readers warn); beyond the second
``inconsistent`` (the readers refuse, naming the two signals). The bounds are wide against
noise (a factor 1.25 on a median over at least :data:`MIN_WINDOWS` windows) and narrow
against the mistakes above (a factor 3.6 or more).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["Agreement", "consistency", "quat_to_matrix"]

# Median ratio D/I: consistent within a factor RATIO[0], doubtful up to RATIO[1].
RATIO = (1.25, 2.0)
# Median relative error ‖D − I‖/‖I‖: consistent up to ERROR[0], doubtful up to ERROR[1].
ERROR = (0.25, 0.5)
# The thrust axis's median angle to the velocity's change, rad: a drag of a quarter of the
# weight is 14°; a turned attitude is tens of degrees.
ANGLE = (math.radians(30.0), math.radians(60.0))
# An axis's ratio counts the windows where it carries this share of the motion or more: on an
# axis that moves little beside others, the rotation's second-order terms rival its own.
DOMINANCE = 0.5
# The fewest windows a ratio or an error is taken over; fewer: uninformative.
MIN_WINDOWS = 5
GRAVITY = 9.81  # m/s², the checks' gravity (a vehicle's own differs by far less than RATIO)
GAP_FACTOR = 5.0  # a step this many times the median one splits the flight (as FlightLog)

# Each check: (window length s, the least mean rate |I|/Δt of an axis or of the vector that
# counts as motion; a change |D|/Δt ten times that counts too: a unit mistake the other way)
_CHECKS = {
    "position": (1.0, 0.1),  # m/s
    "attitude": (0.2, 0.2),  # rad/s; a short window: the rotation to first order
    "specific_force": (0.5, 0.4),  # m/s²
    "thrust_axis": (0.5, 0.5 * GRAVITY),  # m/s²: half of gravity's (a direction only)
}


class _Flight(Protocol):  # what a FlightLog gives the checks
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    rates: np.ndarray
    specific_force: np.ndarray | None
    name: str


@dataclass(frozen=True)
class Agreement:
    """How well one signal agrees with the integral of another over a flight.

    Attributes:
        signal: the signal whose change is compared (``position``, ``attitude``,
            ``velocity``).
        rate: what is integrated (``velocity``, ``rates``, ``specific_force``,
            ``thrust_axis``).
        ratio: per axis, the median of change over integral where that axis moves; None
            where it does not (or for the thrust axis, a direction only).
        error: the median relative error of the vector (the thrust axis: the median
            angle, rad); NaN where no window moves enough.
        windows: how many windows the error is the median of.
        verdict: ``consistent``, ``doubtful``, ``inconsistent`` or ``uninformative``.
    """

    signal: str
    rate: str
    ratio: tuple[float | None, float | None, float | None]
    error: float
    windows: int
    verdict: str

    def describe(self) -> str:
        """One line: the two signals, the ratios and the error, the verdict.

        Returns:
            The line, for messages and tables.
        """
        axes = ", ".join(
            f"{a} {r:.3g}" for a, r in zip("xyz", self.ratio, strict=True) if r is not None
        )
        what = "angle" if self.rate == "thrust_axis" else "relative error"
        err = (
            f"{math.degrees(self.error):.3g}°"
            if self.rate == "thrust_axis"
            else f"{self.error:.3g}"
        )
        ratio = f"Δ{self.signal}/∫{self.rate} dt = {axes}; " if axes else ""
        return (
            f"{self.signal} against {self.rate}: {ratio}median {what} {err} over "
            f"{self.windows} windows: {self.verdict}"
        )


# What each check's disagreement usually means.
HINTS = {
    "velocity": "position in mm or cm, velocity in km/h, or frames that differ between them",
    "rates": (
        "body rates in deg/s (a ratio near 0.017), a quaternion in another order "
        "(scalar last), or a body frame that differs between attitude and rates"
    ),
    "specific_force": (
        "a specific force in g (a ratio near 9.8), a quaternion in another order, or "
        "world or body frames that differ between the signals"
    ),
    "thrust_axis": "a quaternion in another order (scalar last) or a world/body frame mistake",
}


def consistency(log: _Flight, *, gravity: float = GRAVITY) -> tuple[Agreement, ...]:
    """The kinematic checks of a flight's signals against each other (module docstring).

    Args:
        log: the flight (:class:`~gpg.flight.log.FlightLog`).
        gravity: m/s², along the world's z (NED: down).

    Returns:
        One :class:`Agreement` per check: position against velocity, attitude against the
        body rates, and velocity against the specific force where the log has one, else
        against the thrust axis.
    """
    t = np.asarray(log.t, float)
    q = np.asarray(log.quaternion, float)
    R = quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
    v = np.asarray(log.velocity, float)
    p = np.asarray(log.position, float)
    out = []
    # position: Δp against ∫v
    a, b, dt = _windows(t, "position")
    out.append(
        _agree("position", "velocity", (p[b] - p[a]) / dt, _mean(t, v, a, b, dt), "position")
    )
    # attitude: rotvec(R_aᵀ R_b) against ∫ω
    a, b, dt = _windows(t, "attitude")
    turn = _rotvec(np.einsum("nji,njk->nik", R[a], R[b])) / dt
    w = _mean(t, np.asarray(log.rates, float), a, b, dt)
    out.append(_agree("attitude", "rates", turn, w, "attitude"))
    # velocity: Δv − g Δt against ∫R f, or its direction against the thrust axis
    if log.specific_force is not None:
        a, b, dt = _windows(t, "specific_force")
        f = np.einsum("nij,nj->ni", R, np.asarray(log.specific_force, float))
        dv = (v[b] - v[a]) / dt - [0.0, 0.0, gravity]
        out.append(
            _agree("velocity", "specific_force", dv, _mean(t, f, a, b, dt), "specific_force")
        )
    else:
        a, b, dt = _windows(t, "thrust_axis")
        dv = (v[b] - v[a]) / dt - [0.0, 0.0, gravity]
        out.append(_direction("velocity", "thrust_axis", dv, _mean(t, -R[:, :, 2], a, b, dt)))
    return tuple(out)


def _windows(t: np.ndarray, check: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start and end rows of consecutive windows of about ``check``'s length that cross no
    gap, and their durations (N, 1)."""
    steps = np.diff(t)
    med = float(np.median(steps))
    k = max(1, min(int(round(_CHECKS[check][0] / med)), t.size // (4 * MIN_WINDOWS)))
    cut = np.flatnonzero(steps > GAP_FACTOR * med) + 1
    bounds = np.concatenate([[0], cut, [t.size]])
    starts = [np.arange(lo, hi - k, k) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    a = np.concatenate(starts) if starts else np.zeros(0, int)
    return a, a + k, (t[a + k] - t[a])[:, None]


def _mean(t: np.ndarray, x: np.ndarray, a: np.ndarray, b: np.ndarray, dt: np.ndarray):
    """The mean of ``x`` (T, k) over each window ``a..b`` (trapezoidal)."""
    inc = 0.5 * (x[1:] + x[:-1]) * np.diff(t)[:, None]
    C = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(inc, axis=0)])
    return (C[b] - C[a]) / dt


def _agree(signal: str, rate: str, D: np.ndarray, I: np.ndarray, check: str) -> Agreement:  # noqa: E741
    """The per-axis median ratios and the median relative error of ``D`` against ``I`` (both
    per second of their windows), motion as ``check``'s least rate."""
    least = _CHECKS[check][1]
    ratio: list[float | None] = []
    nI, nD = np.linalg.norm(I, axis=1), np.linalg.norm(D, axis=1)
    for k in range(3):
        # an axis counts where the integral moves, or the change moves far more (a unit
        # mistake the other way round), and carries DOMINANCE of the motion
        use = ((np.abs(I[:, k]) >= least) & (np.abs(I[:, k]) >= DOMINANCE * nI)) | (
            (np.abs(D[:, k]) >= 10 * least) & (np.abs(D[:, k]) >= DOMINANCE * nD)
        )
        if np.count_nonzero(use) < MIN_WINDOWS:
            ratio.append(None)
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            r = D[use, k] / I[use, k]
        ratio.append(float(np.median(np.nan_to_num(r, nan=np.inf))))
    norm = np.linalg.norm(I, axis=1)
    use = (norm >= least) | (np.linalg.norm(D, axis=1) >= 10 * least)
    n = int(np.count_nonzero(use))
    err = (
        float(np.median(np.linalg.norm(D[use] - I[use], axis=1) / np.maximum(norm[use], 1e-300)))
        if n >= MIN_WINDOWS
        else math.nan
    )
    return Agreement(signal, rate, (ratio[0], ratio[1], ratio[2]), err, n, _verdict(ratio, err))


def _direction(signal: str, rate: str, D: np.ndarray, I: np.ndarray) -> Agreement:  # noqa: E741
    """The median angle between ``D`` and ``I`` over the windows where ``D`` is large."""
    nD, nI = np.linalg.norm(D, axis=1), np.linalg.norm(I, axis=1)
    use = (nD >= _CHECKS["thrust_axis"][1]) & (nI > 0)
    n = int(np.count_nonzero(use))
    if n < MIN_WINDOWS:
        return Agreement(signal, rate, (None, None, None), math.nan, n, "uninformative")
    cos = np.sum(D[use] * I[use], axis=1) / (nD[use] * nI[use])
    angle = float(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))
    verdict = (
        "consistent" if angle <= ANGLE[0] else "doubtful" if angle <= ANGLE[1] else "inconsistent"
    )
    return Agreement(signal, rate, (None, None, None), angle, n, verdict)


def _verdict(ratio: list[float | None], err: float) -> str:
    known = [r for r in ratio if r is not None]
    if not known and math.isnan(err):
        return "uninformative"
    off = [abs(math.log(r)) if r > 0 and math.isfinite(r) else math.inf for r in known]
    worst = max(off, default=0.0)
    e = 0.0 if math.isnan(err) else err
    if worst > math.log(RATIO[1]) or e > ERROR[1]:
        return "inconsistent"
    if worst > math.log(RATIO[0]) or e > ERROR[0]:
        return "doubtful"
    return "consistent"


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Args:
        q: (…, 4) unit quaternions ``(w, x, y, z)``.

    Returns:
        (…, 3, 3) the rotations they stand for.
    """
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _rotvec(R: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors of rotation matrices (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    if R.shape[0] == 0:
        return np.zeros((0, 3))
    return Rotation.from_matrix(R).as_rotvec()
