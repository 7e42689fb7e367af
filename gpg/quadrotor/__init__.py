"""Quadrotor physics: frames, vehicle, simplified model, BEMT aerodynamics, tonal acoustics."""

from gpg.quadrotor.generator import Generator
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle, load_vehicle

__all__ = ["Generator", "SimpleModel", "Vehicle", "load_vehicle"]
