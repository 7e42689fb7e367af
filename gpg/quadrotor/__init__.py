"""Quadrotor physics: frames, vehicle, simplified model, BEMT aerodynamics, tonal acoustics.

The submodules: :mod:`~gpg.quadrotor.frames` (rotations, the airflow frame ``H``),
:mod:`~gpg.quadrotor.vehicle` (vehicle files), :mod:`~gpg.quadrotor.simple_model` (the paper's
``M``), :mod:`~gpg.quadrotor.simple_noise` (``M_noise``), :mod:`~gpg.quadrotor.bemt` and
:mod:`~gpg.quadrotor.acoustics` (the generator's aerodynamics and tones),
:mod:`~gpg.quadrotor.generator` (dataset inputs to outputs), :mod:`~gpg.quadrotor.dynamics`
(the 6-DoF rigid body), :mod:`~gpg.quadrotor.control` (the geometric controller and its
references), :mod:`~gpg.quadrotor.rollout` (closed-loop simulation) and
:mod:`~gpg.quadrotor.metrics` (how a flight went).
"""

from gpg.quadrotor import (
    acoustics,
    bemt,
    control,
    dynamics,
    frames,
    generator,
    metrics,
    rollout,
    simple_model,
    simple_noise,
    vehicle,
)
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import Quadrotor, SimpleAero, State, Wind
from gpg.quadrotor.generator import Generator
from gpg.quadrotor.metrics import flight_metrics
from gpg.quadrotor.rollout import simulate
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise
from gpg.quadrotor.vehicle import Vehicle, load_vehicle

__all__ = [
    "Generator",
    "GeometricController",
    "Quadrotor",
    "SimpleAero",
    "SimpleModel",
    "SimpleNoise",
    "State",
    "Vehicle",
    "WaypointPlan",
    "Wind",
    "acoustics",
    "bemt",
    "control",
    "dynamics",
    "flight_metrics",
    "frames",
    "generator",
    "load_vehicle",
    "metrics",
    "rollout",
    "simple_model",
    "simple_noise",
    "simulate",
    "vehicle",
]
