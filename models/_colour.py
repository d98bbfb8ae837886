"""Private helpers turning colour-science spectral objects into arrays, and
the shipped cache of what the hot path takes from colour-science.

Importing colour-science costs about 0.6 s (it also imports Matplotlib when
installed), more than the whole analysis of a photograph (issue 19). The
functions of :mod:`models` (and the encoding LUT of :mod:`service.correction`, which
registers itself here when imported)
that the CLI and the service call with the same arguments every time are
wrapped in :func:`cached`: their results for those arguments ship in
``models/data/colour_cache.npz``, computed by colour-science itself
(``python -m benchmarks.build_colour_cache``). A call whose arguments are not in the file
runs the wrapped function (and so colour-science) as before, and so does every
call with ``WANDELL_NO_COLOUR_CACHE=1`` in the environment. The test
``tests/test_colour_cache.py`` recomputes every entry from colour-science and
asserts exact equality, so the file cannot drift from the library.

CCT/Duv (Ohno 2013) is :func:`uv_to_CCT_Ohno2013`: colour-science's algorithm
written out with numpy over its Planckian table, the table itself shipped in
the same file.
"""

from __future__ import annotations

import functools
import os
import threading
from pathlib import Path

import numpy as np

from .grid import DEFAULT_WAVELENGTHS, resample

CACHE_FILE = Path(__file__).with_name("data") / "colour_cache.npz"

_REGISTRY: dict = {}      # function name -> the uncached function
_cache: dict | None = None  # key -> index in the file
_npz = None
_recording: dict | None = None  # while building: key -> value
_lock = threading.RLock()


