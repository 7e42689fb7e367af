"""The one table of input and output names, their units, and the gradient dims.

Inputs ``x = (r1..r4, ψ, θ, φ, |V|)`` (rpm, rad, m/s); outputs the force and moment in the
airflow frame (N, N·m) and three microphone levels (dB). Gradients are taken along the rotor
speeds and the Euler angles, not along the airspeed (the paper's ``X_g``).
"""

__all__ = [
    "AERO",
    "BODY_INPUTS",
    "FRAMES",
    "GRAD_DIMS",
    "GRAD_INPUTS",
    "INPUTS",
    "NOISE",
    "OUTPUTS",
    "UNITS",
    "grad_inputs",
    "inputs",
]

INPUTS = ("r1", "r2", "r3", "r4", "yaw", "pitch", "roll", "airspeed")
GRAD_DIMS = tuple(range(7))  # rpm and Euler angles; no gradient along airspeed
GRAD_INPUTS = tuple(INPUTS[i] for i in GRAD_DIMS)
AERO = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
NOISE = ("L1", "L2", "L3")
OUTPUTS = AERO + NOISE
UNITS = {
    **{r: "rpm" for r in INPUTS[:4]},
    **{a: "rad" for a in ("yaw", "pitch", "roll")},
    "airspeed": "m/s",
    **{f: "N" for f in AERO[:3]},
    **{m: "N*m" for m in AERO[3:]},
    **{n: "dB" for n in NOISE},
}

# The body-frame formulation (gpg.quadrotor.generator, "frame: body"): the loads depend on the
# rotor speeds and the air velocity in the body frame alone, ``x_B = (r1..r4, u, v, w)`` with
# ``(u, v, w) = R_WBᵀ v_air`` (m/s, FRD: u forward, v right, w down), smooth everywhere, hover
# included; outputs the force and moment in the body frame. Gradients along all seven inputs.
FRAMES = ("airflow", "body")
BODY_INPUTS = ("r1", "r2", "r3", "r4", "u", "v", "w")
UNITS.update({c: "m/s" for c in BODY_INPUTS[4:]})


def inputs(frame: str = "airflow") -> tuple[str, ...]:
    """The input names of a dataset in ``frame``.

    Args:
        frame: one of :data:`FRAMES`, ``"airflow"`` (the paper's ``x_H``) or ``"body"``
            (``x_B``).

    Returns:
        :data:`INPUTS` for the airflow frame, :data:`BODY_INPUTS` for the body frame.

    Raises:
        ValueError: if ``frame`` is not one of :data:`FRAMES`.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {list(FRAMES)}, got {frame!r}")
    return INPUTS if frame == "airflow" else BODY_INPUTS


def grad_inputs(frame: str = "airflow") -> tuple[str, ...]:
    """The inputs a dataset in ``frame`` has gradients along.

    Seven in both frames: the airflow frame has none along the airspeed, the body frame has
    them along every input.

    Args:
        frame: one of :data:`FRAMES`.

    Returns:
        The first seven names of :func:`inputs` for ``frame``.

    Raises:
        ValueError: if ``frame`` is unknown (from :func:`inputs`).
    """
    return inputs(frame)[:7]
