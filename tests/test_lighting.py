"""Lighting matrices (eq. 17-21, 32-33) and Gamma (eq. 2-4) against
brute-force sums over wavelength."""

from __future__ import annotations

import numpy as np

import models
from recovery import Camera
from recovery.lighting import (display_matrix, lighting_matrix, lighting_matrix_from_spectrum,
                               lighting_tensor, surface_lighting_matrix)


def _setup():
    cam = Camera.named("Canon EOS 5D Mark II")
    E = models.daylight_model(3).basis
    S = models.surface_pca_model(4).basis
    return cam, E, S


def test_lighting_tensor_brute_force():
    cam, E, S = _setup()
    T = lighting_tensor(E, S, cam.sensitivities, cam.dlambda)
    N = cam.wavelengths.size
    for i in range(E.shape[1]):
        for k in range(cam.channels):
            for j in range(S.shape[1]):
                brute = 0.0
                for n in range(N):
                    brute += E[n, i] * S[n, j] * cam.sensitivities[n, k] * cam.dlambda[n]
                assert np.isclose(T[i, k, j], brute, rtol=1e-12, atol=1e-12)


def test_lighting_matrix_equals_eq17_and_symmetry_eq32(rng=np.random.default_rng(3)):
    cam, E, S = _setup()
    T = lighting_tensor(E, S, cam.sensitivities, cam.dlambda)
    eps = rng.normal(size=3)
    sig = rng.normal(size=4)
    L_E = lighting_matrix(eps, T)
    spd = E @ eps
    brute = np.zeros((cam.channels, S.shape[1]))
    for k in range(cam.channels):
        for j in range(S.shape[1]):
            brute[k, j] = sum(spd[n] * S[n, j] * cam.sensitivities[n, k] * cam.dlambda[n]
                              for n in range(spd.size))
    assert np.allclose(L_E, brute, rtol=1e-12, atol=1e-12)
    assert np.allclose(lighting_matrix_from_spectrum(spd, S, cam.sensitivities, cam.dlambda), brute,
                       rtol=1e-12, atol=1e-12)
    # eq. 32: Lambda_E sigma = Lambda_S eps, and eq. 33 entry by entry
    L_S = surface_lighting_matrix(sig, T)
    assert np.allclose(L_E @ sig, L_S @ eps, rtol=1e-12, atol=1e-12)
    surf = S @ sig
    for k in range(cam.channels):
        for i in range(3):
            b = sum(E[n, i] * surf[n] * cam.sensitivities[n, k] * cam.dlambda[n] for n in range(surf.size))
            assert np.isclose(L_S[k, i], b, rtol=1e-12, atol=1e-12)


def test_display_matrix_brute_force():
    wl = models.DEFAULT_WAVELENGTHS
    guns = models.display("Typical CRT Brainard 1997", wl).guns
    obs = models.observer("cones", wl)
    dl = models.wavelength_step(wl)
    G = display_matrix(guns, obs, dl)
    for k in range(3):
        for j in range(3):
            b = sum(guns[n, j] * obs[n, k] * dl[n] for n in range(wl.size))
            assert np.isclose(G[k, j], b, rtol=1e-12)
    # eq. 3: the observer response to intensities I is Gamma I
    I = np.array([0.2, 0.5, 0.9])
    assert np.allclose(G @ I, (guns @ I * dl) @ obs, rtol=1e-12)
