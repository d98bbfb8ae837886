"""Minimal uncompressed CFA DNG files, LinearRaw DNGs (:func:`write_linear_dng`:
compressed, tiled, float), and spectral scenes to fill them.

Test fixtures for the RAW white-balance service: a scene whose every number
is known (surfaces, light, camera), rendered through a measured camera,
mosaicked, quantised and written as a DNG that LibRaw (``rawpy``) decodes.

The camera response of pixel ``x`` in channel ``k`` is Wandell (1985),
eq. 12, with the interval made explicit:

.. math::

    \\rho_k^x = s^x\\,\\kappa \\sum_n E(\\lambda_n) S^x(\\lambda_n)
    R_k(\\lambda_n) \\Delta\\lambda_n

with :math:`s^x` a shading factor, :math:`\\kappa` the exposure scale (the
brightest noiseless value equals ``exposure``, a fraction of the range
``white_level - black_level``) and the truth of the light the response to a
perfect white reflector, :math:`\\kappa \\sum_n E R_k \\Delta\\lambda_n`.
The digital number written is
:math:`\\mathrm{round}(b + \\rho (w - b))` with :math:`b, w` the black and
white levels.

What LibRaw 0.22 (rawpy 0.28) reads from these files, measured by
``tests/test_dngwriter.py``:

- ``raw_image`` is the written CFA, bit for bit; ``black_level_per_channel``
  and ``white_level`` are BlackLevel and WhiteLevel; ``raw_pattern`` follows
  CFAPattern (with the second green numbered 3, ``color_desc`` ``b"RGBG"``);
- ``camera_whitebalance`` is ``1 / AsShotNeutral`` (green 1, fourth entry 0);
- ColorMatrix1 is honoured through ``color_matrix`` (LibRaw's ``rgb_cam``) and
  ``daylight_whitebalance`` (``pre_mul``), but ``rgb_xyz_matrix`` is *not*
  ColorMatrix1: it is LibRaw's built-in table entry for the Make/Model
  (Adobe's matrix for a NIKON D5100 or a Canon EOS 5D Mark II, zeros for an
  unknown camera);
- for a known camera LibRaw also fills ``camera_white_level_per_channel``
  from its own table (15311 for the NIKON D5100), whatever WhiteLevel says;
- CalibrationIlluminant1 changes nothing when there is a single matrix;
  without AsShotNeutral ``camera_whitebalance`` is ``[0, 1, 0, 0]``; a
  non-integer BlackLevel is reported truncated; rawpy does not expose
  Make/Model (read them with ``tifffile``);
- LibRaw refuses images under 22 pixels on a side
  (``LibRawFileUnsupportedError``). Errors: empty or truncated file
  ``LibRawIOError`` (a ``LibRawFatalError``; for a truncated file only when
  the pixels are unpacked, not at ``imread``), not a RAW (random bytes, JPEG,
  PNG, RGB TIFF) ``LibRawFileUnsupportedError`` (a ``LibRawNonFatalError``).
  From a memory buffer a file one byte short decodes silently with the last
  pixel wrong.

References
----------
Adobe, *Digital Negative (DNG) Specification*, version 1.4.0.0 (2012),
chapter 4 (tags) and chapter 6 (mapping camera colour space to XYZ).
Wandell (1985) [docs/references.md#seed-002], eq. 12.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CAMERA_MAKE_MODEL",
    "DngTruth",
    "SpectralScene",
    "cfa_colour_indices",
    "color_matrix_for_camera",
    "d50_xyz",
    "mosaic",
    "scene_dng",
    "spectral_scene",
    "write_dng",
    "write_linear_dng",
]

#: Canonical camera name (``models.camera_names``) -> (Make, Model) strings
#: as the real cameras write them, so that the service's RAW-metadata
#: matching (``models.canonical_camera_name(make + " " + model)``) finds the
#: measured sensitivities.
CAMERA_MAKE_MODEL = {
    "Nikon 5100 (NPL)": ("NIKON CORPORATION", "NIKON D5100"),
    "Canon EOS 5D Mark II": ("Canon", "Canon EOS 5D Mark II"),
    "Sigma SDMerill (NPL)": ("SIGMA", "SIGMA SD1 Merrill"),
}

# TIFF/DNG tag codes (DNG specification 1.4, chapter 4).
from service.dngwrite import (_COLOUR_CODE, _PHOTOMETRIC_CFA, _TAG_AS_SHOT_NEUTRAL, _TAG_BLACK_LEVEL,  # noqa: E402,F401
                               _TAG_BLACK_LEVEL_REPEAT_DIM, _TAG_ORIENTATION, _TAG_CALIBRATION_ILLUMINANT1, _TAG_CFA_PATTERN, _TAG_COLOR_MATRIX1, _TAG_MAKE,
                               _TAG_MODEL, _TAG_WHITE_LEVEL, _ascii, _level_tag, _pattern_letters, _rational,
                               _rationals, cfa_colour_indices)
from service.dngwrite import write_dng as _write_dng  # noqa: E402



# --------------------------------------------------------------------------
# CFA patterns and mosaicking
# --------------------------------------------------------------------------

def mosaic(rgb, pattern="RGGB") -> np.ndarray:
    """Sample a full-RGB camera image through a 2x2 colour filter array.

    ``cfa[y, x] = rgb[y, x, P[y mod 2, x mod 2]]`` with ``P`` the pattern's
    colour codes (:func:`cfa_colour_indices`).

    Parameters
    ----------
    rgb : (H, W, 3) array_like
        Linear camera response (any dtype).
    pattern : str or array_like
        As :func:`cfa_colour_indices`.

    Returns
    -------
    numpy.ndarray
        ``(H, W)``, dtype of ``rgb``.

    Examples
    --------
    >>> rgb = np.zeros((2, 4, 3)); rgb[..., 0] = 1; rgb[..., 1] = 2; rgb[..., 2] = 3
    >>> mosaic(rgb, "RGGB").tolist()
    [[1.0, 2.0, 1.0, 2.0], [2.0, 3.0, 2.0, 3.0]]
    """
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"mosaic needs an (H, W, 3) image, got shape {img.shape}")
    codes = cfa_colour_indices(pattern)
    out = np.empty(img.shape[:2], dtype=img.dtype)
    for dy in (0, 1):
        for dx in (0, 1):
            out[dy::2, dx::2] = img[dy::2, dx::2, int(codes[dy, dx])]
    return out


# --------------------------------------------------------------------------
# The DNG writer
# --------------------------------------------------------------------------

def _default_color_matrix() -> np.ndarray:
    """XYZ -> linear sRGB (camera space taken as sRGB), normalised as the DNG
    SDK's NormalizeColorMatrix does (D50 white -> camera max 1)."""
    import colour

    m = np.linalg.inv(np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, float))
    return _normalise_color_matrix(m)


