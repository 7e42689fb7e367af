"""gpg inside other simulators: conventions (frames, quaternion order, units) converted at one
tested boundary (:mod:`gpg.adapters.conventions`), and a RotorPy plug-in
(:mod:`gpg.adapters.rotorpy`, needs the ``rotorpy`` extra)."""

from gpg.adapters.conventions import ZUp

__all__ = ["ZUp"]
