"""The one table of input and output names, their units, and the gradient dims.

Inputs ``x = (r1..r4, ψ, θ, φ, |V|)`` (rpm, rad, m/s); outputs the force and moment in the
airflow frame (N, N·m) and three microphone levels (dB). Gradients are taken along the rotor
speeds and the Euler angles, not along the airspeed (the paper's ``X_g``).
"""

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
