"""gpg inside other simulators: conventions (frames, quaternion order, units) converted at one
tested boundary (:mod:`gpg.adapters.conventions`), and a RotorPy plug-in
(:mod:`gpg.adapters.rotorpy`, needs the ``rotorpy`` extra: imported on its own,
``from gpg.adapters.rotorpy import GpgMultirotor``)."""

from gpg.adapters import conventions
from gpg.adapters.conventions import ZUp, ZUpWrench

__all__ = ["ZUp", "ZUpWrench", "conventions"]
