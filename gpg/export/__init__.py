"""A fitted surrogate outside JAX: self-contained C source (:func:`to_c`), a CasADi function
with exact derivatives (:func:`to_casadi`) and an ONNX model (:func:`to_onnx`), each of the
world-frame prediction ``(rpm, euler, v_air) -> (force, torque, levels[, variance],
in_domain)`` with the trained arrays as constants, and each carrying a record of the gpg
version, the model, the SHA-256 of its arrays and the units (:func:`gpg.export.layout.spec`).
A surrogate fitted in either frame exports with that call: the airflow frame's (the paper's
inputs) or the body frame's (rotor speeds and ``R_WBᵀ v_air``, the ball as its domain).

Kinds: every real-time kind (``gpg``, ``gpgs_hybrid``, ``gpg_pic``, ``gpgs``, ``gpgs_schur``,
``gps_*``; ``gp`` like ``gpg``) exports its mean and its variance. The exact kinds' variance
factor is the dense ``(N(1+G))²`` triangle (over ``max_bytes`` at data=default, see
docs/measurements.md), so it passes only under ``max_bytes`` (small models); a surrogate with
``M_noise`` is refused (its acoustic model, :mod:`gpg.quadrotor.simple_noise`, is not
exported), as is an exact model grown by ``condition`` when its variance is asked for.
A model corrected by flights (:func:`gpg.flight.correct`) exports with its correction over its
prior's closed form (:class:`gpg.export.layout.Correction`), an adapted one
(:func:`gpg.flight.adapt`, or a bank of such terms from :func:`gpg.flight.adapt_bank`, with
its variance) or tracked one (:func:`gpg.flight.track`, of the physical basis) with its
online term as well (in C with its update, on a state the caller holds; CasADi and ONNX at
the exported state); a tracked model with a wind state (:func:`gpg.flight.gusts`)
exports to C only (its update and prediction differentiate the model in the air velocity by
central differences there), with its variance; CasADi and ONNX refuse it.

:func:`to_native` builds the C with the system's compiler and loads it with ctypes: the
prediction and the online update called from Python at the C's cost (:class:`Native`).
"""

from gpg._deprecated import deprecated
from gpg.export.c_source import to_c
from gpg.export.casadi_function import to_casadi
from gpg.export.layout import Layout, spec
from gpg.export.native import Native, NativePrediction, to_native
from gpg.export.onnx_model import to_onnx

__all__ = [
    "Layout",
    "Native",
    "NativePrediction",
    "spec",
    "to_c",
    "to_casadi",
    "to_native",
    "to_onnx",
]


def __getattr__(name: str):
    # gpg.export.Spec, the name before gpg 0.3 (gpg.models.Spec is the registry's): one release
    if name == "Spec":
        deprecated("gpg.export.Spec", "gpg.export.Layout")
        return Layout
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