def sd_to_array(sd, wavelengths=None) -> np.ndarray:
    """A colour ``SpectralDistribution`` or ``MultiSpectralDistributions``
    as a float64 array on ``wavelengths`` (``(N,)`` or ``(N, K)``)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return resample(np.asarray(sd.wavelengths, float), np.asarray(sd.values, float), wl)


def _plain(v):
    """An argument as a hashable literal (``repr`` round-trips it)."""
    if isinstance(v, np.ndarray):
        return tuple(float(x) for x in v.ravel().tolist()) if v.ndim == 1 else None
    if isinstance(v, (tuple, list)):
        return tuple(_plain(x) for x in v)
    if isinstance(v, (bool, str, type(None))):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    return _Unkeyable


class _Unkeyable:  # an argument no key can name: never cached
    pass


def make_key(name: str, args: tuple) -> str | None:
    plain = tuple(_plain(a) for a in args)
    if any(p is _Unkeyable or (p is None and a is not None) for p, a in zip(plain, args)):
        return None
    return f"{name}{plain!r}"


def _index() -> dict:
    global _cache, _npz
    if _cache is None:
        with _lock:
            if _cache is None:
                index = {}
                if CACHE_FILE.exists() and not os.environ.get("WANDELL_NO_COLOUR_CACHE"):
                    _npz = np.load(CACHE_FILE, allow_pickle=False)
                    index = {k: i for i, k in enumerate(_npz["keys"].tolist())}
                _cache = index
    return _cache


def _decode(arr: np.ndarray):
    if arr.dtype.kind == "U":
        return str(arr) if arr.ndim == 0 else arr.tolist()
    return arr.copy()


def _get(i: int):
    with _lock:  # one reader of the zip at a time (the service's threads)
        n = int(_npz[f"n{i}"])
        if n < 0:
            return _decode(_npz[f"v{i}_0"])
        return tuple(_decode(_npz[f"v{i}_{j}"]) for j in range(n))


def lookup(key: str):
    """The cached value of ``key`` or ``KeyError``."""
    i = _index()[key]
    return _get(i)


def cached(name: str):
    """Serve ``fn(*args)`` from the shipped file when its positional
    arguments are in it (keyword arguments bypass the cache)."""

    def deco(fn):
        _REGISTRY[name] = fn

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            key = None if kwargs else make_key(name, args)
            if key is not None and _recording is None:
                idx = _index()
                if key in idx:
                    return _get(idx[key])
            out = fn(*args, **kwargs)
            if key is not None and _recording is not None:
                _recording[key] = out
            return out

        return wrapper

    return deco


# --- Ohno (2013) CCT/Duv, colour-science's algorithm over its shipped table --

_OHNO_KEY = "planckian_table_ohno2013(CIE 1931 2 Degree Standard Observer, 1000, 100000, 1.001)"


def _ohno_table_from_colour() -> np.ndarray:
    import colour
    from colour.temperature.ohno2013 import (CCT_DEFAULT_SPACING_OHNO2013, CCT_MAXIMAL_OHNO2013,
                                             CCT_MINIMAL_OHNO2013, planckian_table)
    from colour.colorimetry import handle_spectral_arguments

    cmfs, _ = handle_spectral_arguments(None)
    assert cmfs.name == "CIE 1931 2 Degree Standard Observer", cmfs.name
    assert (CCT_MINIMAL_OHNO2013, CCT_MAXIMAL_OHNO2013, CCT_DEFAULT_SPACING_OHNO2013) == (1000, 100000, 1.001)
    del colour
    return np.asarray(planckian_table(cmfs, CCT_MINIMAL_OHNO2013, CCT_MAXIMAL_OHNO2013,
                                      CCT_DEFAULT_SPACING_OHNO2013), float)


@functools.lru_cache(maxsize=1)
def _ohno_table() -> np.ndarray:
    try:
        t = lookup(_OHNO_KEY)
    except KeyError:
        t = _ohno_table_from_colour()
    t.flags.writeable = False
    return t


def xy_to_UCS_uv(xy) -> np.ndarray:
    """CIE 1960 UCS uv of CIE xy (colour-science's ``xy_to_UCS_uv``:
    xy -> XYZ with Y = 1 -> UCS -> uv)."""
    xy = np.asarray(xy, float)
    x, y = xy[..., 0], xy[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        Y = np.ones_like(x)
        X = x * Y / y
        Z = (1 - x - y) * Y / y
    X, Y, Z = np.where(y == 0, 0.0, X), np.where(y == 0, 0.0, Y), np.where(y == 0, 0.0, Z)
    U, V, W = 2 / 3 * X, Y, 1 / 2 * (-X + 3 * Y + Z)
    s = U + V + W
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = U / s, V / s
    return np.stack([u, v], -1)


def uv_to_CCT_Ohno2013(uv) -> np.ndarray:
    """CCT (K) and Duv of CIE 1960 uv by Ohno (2013), exactly as
    colour-science's ``colour.temperature.uv_to_CCT_Ohno2013`` with its
    defaults (CIE 1931 2 degree observer, 1000-100000 K, spacing 1.001), on
    the Planckian table colour-science computes (shipped in the cache)."""
    uv = np.asarray(uv, float)
    shape = uv.shape
    uv = np.reshape(uv, (-1, 2))
    table = _ohno_table()
    rows = []
    for uv_i in uv:
        dists = np.linalg.norm(table[:, 1:] - uv_i, axis=-1)
        index = int(np.argmin(dists))
        if index == 0:
            index += 1
        elif index == len(table) - 1:
            index -= 1
        rows.append(np.vstack([[*table[index - 1, ...], dists[index - 1]],
                               [*table[index, ...], dists[index]],
                               [*table[index + 1, ...], dists[index + 1]]]))
    tables = np.asarray(rows, float)
    Tip, uip, vip, dip = (tables[:, 0, k] for k in range(4))
    Ti, _ui, _vi, di = (tables[:, 1, k] for k in range(4))
    Tin, uin, vin, din = (tables[:, 2, k] for k in range(4))
    with np.errstate(divide="ignore", invalid="ignore"):
        l = np.hypot(uin - uip, vin - vip)  # noqa: E741
        x = (dip**2 - din**2 + l**2) / (2 * l)
        T_t = Tip + (Tin - Tip) * (x / l)
        vtx = vip + (vin - vip) * (x / l)
        sign = np.sign(uv[..., 1] - vtx)
        D_uv_t = (dip**2 - x**2) ** (1 / 2) * sign
        X = (Tin - Ti) * (Tip - Tin) * (Ti - Tip)
        a = (Tip * (din - di) + Ti * (dip - din) + Tin * (di - dip)) * X**-1
        b = -(Tip**2 * (din - di) + Ti**2 * (dip - din) + Tin**2 * (di - dip)) * X**-1
        c = -(dip * (Tin - Ti) * Ti * Tin + di * (Tip - Tin) * Tip * Tin + din * (Ti - Tip) * Tip * Ti) * X**-1
        T_p = -b / (2 * a)
        D_uv_p = (a * T_p**2 + b * T_p + c) * sign
    out = np.where((np.abs(D_uv_t) >= 0.002)[..., None], np.stack([T_p, D_uv_p], -1),
                   np.stack([T_t, D_uv_t], -1))
    return np.reshape(out, shape)


# --- building the file --------------------------------------------------------

def _modules():
    """The modules whose functions are cached (``models.illuminants`` the
    module, not the function :mod:`models` exports under that name)."""
    import importlib

    return tuple(importlib.import_module(f"models.{m}")
                 for m in ("displays", "illuminants", "observers", "reflectances", "cameras"))


def _record_defaults() -> None:
    """Call what every caller of :mod:`models` takes on every image, so that
    :data:`_recording` holds those results. What only the packages above
    call (the light posterior's candidates and loci, the service's encoding
    tables) is recorded by ``benchmarks.build_colour_cache``, which passes it
    as ``extra`` to :func:`build`: ``models`` imports neither ``recovery``
    nor ``service`` (issue 29)."""
    displays, illuminants, observers, reflectances, cameras = _modules()

    illuminants.illuminants()
    for k in ("fluorescent", "non-fluorescent"):
        illuminants.illuminant_names(k)
    illuminants.daylight_basis()
    for o in ("CIE 1931 2 Degree Standard Observer", "XYZ"):   # XYZ: a measured camera's rendering
        observers.observer(o)
    reflectances.reflectance_set("all")
    for d in ("sRGB",):
        displays.display(d)
    for name in cameras.camera_names():      # the measured cameras a RAW's make/model selects
        cameras.camera_sensitivities(name, DEFAULT_WAVELENGTHS)


def _encode(v) -> tuple[int, list]:
    if isinstance(v, tuple):
        return len(v), [np.asarray(x) for x in v]
    return -1, [np.asarray(v)]


def build(path: Path = CACHE_FILE, extra=None) -> dict:
    """Recompute every entry from colour-science and write ``path``;
    ``extra``: a callable run while recording (more calls to cache)."""
    global _recording, _cache, _npz
    _, illuminants, observers, _, _ = _modules()

    _recording, _cache, _npz = {}, {}, None
    illuminants._illuminant_cached.cache_clear()
    observers._observer_cached.cache_clear()
    try:
        _record_defaults()
        if extra is not None:
            extra()
        rec = dict(_recording)
    finally:
        _recording, _cache, _npz = None, None, None
        illuminants._illuminant_cached.cache_clear()
        observers._observer_cached.cache_clear()
    rec[_OHNO_KEY] = _ohno_table_from_colour()
    keys = sorted(rec)
    data = {"keys": np.array(keys)}
    for i, k in enumerate(keys):
        n, arrs = _encode(rec[k])
        data[f"n{i}"] = np.array(n)
        for j, a in enumerate(arrs):
            assert a.dtype != object, k
            data[f"v{i}_{j}"] = a
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **data)
    os.replace(tmp, path)
    return rec


def recompute(key: str):
    """``key``'s value computed now by colour-science (the uncached function).

    The functions of :mod:`models` register themselves here; a key of a
    package above (``service.pipeline._encoding_lut``, defined in
    :mod:`service.correction`) needs that module imported by the caller,
    since :mod:`models` never imports upwards."""
    import ast

    if key == _OHNO_KEY:
        return _ohno_table_from_colour()
    name, _, rest = key.partition("(")
    args = ast.literal_eval("(" + rest)
    _modules()
    if name not in _REGISTRY:   # a function of a package above (e.g. service.correction): import it first
        raise KeyError(f"{name} is not registered: import the module that defines it before recompute()")
    fn = _REGISTRY[name]
    args = tuple(np.asarray(a, float) if isinstance(a, tuple) else a for a in args)
    return fn(*args)