def d50_xyz() -> np.ndarray:
    """CIE XYZ of D50 (CIE 1931 2 degree, Y = 1): the white of the DNG ColorMatrix tags."""
    import colour

    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D50"]
    return np.asarray(colour.xy_to_XYZ(xy), float)


def _normalise_color_matrix(m: np.ndarray) -> np.ndarray:
    """Scale an XYZ->camera matrix so the D50 white (Y = 1) maps to a camera
    vector whose largest entry is 1 (DNG SDK ``NormalizeColorMatrix``)."""
    top = float(np.max(m @ d50_xyz()))
    if top <= 0:
        raise ValueError("colour matrix maps the D50 white to no positive camera response")
    return m / top


def write_dng(path, cfa, *, color_matrix1=None, **kw) -> None:
    """:func:`service.dngwrite.write_dng` (the product's writer; see it for
    the tags and parameters), with ColorMatrix1 by default XYZ -> linear sRGB
    from colour-science's sRGB matrix (:func:`_default_color_matrix`) and this
    module named as the Software.

    Examples
    --------
    >>> import io, tifffile
    >>> buf = io.BytesIO()
    >>> write_dng(buf, np.zeros((24, 32), np.uint16))
    >>> tifffile.TiffFile(io.BytesIO(buf.getvalue())).pages[0].tags["Software"].value
    'wandell-recovery testing.dngwriter'
    """
    kw.setdefault("software", "wandell-recovery testing.dngwriter")
    _write_dng(path, cfa, color_matrix1=_default_color_matrix() if color_matrix1 is None else color_matrix1, **kw)


# --------------------------------------------------------------------------
# Colour matrix of a measured camera
# --------------------------------------------------------------------------

