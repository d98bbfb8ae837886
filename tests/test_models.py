"""models/: grids, data access, linear models (Wandell 1985, eq. 5-11)."""

from __future__ import annotations

import numpy as np
import pytest

import models
from models import (daylight_basis, fourier_basis, illuminant, pca_model, reflectance_set,
                    resample, wavelength_grid, wavelength_step)


def test_grid_and_step():
    wl = wavelength_grid(400, 700, 10)
    assert wl.size == 31 and wl[0] == 400 and wl[-1] == 700
    assert np.all(wavelength_step(wl) == 10)
    irregular = np.array([400.0, 410.0, 430.0])
    assert np.allclose(wavelength_step(irregular), [5, 15, 10])
    with pytest.raises(ValueError):
        wavelength_step(np.array([400.0, 400.0]))


def test_resample_is_exact_on_subsets_and_linear_functions():
    src = wavelength_grid(380, 780, 5)
    f = 0.5 + 0.001 * src
    assert np.array_equal(resample(src, f, wavelength_grid(400, 700, 10)), f[4:65:2])
    dst = wavelength_grid(402, 698, 4)  # not a subset: interpolated
    assert np.allclose(resample(src, f, dst), 0.5 + 0.001 * dst, atol=1e-9)


@pytest.mark.parametrize("name", models.camera_names())
def test_cameras_on_grid(name):
    r = models.camera_sensitivities(name)
    assert r.shape == (31, 3) and np.all(r >= 0) and np.isclose(r.max(), 1) and np.all(r.max(axis=0) > 0.2)


def test_data_sets_are_arrays_on_grid():
    wl = wavelength_grid(400, 700, 5)
    assert models.observer("XYZ", wl).shape == (61, 3)
    assert models.observer("cones").shape == (31, 3)
    assert reflectance_set("colorchecker", wl).shape == (24, 61)
    allr = reflectance_set("all")
    assert allr.shape[0] > 250 and np.all(allr >= 0)
    assert models.illuminants().shape[1] == 31
    assert models.display("Typical CRT Brainard 1997", wl).guns.shape == (61, 3)
    with pytest.raises(KeyError, match="accepted"):
        illuminant("nonsense")


def test_daylight_basis_reproduces_cie_d65():
    """D65 = S0 + M1 S1 + M2 S2 (CIE 015): the basis spans D65 to the
    precision of the published tables (4-5 significant digits)."""
    wl = wavelength_grid(400, 700, 10)
    B = daylight_basis(wl)
    d65 = illuminant("D65", wl, normalise=False)
    w, *_ = np.linalg.lstsq(B, d65, rcond=None)
    assert np.max(np.abs(B @ w - d65)) / d65.max() < 5e-3


def test_pca_through_origin_and_centred():
    x = reflectance_set("all")
    m = pca_model(x, 6)
    assert np.allclose(m.basis.T @ m.basis, np.eye(6), atol=1e-12)
    full = pca_model(x)
    assert np.isclose(full.explained_variance.sum(), 1.0)
    # reconstructing with all components is exact
    assert np.allclose(full.fit(x), x, atol=1e-12)
    # error decreases with more terms
    errs = [np.median(models.normalised_rmse(x, pca_model(x, d).fit(x))) for d in range(1, 8)]
    assert all(a > b for a, b in zip(errs, errs[1:]))
    c = pca_model(x, 3, centred=True)
    assert c.mean is not None and np.allclose(c.fit(x).mean(0), x.mean(0), atol=1e-12)


def test_fourier_basis_is_orthonormal_dc_sin_cos():
    wl = wavelength_grid(400, 700, 10)
    b = fourier_basis(wl, 7)
    assert np.allclose(b.T @ b, np.eye(7), atol=1e-12)
    assert np.allclose(b[:, 0], b[0, 0])  # DC
    # a spectrum made of the first 5 terms is fitted exactly
    m = models.fourier_model(5, wl)
    s = b[:, :5] @ np.array([3.0, 0.2, -0.1, 0.05, 0.3])
    assert np.allclose(m.fit(s), s, atol=1e-12)


def test_linear_model_truncate_and_project_shapes():
    m = models.surface_pca_model(5)
    t = m.truncate(2)
    assert t.dimension == 2
    w = t.project(reflectance_set("colorchecker"))
    assert w.shape == (24, 2)
    with pytest.raises(ValueError):
        m.truncate(6)
