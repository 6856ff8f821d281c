"""Shared pytest fixtures: the Mitsuba variant, the real envmaps, a seeded RNG."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

# The suite's build cache and plans live in a folder of its own, made fresh for each run:
# no test reads what an earlier run (or the user's renders) left in the user's cache.
# Removed when the run ends (each of pytest-xdist's workers makes and removes its own): a run
# writes a few hundred MB there.
os.environ["SHSAMPLING_CACHE_DIR"] = tempfile.mkdtemp(prefix="shsampling-tests-")
atexit.register(shutil.rmtree, os.environ["SHSAMPLING_CACHE_DIR"], ignore_errors=True)

# Import the package first: it points Dr.Jit at a libLLVM >= 16 before drjit
# loads one itself (see mitsuba_shsampling/_backend.py).
import mitsuba_shsampling  # noqa: F401
import mitsuba as mi

VARIANT = "llvm_ad_rgb"
mi.set_variant(VARIANT)

ENVMAPS_DIR = Path(__file__).resolve().parent / "data" / "envmaps"
"""The four real CC0 HDR maps (Poly Haven, 1024x512), shipped with the tests (see SOURCES.md there)."""


@pytest.fixture(scope="session")
def variant() -> str:
    """The Mitsuba variant every test runs on (set once, at collection)."""
    mi.set_variant(VARIANT)
    return VARIANT


@pytest.fixture(scope="session")
def envmaps_dir() -> Path:
    """Folder of the real envmaps shipped in ``tests/data/envmaps``."""
    return ENVMAPS_DIR


@pytest.fixture
def rng() -> np.random.Generator:
    """A numpy generator with a fixed seed, fresh for every test."""
    return np.random.default_rng(20090401)
