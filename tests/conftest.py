"""Shared fixtures: a small virtual rig and seeded randomness."""

import numpy as np
import pytest
from hypothesis import settings

# Timing is the benchmarks' business: no per-example deadline on a loaded 2-core CI machine.
settings.register_profile("sliscan", deadline=None)
settings.load_profile("sliscan")

from sliscan import simulate


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def small_rig():
    """A 640x480 camera with the thesis's 1024x768 projector 200 mm above it."""
    return simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768))