def color_matrix_for_camera(camera: str, wavelengths=None, *, training: str = "all",
                            illuminant: str = "D65") -> np.ndarray:
    """An XYZ -> camera 3x3 matrix (DNG ColorMatrix) for a measured camera.

    Least squares over colour-science's reflectances under ``illuminant``:
    with :math:`X_i = \\sum_n E S_i \\bar{x} \\Delta\\lambda` (CIE 1931 2°
    CMFs) and :math:`C_i = \\sum_n E S_i R \\Delta\\lambda` (camera), the
    matrix :math:`M` minimises :math:`\\sum_i \\lVert M X_i - C_i \\rVert^2`
    subject to mapping the illuminant's own white exactly,
    :math:`M X_w = C_w` (a white-preserving fit, solved per camera row with a
    Lagrange multiplier). It is then scaled as the DNG SDK's
    ``NormalizeColorMatrix`` does: the D50 white (Y = 1) maps to a camera
    vector whose largest entry is 1. A three-channel camera that is not a
    linear transform of the CMFs (none is) gets only the best 3x3 fit.

    Parameters
    ----------
    camera : str
        One of ``models.camera_names()``.
    wavelengths : array_like, optional
        Grid; default 400-700 nm at 5 nm.
    training : str
        A ``models.reflectance_set`` name (default ``"all"``: ColorChecker,
        rawtoaces 190, TCS and CQS samples, 267 reflectances).
    illuminant : str
        Calibration light (default D65, CalibrationIlluminant1 = 21).

    Returns
    -------
    numpy.ndarray
        ``(3, 3)``, rows camera R, G, B; columns X, Y, Z.

    Examples
    --------
    >>> m = color_matrix_for_camera("Nikon 5100 (NPL)")
    >>> m.shape, round(float(np.max(m @ d50_xyz())), 6)
    ((3, 3), 1.0)
    """
    import models

    wl = models.wavelength_grid(400, 700, 5) if wavelengths is None else np.asarray(wavelengths, float)
    dl = models.wavelength_step(wl)
    cam = models.camera_sensitivities(camera, wl)
    cmf = models.observer("CIE 1931 2 Degree Standard Observer", wl)
    e = models.illuminant(illuminant, wl) * dl
    refl = models.reflectance_set(training, wl)
    X = (refl * e) @ cmf          # (M, 3) XYZ of the training surfaces
    C = (refl * e) @ cam          # (M, 3) camera response
    xw, cw = e @ cmf, e @ cam     # the illuminant's white
    # KKT system of min ||X b - c||^2 s.t. xw . b = cw_k, for all rows at once
    kkt = np.zeros((4, 4))
    kkt[:3, :3] = 2.0 * X.T @ X
    kkt[:3, 3] = xw
    kkt[3, :3] = xw
    rhs = np.vstack([2.0 * X.T @ C, cw[None, :]])
    sol = np.linalg.solve(kkt, rhs)
    m = sol[:3, :].T              # rows: camera channels
    return _normalise_color_matrix(m)


# --------------------------------------------------------------------------
# Spectral scenes
# --------------------------------------------------------------------------

@dataclass
class SpectralScene:
    """A synthetic scene with known truth (see :func:`spectral_scene`).

    Attributes
    ----------
    image : (H, W, 3) float32 or None
        Linear camera RGB as a fraction of the range ``white - black``,
        noisy, clipped to [0, 1]; ``None`` when not rendered.
    labels : (H, W) int16
        Region index of every pixel into ``reflectances``/``patch_rgb``.
    reflectances : (P, N) float64
        Reflectance of every region; the last region is the frame.
    patch_names : list of str
    shading : (P,) float64
        Shading factor of each region (1 for the grid layout).
    patch_rgb : (P, 3) float64
        Noiseless camera response of each region, in image units.
    light_rgb : (3,) float64
        Camera response to the light (a perfect white, unshaded), image units.
    wavelengths, illuminant_spd, sensitivities : numpy.ndarray
        The spectral data used, ``(N,)``, ``(N,)``, ``(N, 3)``.
    camera, illuminant : str
    exposure_scale : float
        :math:`\\kappa`, image units per unit of :math:`\\sum E S R \\Delta\\lambda`.
    noise_multiplicative, noise_additive : float
        Standard deviations of the noise (relative, and in image units).
    seed : int
    """

    image: np.ndarray | None
    labels: np.ndarray
    reflectances: np.ndarray
    patch_names: list
    shading: np.ndarray
    patch_rgb: np.ndarray
    light_rgb: np.ndarray
    wavelengths: np.ndarray
    illuminant_spd: np.ndarray
    sensitivities: np.ndarray
    camera: str
    illuminant: str
    exposure_scale: float
    noise_multiplicative: float
    noise_additive: float
    seed: int

    @property
    def light_rgb_normalised(self) -> np.ndarray:
        """``light_rgb`` with green = 1 (the AsShotNeutral convention)."""
        return self.light_rgb / self.light_rgb[1]

    def patch_index(self, name_contains: str) -> int:
        """Index of the first region whose name contains ``name_contains``."""
        for i, n in enumerate(self.patch_names):
            if name_contains in n:
                return i
        raise KeyError(f"no patch named like {name_contains!r}")


def _edges(n: int, parts: int) -> np.ndarray:
    return np.round(np.linspace(0, n, parts + 1)).astype(int)


