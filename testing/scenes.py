"""Synthetic scenes with known truth, shared by the tests and the benchmarks.

Mondrians of K surfaces (colour-science's reflectances, each a rectangle
with a random shading factor) under one light (:func:`mondrian_scene`,
:func:`draw_scene`: the scenes of the development benchmark,
``docs/DESIGN.md``, "The development benchmark") or two
(:func:`two_light_scene`, :func:`draw_two_light_scene`: a light that changes
across the image), seen by one of the shipped cameras, synthesised
spectrally on a 5 nm grid (Wandell 1985, eq. 12 [docs/references.md#seed-002]).
Not part of the product.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

import models
from recovery import Camera, angular_error

__all__ = ["MondrianScene", "kd_partition", "mondrian_scene", "scene_rng", "draw_scene", "LAYOUTS",
           "two_light_scene", "draw_two_light_scene", "grid_reflectances", "grid_sensitivities",
           "grid_illuminant", "named_camera"]


# --------------------------------------------------------------------------- data (cached)
@lru_cache(maxsize=None)
def grid_reflectances(step: float) -> np.ndarray:
    return models.reflectance_set("all", models.wavelength_grid(400, 700, step))


@lru_cache(maxsize=None)
def grid_sensitivities(camera_name: str, step: float) -> np.ndarray:
    return models.camera_sensitivities(camera_name, models.wavelength_grid(400, 700, step))


@lru_cache(maxsize=None)
def grid_illuminant(name: str, step: float) -> np.ndarray:
    return models.illuminant(name, models.wavelength_grid(400, 700, step))


@lru_cache(maxsize=None)
def named_camera(name: str) -> Camera:
    return Camera.named(name)


# --------------------------------------------------------------------------- scenes
@dataclass(frozen=True)
class MondrianScene:
    """One synthetic Mondrian and its truth.

    Attributes
    ----------
    image : (H, W, 3) float32, linear camera data in [0, 1]
    rgb_true : (3,) camera response to the illuminant (unit norm), on the
        synthesis grid: the truth of the angular error
    labels : (H, W) int, index into ``reflectances`` of the surface at each pixel
    reflectances : (K, N) surface reflectances on ``wavelengths``
    shading : (K,) shading factor of each surface
    surface_indices : (K,) rows of ``models.reflectance_set("all")``
    rects : (K, 4) int, ``(row0, row1, col0, col1)`` (half-open) of each surface
    illuminant : (N,) illuminant spectrum on ``wavelengths``, unit mean
    wavelengths : (N,) synthesis grid in nm
    camera_name, illuminant_name : str
    exposure : float, the factor that scaled the noiseless image to max 0.9
    """

    image: np.ndarray
    rgb_true: np.ndarray
    labels: np.ndarray
    reflectances: np.ndarray
    shading: np.ndarray
    surface_indices: np.ndarray
    rects: np.ndarray
    illuminant: np.ndarray
    wavelengths: np.ndarray
    camera_name: str
    illuminant_name: str
    exposure: float


def kd_partition(rng: np.random.Generator, shape: tuple[int, int], k: int, min_side: int = 4,
                 split_range: tuple[float, float] = (0.25, 0.75)) -> np.ndarray:
    """Split an ``(H, W)`` image into ``k`` rectangles by a random k-d split.

    Repeatedly pick a rectangle (probability proportional to its area, among
    those whose longer side can be split leaving ``min_side`` pixels on each
    side) and cut it across its longer side at a uniform fraction in
    ``split_range``.

    Returns
    -------
    (k, 4) int array of ``(row0, row1, col0, col1)``, half-open.

    Examples
    --------
    >>> r = kd_partition(np.random.default_rng(0), (64, 64), 8)
    >>> r.shape, int(((r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2])).sum())
    ((8, 4), 4096)
    """
    h, w = int(shape[0]), int(shape[1])
    rects = [(0, h, 0, w)]
    while len(rects) < k:
        sides = np.array([max(r1 - r0, c1 - c0) for r0, r1, c0, c1 in rects])
        ok = sides >= 2 * min_side
        if not ok.any():
            raise ValueError(f"cannot split a {h}x{w} image into {k} rectangles of side >= {min_side}")
        area = np.array([(r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in rects], float) * ok
        i = int(rng.choice(len(rects), p=area / area.sum()))
        r0, r1, c0, c1 = rects.pop(i)
        rows = r1 - r0 >= c1 - c0 if r1 - r0 != c1 - c0 else bool(rng.integers(2))
        lo, hi = (r0, r1) if rows else (c0, c1)
        cut = lo + int(round(rng.uniform(*split_range) * (hi - lo)))
        cut = min(max(cut, lo + min_side), hi - min_side)
        if rows:
            rects += [(r0, cut, c0, c1), (cut, r1, c0, c1)]
        else:
            rects += [(r0, r1, c0, cut), (r0, r1, cut, c1)]
    return np.array(rects, dtype=int)


def mondrian_scene(rng: np.random.Generator, k: int, camera_name: str, illuminant_name: str,
                   size: int = 64, *, shading: tuple[float, float] = (0.5, 1.0), peak: float = 0.9,
                   multiplicative_noise: float = 0.01, additive_noise: float = 0.0005,
                   step: float = 5.0, min_side: int = 4) -> MondrianScene:
    """A Mondrian of ``k`` rectangles under one light, seen by one camera.

    ``docs/DESIGN.md``, "The development benchmark". The ``k`` surfaces
    are drawn without replacement from ``models.reflectance_set("all")``;
    the image is cut into ``k`` rectangles by :func:`kd_partition`; each
    rectangle gets one surface and a shading factor uniform in ``shading``.
    Sensor values are the spectral sums (Wandell 1985, eq. 12 with
    :math:`\\Delta\\lambda`) ``rho_k = s sum_n E(l_n) S(l_n) R_k(l_n) dl`` on a
    ``step`` nm grid over 400-700 nm (exact per rectangle, since each is
    uniform). The image is then scaled so its maximum is ``peak``, given
    multiplicative ``(1 + multiplicative_noise * N(0, 1))`` and additive
    ``additive_noise * N(0, 1)`` noise per pixel and channel, and clipped
    to [0, 1].

    The function is pure: everything random comes from ``rng``.

    Parameters
    ----------
    rng : numpy.random.Generator
    k : int, number of surfaces
    camera_name : one of :func:`models.camera_names`
    illuminant_name : one of :func:`models.illuminant_names`
    size : int, image side in pixels (square image)

    Returns
    -------
    MondrianScene

    Examples
    --------
    >>> s = mondrian_scene(np.random.default_rng(1), 4, "Nikon 5100 (NPL)", "A", 32)
    >>> s.image.shape, s.image.dtype, s.reflectances.shape, sorted(np.unique(s.labels).tolist())
    ((32, 32, 3), dtype('float32'), (4, 61), [0, 1, 2, 3])
    """
    wl = models.wavelength_grid(400, 700, step)
    library = grid_reflectances(step)
    if not 1 <= k <= library.shape[0]:
        raise ValueError(f"k must be in 1..{library.shape[0]}, not {k}")
    R = grid_sensitivities(camera_name, step) * models.wavelength_step(wl)[:, None]   # (N, 3), with dl
    E = grid_illuminant(illuminant_name, step)
    idx = rng.choice(library.shape[0], size=k, replace=False)
    refl = library[idx]
    rects = kd_partition(rng, (size, size), k, min_side)
    shade = rng.uniform(shading[0], shading[1], size=k)
    labels = np.empty((size, size), dtype=int)
    for j, (r0, r1, c0, c1) in enumerate(rects):
        labels[r0:r1, c0:c1] = j
    rgb_surf = shade[:, None] * ((E * refl) @ R)                                 # (K, 3)
    img = rgb_surf[labels]
    exposure = float(peak / img.max())
    img = img * exposure
    img = img * (1.0 + multiplicative_noise * rng.standard_normal(img.shape))
    img = img + additive_noise * rng.standard_normal(img.shape)
    img = np.clip(img, 0.0, 1.0).astype(np.float32)
    truth = E @ R
    return MondrianScene(img, truth / np.linalg.norm(truth), labels, refl, shade, idx, rects, E, wl,
                         camera_name, illuminant_name, exposure)


def scene_rng(seed: int, k: int, index: int) -> np.random.Generator:
    """The generator of scene ``index`` with ``k`` surfaces: independent of
    how many scenes or which K are run, so tables are reproducible."""
    return np.random.default_rng([int(seed), int(k), int(index)])


def draw_scene(seed: int, k: int, index: int, size: int = 64) -> MondrianScene:
    """Scene ``index`` of the benchmark for ``k`` surfaces: camera and
    illuminant drawn uniformly from all shipped ones, then
    :func:`mondrian_scene`."""
    rng = scene_rng(seed, k, index)
    cams = models.camera_names()
    lights = models.illuminant_names()
    cam = cams[int(rng.integers(len(cams)))]
    light = lights[int(rng.integers(len(lights)))]
    return mondrian_scene(rng, k, cam, light, size)


LAYOUTS = ("halves", "gradient")


def _mix_field(rng: np.random.Generator, size: int, layout: str) -> np.ndarray:
    """The fraction ``a(x)`` of light B at each pixel, ``(size, size)``."""
    r, c = np.mgrid[0:size, 0:size].astype(float) + 0.5
    if layout == "halves":
        cut = rng.uniform(0.35, 0.65) * size
        a = (c >= cut) if rng.integers(2) else (r >= cut)
        return a.astype(float)
    if layout == "gradient":
        kind = int(rng.integers(3))
        t = c / size if kind == 0 else (r / size if kind == 1 else (r + c) / (2 * size))
        return t
    raise ValueError(f"layout must be one of {LAYOUTS}, not {layout!r}")


def two_light_scene(rng: np.random.Generator, k: int, camera_name: str, light_a: str, light_b: str,
                    layout: str, size: int = 64, *, shading=(0.5, 1.0), peak: float = 0.9,
                    multiplicative_noise: float = 0.01, additive_noise: float = 0.0005, step: float = 5.0):
    """A development-benchmark Mondrian lit by two lights.

    As :func:`mondrian_scene` (Wandell 1985, eq. 12 on a
    ``step`` nm grid, the same noise and scaling), but the light at pixel
    ``x`` is ``(1 - a(x)) E_A + a(x) E_B`` (unit-mean spectra), so the sensor
    value is ``s_j [(1 - a) rho_A,j + a rho_B,j]``: light is additive.

    Returns
    -------
    image : (size, size, 3) float32 in [0, 1]
    truth : (size, size, 3) unit camera response to the light at each pixel
    separation : angle (deg) between the two lights' camera responses
    """
    wl = models.wavelength_grid(400, 700, step)
    library = grid_reflectances(step)
    R = grid_sensitivities(camera_name, step) * models.wavelength_step(wl)[:, None]
    Ea, Eb = grid_illuminant(light_a, step), grid_illuminant(light_b, step)
    idx = rng.choice(library.shape[0], size=k, replace=False)
    refl = library[idx]
    rects = kd_partition(rng, (size, size), k, 4)
    shade = rng.uniform(shading[0], shading[1], size=k)
    labels = np.empty((size, size), dtype=int)
    for j, (r0, r1, c0, c1) in enumerate(rects):
        labels[r0:r1, c0:c1] = j
    a = _mix_field(rng, size, layout)[..., None]
    rho_a = shade[:, None] * ((Ea * refl) @ R)
    rho_b = shade[:, None] * ((Eb * refl) @ R)
    img = (1 - a) * rho_a[labels] + a * rho_b[labels]
    img = img * (peak / img.max())
    img = img * (1.0 + multiplicative_noise * rng.standard_normal(img.shape))
    img = img + additive_noise * rng.standard_normal(img.shape)
    img = np.clip(img, 0.0, 1.0).astype(np.float32)
    ea, eb = Ea @ R, Eb @ R
    truth = (1 - a) * ea + a * eb
    truth = truth / np.linalg.norm(truth, axis=2, keepdims=True)
    return img, truth, float(angular_error(ea, eb))


def draw_two_light_scene(seed: int, k: int, index: int, layout: str, size: int = 64,
                         min_separation: float = 3.0):
    """Two-light scene ``index``: camera and two lights drawn uniformly from
    the shipped ones (as :func:`draw_scene`), redrawn until
    the lights are more than ``min_separation`` degrees apart for that
    camera. Independent of the uniform scenes (its own generator)."""
    rng = np.random.default_rng([int(seed), int(k), int(index), 2, LAYOUTS.index(layout)])
    cams = models.camera_names()
    lights = models.illuminant_names()
    cam = cams[int(rng.integers(len(cams)))]
    R = grid_sensitivities(cam, 5.0)
    for _ in range(1000):
        la, lb = (lights[int(i)] for i in rng.choice(len(lights), 2, replace=False))
        if angular_error(grid_illuminant(la, 5.0) @ R, grid_illuminant(lb, 5.0) @ R) > min_separation:
            break
    img, truth, sep = two_light_scene(rng, k, cam, la, lb, layout, size)
    return img, truth, sep, cam, la, lb
