"""Synthesis (Wandell 1985, eq. 22-25, Fig. 6) against colour-science."""

from __future__ import annotations

import colour
import numpy as np
import pytest

import models
from recovery import Camera, IlluminantEstimate, estimate_illuminant, render
from recovery.lighting import lighting_matrix_from_spectrum
from recovery.synthesis import display_intensities, output_space

WL = models.DEFAULT_WAVELENGTHS


def _colour_linear_srgb(refl, wl):
    """colour-science's own path: sd_to_XYZ (integration) then XYZ to
    linear sRGB with the colourspace matrix, with the same D65 samples
    (models.illuminant box-averages 5 nm data onto the 10 nm grid)."""
    shape = colour.SpectralShape(wl[0], wl[-1], wl[1] - wl[0])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    d65 = colour.SpectralDistribution(models.illuminant("D65", wl), wl)
    out = []
    for r in refl:
        sd = colour.SpectralDistribution(r, wl)
        XYZ = colour.sd_to_XYZ(sd, cmfs, d65, method="Integration") / 100
        out.append(colour.XYZ_to_RGB(XYZ, "sRGB", apply_cctf_encoding=False,
                                     chromatic_adaptation_transform=None))
    return np.array(out)


def test_wavelength_basis_synthesis_matches_colour():
    """Eq. 23 with the wavelength basis (eq. 8-9, 13-14): I = Gamma^-1 Omega_E' S."""
    refl = models.reflectance_set("colorchecker")
    d65 = models.illuminant("D65")
    space = output_space("linear-sRGB", WL)
    L = lighting_matrix_from_spectrum(d65, np.eye(WL.size), space.observer, models.wavelength_step(WL))
    white = L[1].sum()
    ours = display_intensities(refl, L / white, space.Gamma)
    assert np.max(np.abs(ours - _colour_linear_srgb(refl, WL))) < 1e-6


def test_render_of_observer_camera_matches_colour():
    """Fig. 6 with a camera that is the observer (Horn's easy case): render()
    of the camera's image of known spectra under D65, with the true light,
    equals colour-science's sRGB of those spectra (any spectra, not only
    ones inside the surface model, since the synthesis matrix is then k I)."""
    cmfs = models.observer("XYZ")
    cam = Camera(WL, cmfs, "CIE 1931 observer as camera")
    refl = models.reflectance_set("all")[:60]
    d65 = models.illuminant("D65")
    img = cam.response(refl * d65).reshape(6, 10, 3)
    est = IlluminantEstimate(cam.response(d65), d65, WL, "true-light")
    lin = render(img, cam, est, target="D65", output="linear-sRGB", gamut="none")
    ref = _colour_linear_srgb(refl, WL).reshape(6, 10, 3)
    # float32 output: 1e-6 holds for values below 1 (float32 spacing 6e-8)
    assert np.max(np.abs(lin - ref)) < 1e-6
    xyz = render(img, cam, est, target="D65", output="XYZ")
    shape = colour.SpectralShape(400, 700, 10)
    XYZ_ref = colour.sd_to_XYZ(colour.SpectralDistribution(refl[7], WL),
                               colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape),
                               colour.SpectralDistribution(models.illuminant("D65", WL), WL),
                               method="Integration") / 100
    assert np.allclose(xyz.reshape(-1, 3)[7], XYZ_ref, atol=1e-6)
    enc = render(img, cam, est, output="sRGB")
    ref_enc = colour.cctf_encoding(np.clip(ref, 0, 1), "sRGB")
    assert np.max(np.abs(enc - ref_enc)) < 1e-5


@pytest.mark.parametrize("gamut", ["clip", "adjust-light"])
@pytest.mark.parametrize("output", ["linear-sRGB", "Typical CRT Brainard 1997"])
def test_gamut_handling_never_negative(gamut, output, rng=np.random.default_rng(5)):
    cam = Camera.named("Nikon 5100 (NPL)")
    refl = models.reflectance_set("all")
    spd = models.illuminant("FL11")
    img = cam.response(refl * spd)[None]
    est = estimate_illuminant(img, cam, method="gray-world")
    raw, info0 = render(img, cam, est, output=output, gamut="none", return_info=True)
    assert raw.min() < 0  # saturated surfaces really are out of gamut
    out, info = render(img, cam, est, output=output, gamut=gamut, return_info=True)
    assert out.min() >= 0 and np.all(np.isfinite(out))
    assert info["out_of_gamut_fraction"] > 0
    if gamut == "adjust-light" and info["gamut_adjustment"].get("adjusted"):
        # the adjusted light keeps every pixel in gamut before any clipping
        assert info["gamut_adjustment"]["feasible"]


def test_adjust_light_moves_all_pixels_into_gamut():
    """A scene whose colours are only slightly out of gamut under D65: the
    whole-image light adjustment (Wandell's second option) finds a light
    that puts every pixel inside without clipping."""
    cam = Camera(WL, models.observer("XYZ"), "observer")
    refl = models.reflectance_set("colorchecker")
    d65 = models.illuminant("D65")
    img = cam.response(refl * d65)[None]
    est = IlluminantEstimate(cam.response(d65), d65, WL, "true-light")
    raw = render(img, cam, est, output="linear-sRGB", gamut="none")
    assert raw.min() < 0
    out, info = render(img, cam, est, output="linear-sRGB", gamut="adjust-light", return_info=True)
    g = info["gamut_adjustment"]
    assert g["adjusted"] and g["feasible"]
    M = np.asarray(info["matrix"])
    assert np.min(img.reshape(-1, 3) @ M.T) > -1e-6


def test_render_rejects_bad_target():
    cam = Camera.named("Nikon 5100 (NPL)")
    img = np.ones((2, 2, 3))
    est = estimate_illuminant(np.random.default_rng(0).uniform(0.1, 1, (8, 8, 3)), cam, method="gray-world")
    with pytest.raises(ValueError, match="unknown illuminant"):
        render(img, cam, est, target="D65x")
    with pytest.raises(ValueError, match="unknown output"):
        render(img, cam, est, output="CMYK")