def _grid_labels(height, width, n_patches, grid, gap, frame):
    if grid is None:
        cols = max(1, int(np.ceil(np.sqrt(n_patches * width / height))))
        rows = int(np.ceil(n_patches / cols))
    else:
        rows, cols = (int(g) for g in grid)
    if rows * cols < n_patches:
        raise ValueError(f"grid {rows}x{cols} has fewer cells than {n_patches} patches")
    if not (0.0 <= gap < 1.0):
        raise ValueError(f"gap must be in [0, 1), got {gap}")
    ye, xe = _edges(height, rows), _edges(width, cols)
    labels = np.full((height, width), frame, dtype=np.int16)
    for p in range(n_patches):
        r, c = divmod(p, cols)
        y0, y1, x0, x1 = ye[r], ye[r + 1], xe[c], xe[c + 1]
        my, mx = int(round((y1 - y0) * gap / 2)), int(round((x1 - x0) * gap / 2))
        labels[y0 + my:y1 - my, x0 + mx:x1 - mx] = p
    return labels


def _mondrian_labels(height, width, n_regions, rng):
    labels = np.zeros((height, width), dtype=np.int16)
    for p in range(1, n_regions):
        h = max(1, int(rng.uniform(0.1, 0.5) * height))
        w = max(1, int(rng.uniform(0.1, 0.5) * width))
        y0 = int(rng.integers(0, max(1, height - h + 1)))
        x0 = int(rng.integers(0, max(1, width - w + 1)))
        labels[y0:y0 + h, x0:x0 + w] = p
    return labels


