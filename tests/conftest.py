"""Shared fixtures: in-model scenes with known truth."""

from __future__ import annotations

import os

import numpy as np
import pytest

# The in-process clients' host names (Starlette's TestClient sends
# "testserver", the httpx ASGI clients here "t" and "test"): served like the
# names WANDELL_ALLOWED_HOSTS adds in a deployment. Tests of the Host check
# itself set the variable through env_settings.
os.environ.setdefault("WANDELL_ALLOWED_HOSTS", "testserver,t,test")

from models import DEFAULT_WAVELENGTHS


def gaussian_sensors(centres, width=30.0, wavelengths=DEFAULT_WAVELENGTHS):
    """Sensors with Gaussian sensitivities, one column per centre (nm)."""
    wl = np.asarray(wavelengths, float)[:, None]
    return np.exp(-0.5 * ((wl - np.asarray(centres, float)[None]) / width) ** 2)


def in_model_scene(rng, camera, surface_basis, light_weights, light_basis, n_pixels=4096, shape=None):
    """Pixels generated exactly by eq. 26: rho = Lambda_E sigma, with random
    surface weights (first weight positive and dominant, as for real
    surfaces). Returns image (H, W, C) and the true surface weights."""
    d_s = surface_basis.shape[1]
    sig = rng.normal(scale=0.3, size=(n_pixels, d_s))
    sig[:, 0] = 1.0 + np.abs(sig[:, 0])
    spd = light_basis @ light_weights
    refl = sig @ surface_basis.T
    rho = camera.response(refl * spd)
    shape = shape or (64, n_pixels // 64)
    return rho.reshape(*shape, camera.channels), sig


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture
def env_settings(monkeypatch):
    """Set WANDELL_* variables for one test; settings are re-read from the
    environment (get_settings is cached per process) and restored after."""
    from service.settings import get_settings

    def set_env(**values):
        for k, v in values.items():
            monkeypatch.setenv(f"WANDELL_{k.upper()}", str(v))
        get_settings.cache_clear()
    yield set_env
    monkeypatch.undo()
    get_settings.cache_clear()
