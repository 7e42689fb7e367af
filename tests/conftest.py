"""Shared test set-up: float64 (importing gpg enables it) and fixed seeds."""

import numpy as np
import pytest

import gpg  # noqa: F401  (enables jax_enable_x64 before any test builds an array)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)