def _visible_regions(labels: np.ndarray, n: int) -> np.ndarray:
    """Which of ``n`` regions own at least one pixel (row blocks, so a
    24-megapixel int16 map is never cast to intp whole)."""
    counts = np.zeros(n, dtype=np.int64)
    step = max(1, (1 << 20) // max(1, labels.shape[1]))
    for y in range(0, labels.shape[0], step):
        counts += np.bincount(labels[y:y + step].ravel(), minlength=n)[:n]
    return counts > 0


def _noise_streams(seed: int):
    """One generator for the layout and one per (CFA site parity, channel):
    stream ``1 + 3 * (2 * (y % 2) + x % 2) + c``, so a CFA rendered directly
    draws exactly the noise the full image has at those sites."""
    children = np.random.SeedSequence(int(seed)).spawn(13)
    return np.random.default_rng(children[0]), [np.random.default_rng(s) for s in children[1:]]


def _add_noise(v: np.ndarray, rng, mult: float, add: float) -> np.ndarray:
    """``clip(v (1 + m n1) + a n2, 0, 1)`` in float32, in place on ``v``."""
    if mult > 0:
        v *= 1.0 + np.float32(mult) * rng.standard_normal(v.shape, dtype=np.float32)
    if add > 0:
        v += np.float32(add) * rng.standard_normal(v.shape, dtype=np.float32)
    np.clip(v, 0.0, 1.0, out=v)
    return v


def _scene_layout(camera, illuminant, height, width, seed, surfaces, layout, grid, gap,
                  n_surfaces, shading_range, exposure, frame_reflectance, wavelengths):
    import models

    if height < 2 or width < 2:
        raise ValueError(f"scene must be at least 2x2, got {height}x{width}")
    if not (0.0 < exposure <= 1.0):
        raise ValueError(f"exposure must be in (0, 1], got {exposure}")
    wl = models.wavelength_grid(400, 700, 5) if wavelengths is None else np.asarray(wavelengths, float)
    dl = models.wavelength_step(wl)
    canon = models.canonical_camera_name(camera)
    if canon is None:
        raise KeyError(f"unknown camera {camera!r}; accepted: {models.camera_names()}")
    sens = models.camera_sensitivities(canon, wl)
    spd = models.illuminant(illuminant, wl)
    if isinstance(surfaces, str):
        refl, names = models.reflectance_set(surfaces, wl, return_names=True)
    else:
        refl = np.atleast_2d(np.asarray(surfaces, dtype=np.float64))
        if refl.shape[1] != wl.size:
            raise ValueError(f"surfaces must be (M, {wl.size}) on the wavelength grid, got {refl.shape}")
        names = [f"surface {i}" for i in range(refl.shape[0])]
    rng_layout, streams = _noise_streams(seed)

    if layout == "grid":
        n = refl.shape[0] if n_surfaces is None else int(n_surfaces)
        pick = np.arange(n) % refl.shape[0]
        labels = _grid_labels(height, width, n, grid, gap, frame=n)
        shading = np.ones(n)
    elif layout == "mondrian":
        n = 16 if n_surfaces is None else int(n_surfaces)
        pick = rng_layout.choice(refl.shape[0], size=n, replace=n > refl.shape[0])
        labels = _mondrian_labels(height, width, n, rng_layout)
        shading = rng_layout.uniform(*shading_range, size=n)
    else:
        raise ValueError(f"layout must be 'grid' or 'mondrian', not {layout!r}")
    frame = np.full((1, wl.size), float(frame_reflectance))
    reflectances = np.vstack([refl[pick], frame])
    patch_names = [names[i] for i in pick] + [f"frame (flat {frame_reflectance:g})"]
    shading = np.append(shading, 1.0)

    e = spd * dl
    region_rgb = shading[:, None] * ((reflectances * e) @ sens)
    visible = _visible_regions(labels, len(patch_names))
    top = float(region_rgb[visible].max())
    if top <= 0:
        raise ValueError("the scene has no positive camera response")
    k = exposure / top
    return dict(labels=labels, reflectances=reflectances, patch_names=patch_names, shading=shading,
                patch_rgb=k * region_rgb, light_rgb=k * (e @ sens), wavelengths=wl,
                illuminant_spd=spd, sensitivities=sens, camera=canon, illuminant=illuminant,
                exposure_scale=k), streams


def spectral_scene(
    camera: str = "Nikon 5100 (NPL)",
    illuminant: str = "D65",
    height: int = 64,
    width: int = 96,
    seed: int = 0,
    *,
    surfaces="colorchecker",
    layout: str = "grid",
    grid=None,
    gap: float = 0.2,
    n_surfaces: int | None = None,
    shading_range=(0.5, 1.0),
    exposure: float = 0.9,
    noise_multiplicative: float = 0.01,
    noise_additive: float = 0.0005,
    frame_reflectance: float = 0.05,
    wavelengths=None,
    render: bool = True,
) -> SpectralScene:
    """A scene of known surfaces under a known light, seen by a measured camera.

    Every region ``p`` has reflectance :math:`S_p`, shading :math:`s_p`; its
    noiseless response is
    :math:`\\rho_p = \\kappa s_p \\sum_n E S_p R \\Delta\\lambda`, with
    :math:`\\kappa` chosen so that the brightest visible region's largest
    channel equals ``exposure``. The rendered image is
    :math:`\\mathrm{clip}(\\rho (1 + m n_1) + a n_2, 0, 1)` with
    :math:`n_1, n_2` standard normal (``m``, ``a`` the multiplicative and
    additive noise; DESIGN.md's benchmark uses 0.01 and 0.0005).

    Parameters
    ----------
    camera : str
        ``"Nikon 5100 (NPL)"``, ``"Sigma SDMerill (NPL)"`` or ``"Canon EOS 5D Mark II"``.
    illuminant : str
        A ``models.illuminant`` name (``"D65"``, ``"A"``, ``"FL11"``, ``"D5000"``, ...).
    height, width : int
        Image size in pixels (6000x4000 sensors: ``height=4000, width=6000``).
    seed : int
        Seeds the Mondrian layout and the noise.
    surfaces : str or (M, N) array_like
        A ``models.reflectance_set`` name, or reflectances on the grid.
    layout : {"grid", "mondrian"}
        ``grid``: the surfaces in order in a rows x cols chart (ColorChecker:
        4 x 6 when ``grid=(4, 6)``), each cell's central part a patch, the rest
        frame. ``mondrian``: ``n_surfaces`` (default 16) surfaces drawn at
        random, the first filling the image, the others random rectangles
        (10-50 % of each side) painted over it, each with a random shading in
        ``shading_range``.
    grid : (rows, cols), optional
        Default: about square cells.
    gap : float
        Fraction of a cell's side that is frame (split on both sides).
    exposure : float
        Brightest noiseless value, as a fraction of the range.
    noise_multiplicative, noise_additive : float
        Noise standard deviations (0 for none).
    frame_reflectance : float
        Spectrally flat reflectance of the frame (the last region).
    wavelengths : array_like, optional
        Grid; default 400-700 nm at 5 nm.
    render : bool
        Build the ``(H, W, 3)`` image (12 bytes a pixel); ``False`` leaves
        ``image`` ``None`` and keeps only the truth.

    Returns
    -------
    SpectralScene

    Examples
    --------
    >>> sc = spectral_scene("Canon EOS 5D Mark II", "A", 32, 48, grid=(4, 6))
    >>> sc.image.shape, sc.labels.max(), len(sc.patch_names)
    ((32, 48, 3), 24, 25)
    >>> round(float(sc.patch_rgb.max()), 6)
    0.9
    """
    truth, streams = _scene_layout(camera, illuminant, height, width, seed, surfaces, layout, grid,
                                   gap, n_surfaces, shading_range, exposure, frame_reflectance,
                                   wavelengths)
    image = None
    if render:
        rgb32 = truth["patch_rgb"].astype(np.float32)
        image = rgb32[truth["labels"]]
        for dy in (0, 1):
            for dx in (0, 1):
                for c in range(3):
                    block = np.ascontiguousarray(image[dy::2, dx::2, c])
                    _add_noise(block, streams[3 * (2 * dy + dx) + c],
                               noise_multiplicative, noise_additive)
                    image[dy::2, dx::2, c] = block
    return SpectralScene(image=image, noise_multiplicative=float(noise_multiplicative),
                         noise_additive=float(noise_additive), seed=int(seed), **truth)


# --------------------------------------------------------------------------
# A DNG of a spectral scene
# --------------------------------------------------------------------------

@dataclass
class DngTruth:
    """What :func:`scene_dng` wrote, and the truth behind it.

    Attributes
    ----------
    path : str
    camera, illuminant : str
        Canonical camera name and light.
    make, model : str
    pattern : str
        CFA pattern letters, e.g. ``"RGGB"``.
    black_level, white_level : int
    light_rgb : (3,) float64
        True camera RGB of the light, green = 1.
    as_shot_neutral : (3,) float64 or None
        AsShotNeutral as written (equal to ``light_rgb`` unless a wrong one
        was asked for).
    color_matrix1 : (3, 3) float64
        ColorMatrix1 as intended (stored as SRATIONAL to about 1e-9).
    light_rgb_scene : (3,) float64
        Camera response to the light in image units (fraction of
        ``white - black``), as :attr:`SpectralScene.light_rgb`.
    patch_rgb : (P, 3) float64
        Noiseless response of each region, image units.
    patch_names : list of str
    reflectances : (P, N) float64
    wavelengths : (N,) float64
    labels : (H, W) int16
    exposure_scale, noise_multiplicative, noise_additive : float
    seed : int
    """

    path: str
    camera: str
    illuminant: str
    make: str
    model: str
    pattern: str
    black_level: int
    white_level: int
    light_rgb: np.ndarray
    as_shot_neutral: np.ndarray | None
    color_matrix1: np.ndarray
    light_rgb_scene: np.ndarray
    patch_rgb: np.ndarray
    patch_names: list
    reflectances: np.ndarray
    wavelengths: np.ndarray
    labels: np.ndarray = field(repr=False)
    exposure_scale: float = 1.0
    noise_multiplicative: float = 0.0
    noise_additive: float = 0.0
    seed: int = 0

    def patch_index(self, name_contains: str) -> int:
        """Index of the first region whose name contains ``name_contains``."""
        for i, n in enumerate(self.patch_names):
            if name_contains in n:
                return i
        raise KeyError(f"no patch named like {name_contains!r}")


def _quantise(v: np.ndarray, black: float, white: float) -> np.ndarray:
    """``round(black + v (white - black))`` as uint16, in place on float32 ``v``."""
    v *= np.float32(white - black)
    v += np.float32(black)
    np.rint(v, out=v)
    np.clip(v, 0, white, out=v)
    return v.astype(np.uint16)


def scene_dng(
    path,
    camera_name: str = "Nikon 5100 (NPL)",
    illuminant_name: str = "D65",
    height: int = 64,
    width: int = 96,
    seed: int = 0,
    *,
    pattern="RGGB",
    black_level: int = 512,
    white_level: int = 16383,
    exposure: float = 0.9,
    noise_multiplicative: float = 0.01,
    noise_additive: float = 0.0005,
    as_shot_neutral="truth",
    color_matrix1=None,
    make: str | None = None,
    model: str | None = None,
    surfaces="colorchecker",
    layout: str = "grid",
    grid=None,
    gap: float = 0.2,
    n_surfaces: int | None = None,
    wavelengths=None,
) -> DngTruth:
    """Write a DNG of a :func:`spectral_scene` and return its truth.

    The CFA is rendered site by site (never the full RGB image) with the same
    noise streams as :func:`spectral_scene`, so for equal arguments
    ``raw_image == round(black + mosaic(scene.image) * (white - black))``
    exactly, while a 6000x4000 file needs only the label map, the CFA and a
    quarter-size float buffer.

    Parameters
    ----------
    path : str, os.PathLike or binary file object
    camera_name, illuminant_name, height, width, seed
        As :func:`spectral_scene`.
    pattern : str
        CFA pattern.
    black_level, white_level : int
        Digital numbers of zero and of full scale (14-bit: 16383).
    exposure, noise_multiplicative, noise_additive
        As :func:`spectral_scene`, in fractions of ``white - black``.
    as_shot_neutral : "truth", str, (3,) array_like or None
        ``"truth"``: the camera's response to the true light, green = 1.
        Another string: the response to that named illuminant (a wrong white
        balance, e.g. ``"A"`` for a daylight scene). An array: written as
        given. ``None``: the tag is omitted.
    color_matrix1 : (3, 3) array_like, optional
        Default :func:`color_matrix_for_camera` (least squares under D65).
    make, model : str, optional
        Default from :data:`CAMERA_MAKE_MODEL`.
    surfaces, layout, grid, gap, n_surfaces, wavelengths
        As :func:`spectral_scene`.

    Returns
    -------
    DngTruth

    Examples
    --------
    >>> import io, rawpy
    >>> buf = io.BytesIO()
    >>> t = scene_dng(buf, "Nikon 5100 (NPL)", "A", 32, 48, seed=1)
    >>> with rawpy.imread(io.BytesIO(buf.getvalue())) as raw:
    ...     wb = np.array(raw.camera_whitebalance[:3])
    >>> bool(np.allclose(wb, 1 / t.light_rgb, rtol=1e-5))
    True
    """
    import models

    truth, streams = _scene_layout(camera_name, illuminant_name, height, width, seed, surfaces,
                                   layout, grid, gap, n_surfaces, (0.5, 1.0), exposure, 0.05,
                                   wavelengths)
    black, white = int(black_level), int(white_level)
    if not (0 <= black < white <= 65535):
        raise ValueError(f"need 0 <= black_level < white_level <= 65535, got {black}, {white}")
    codes = cfa_colour_indices(pattern)
    labels = truth["labels"]
    rgb32 = truth["patch_rgb"].astype(np.float32)
    cfa = np.empty(labels.shape, dtype=np.uint16)
    for dy in (0, 1):
        for dx in (0, 1):
            c = int(codes[dy, dx])
            v = rgb32[labels[dy::2, dx::2], c]
            _add_noise(v, streams[3 * (2 * dy + dx) + c], noise_multiplicative, noise_additive)
            cfa[dy::2, dx::2] = _quantise(v, black, white)
            del v

    light = truth["light_rgb"] / truth["light_rgb"][1]
    if isinstance(as_shot_neutral, str):
        if as_shot_neutral == "truth":
            neutral = light
        else:
            e = models.illuminant(as_shot_neutral, truth["wavelengths"])
            neutral = (e * models.wavelength_step(truth["wavelengths"])) @ truth["sensitivities"]
            neutral = neutral / neutral[1]
    elif as_shot_neutral is None:
        neutral = None
    else:
        neutral = np.asarray(as_shot_neutral, dtype=np.float64).ravel()

    cm = (color_matrix_for_camera(truth["camera"], truth["wavelengths"])
          if color_matrix1 is None else np.asarray(color_matrix1, float))
    default_make, default_model = CAMERA_MAKE_MODEL.get(truth["camera"], ("wandell-recovery", truth["camera"]))
    mk = default_make if make is None else make
    md = default_model if model is None else model

    write_dng(path, cfa, pattern=codes, black_level=black, white_level=white, color_matrix1=cm,
              calibration_illuminant1=21, as_shot_neutral=neutral, make=mk, model=md)
    return DngTruth(
        path=os.fspath(path) if isinstance(path, (str, os.PathLike)) else getattr(path, "name", "<stream>"),
        camera=truth["camera"], illuminant=illuminant_name, make=mk, model=md,
        pattern=_pattern_letters(codes), black_level=black, white_level=white,
        light_rgb=light, as_shot_neutral=None if neutral is None else np.array(neutral, float),
        color_matrix1=cm, light_rgb_scene=truth["light_rgb"], patch_rgb=truth["patch_rgb"],
        patch_names=truth["patch_names"], reflectances=truth["reflectances"],
        wavelengths=truth["wavelengths"], labels=labels, exposure_scale=truth["exposure_scale"],
        noise_multiplicative=float(noise_multiplicative), noise_additive=float(noise_additive),
        seed=int(seed),
    )


# --------------------------------------------------------------------------
# LinearRaw (demosaiced) DNGs
# --------------------------------------------------------------------------

#: ``write_linear_dng``'s compression names -> TIFF Compression codes
LINEAR_COMPRESSIONS = {"none": 1, "adobe_deflate": 8, "deflate": 32946}


def write_linear_dng(path, rgb, *, black_level=0, white_level=None, color_matrix1=None,
                     as_shot_neutral=(0.5, 1.0, 0.6), make: str = "wandell-recovery",
                     model: str = "synthetic LinearRaw", compression: str = "none", predictor: bool = False,
                     tile=None, rows_per_strip: int | None = 16, orientation: int = 1, default_crop=None,
                     linearization=None, as_shot_white_xy=None, color_matrix2=None) -> None:
    """Write a LinearRaw DNG (PhotometricInterpretation 34892: three
    demosaiced samples per pixel, chunky) of ``rgb`` with ``tifffile``: the
    layout Adobe DNG Converter's linear option writes, in any of the
    encodings the service reads.

    Tags written: NewSubfileType 0, the image's size, BitsPerSample and
    SampleFormat of ``rgb``'s dtype, Compression, Predictor (when asked),
    strips (RowsPerStrip) or tiles, Orientation, Make, Model, DNGVersion
    1.4.0.0, DNGBackwardVersion 1.1.0.0, UniqueCameraModel, ColorMatrix1,
    CalibrationIlluminant1 21 (D65), BlackLevelRepeatDim (1, 1), BlackLevel
    (one value or one per sample), WhiteLevel, AsShotNeutral (when given),
    AsShotWhiteXY, ColorMatrix2 with CalibrationIlluminant2 17 (light A),
    DefaultCropOrigin/Size and LinearizationTable when given.

    Parameters
    ----------
    path : str, os.PathLike or binary file object
    rgb : (H, W, 3) uint8, uint16, uint32, float16 or float32
        The samples as stored (``black_level`` .. ``white_level``).
    black_level : float or (3,) array_like
    white_level : int, optional
        Default: the dtype's maximum, 1 for floats.
    color_matrix1 : (3, 3) array_like, optional
        XYZ -> camera; default XYZ -> linear sRGB normalised as the DNG SDK does.
    as_shot_neutral : (3,) array_like or None
    as_shot_white_xy : (2,) array_like, optional
        AsShotWhiteXY (the as-shot white as a chromaticity; the DNG
        specification makes it exclusive with AsShotNeutral: pass
        ``as_shot_neutral=None`` with it).
    color_matrix2 : (3, 3) array_like, optional
        XYZ -> camera under light A (CalibrationIlluminant2 17).
    compression : {"none", "adobe_deflate", "deflate"}
        Compression 1, 8 or 32946 (:data:`LINEAR_COMPRESSIONS`).
    predictor : bool
        With deflate: horizontal differencing (2) for integers, the
        floating-point predictor (3) for floats.
    tile : (int, int), optional
        Tile length and width (multiples of 16); strips of ``rows_per_strip``
        rows otherwise.
    orientation : int
        TIFF Orientation (1-8).
    default_crop : (top, left, height, width), optional
        DefaultCropOrigin (left, top) and DefaultCropSize (width, height).
    linearization : (N,) array_like of uint16, optional
        LinearizationTable (integer samples).

    References
    ----------
    Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (2012), chapter 4
    (PhotometricInterpretation 34892, the tags above) and chapter 5.
    """
    import tifffile

    from service.dngwrite import _srgb_color_matrix

    rgb = np.ascontiguousarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got {rgb.shape}")
    if compression not in LINEAR_COMPRESSIONS:
        raise ValueError(f"compression must be one of {sorted(LINEAR_COMPRESSIONS)}, not {compression!r}")
    if white_level is None:
        white_level = 1 if rgb.dtype.kind == "f" else int(np.iinfo(rgb.dtype).max)
    cm = _srgb_color_matrix() if color_matrix1 is None else np.asarray(color_matrix1, float)
    tags = [(_TAG_MAKE, "s", 0, _ascii("make", make), True), (_TAG_MODEL, "s", 0, _ascii("model", model), True),
            (_TAG_ORIENTATION, "H", 1, int(orientation), True),
            (50706, "B", 4, (1, 4, 0, 0), True), (50707, "B", 4, (1, 1, 0, 0), True),
            (50708, "s", 0, f"{make} {model}", True),
            (_TAG_COLOR_MATRIX1, "2i", 9, _rationals(cm, signed=True), True),
            (_TAG_CALIBRATION_ILLUMINANT1, "H", 1, 21, True),
            (_TAG_BLACK_LEVEL_REPEAT_DIM, "H", 2, (1, 1), True),
            _level_tag(_TAG_BLACK_LEVEL, np.atleast_1d(black_level)),
            _level_tag(_TAG_WHITE_LEVEL, [white_level])]
    if as_shot_neutral is not None:
        tags.append((_TAG_AS_SHOT_NEUTRAL, "2I", 3, _rationals(as_shot_neutral, signed=False), True))
    if as_shot_white_xy is not None:
        tags.append((50729, "2I", 2, _rationals(as_shot_white_xy, signed=False), True))
    if color_matrix2 is not None:
        tags += [(50722, "2i", 9, _rationals(np.asarray(color_matrix2, float), signed=True), True),
                 (50779, "H", 1, 17, True)]
    if default_crop is not None:
        top, left, h, w = (int(v) for v in default_crop)
        tags += [(50719, "I", 2, (left, top), True), (50720, "I", 2, (w, h), True)]
    if linearization is not None:
        lin = np.asarray(linearization, np.uint16).ravel()
        tags.append((50712, "H", lin.size, tuple(int(v) for v in lin), True))
    kw = dict(photometric=34892, subfiletype=0, planarconfig="contig", metadata=None, extratags=tags,
              software="wandell-recovery", compression=None if compression == "none" else
              {"adobe_deflate": "zlib", "deflate": "deflate"}[compression])
    if predictor:
        if compression == "none":
            raise ValueError("a predictor needs a deflate compression")
        kw["predictor"] = True
    if tile is not None:
        kw["tile"] = tuple(int(v) for v in tile)
    else:
        kw["rowsperstrip"] = int(rows_per_strip or rgb.shape[0])
    tifffile.imwrite(path, rgb, **kw)
