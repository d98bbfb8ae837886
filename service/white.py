"""The white a corrected image is rendered for: the estimate, the camera's
as-shot white, or a white given as Camera Raw Temperature/Tint (the web
page's sliders, ``white=5200/+10``).

A Temperature/Tint is a chromaticity on Adobe's scale
(:func:`recovery.dng_color.temperature_tint_to_xy`, Robertson's
isotemperature lines as in the DNG SDK). It becomes the camera's response to
that white the same way the service reports Temperature/Tint, so that the
reported values given back render the estimate again:

* through the file's colour matrices when it has them (DNG SDK
  ``FindXYZtoCamera`` at that white, then ``XYZtoCamera @ XYZ(white)``: the
  inverse of ``NeutralToXY``, :func:`recovery.dng_color.neutral_to_xy`);
* else through the camera's sensitivities: the 3-term CIE daylight-model
  light (Judd, MacAdam & Wyszecki 1964) whose XYZ is that white's, and its
  camera response (the light :func:`service.pipeline.run_with_white` fits
  back from that response is this same light, so its xy is the given one).
"""

from __future__ import annotations

import re

from .errors import ServiceError   # numpy only inside the functions: `wandell --help` imports this module

__all__ = ["WHITE_HELP", "TEMPERATURE_RANGE", "TINT_RANGE", "parse_white", "check_white", "white_from_temperature_tint",
           "with_white", "as_shot_temperature_tint"]

#: Temperature (K) and Tint a white may be given with (Camera Raw's slider ranges).
TEMPERATURE_RANGE = (2000.0, 50000.0)
TINT_RANGE = (-150.0, 150.0)
WHITE_HELP = ("estimate (this service's light, or neutral), as-shot (the camera's own white, rendered the same way, "
              "to compare) or TEMPERATURE/TINT on Camera Raw's scale, e.g. 5200/+10 (a white you set: "
              f"{TEMPERATURE_RANGE[0]:.0f}..{TEMPERATURE_RANGE[1]:.0f} K, tint {TINT_RANGE[0]:+.0f}..{TINT_RANGE[1]:+.0f})")
_TT = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*K?\s*/\s*([+-]?\d+(?:\.\d+)?)\s*$")


def parse_white(value: str):
    """``"estimate"``, ``"as-shot"``, or ``(temperature, tint)`` from
    ``"5200/+10"`` (422 ``invalid_parameter`` naming the accepted forms).

    >>> parse_white("5200/+10"), parse_white("as-shot")
    ((5200.0, 10.0), 'as-shot')
    """
    if value in ("estimate", "as-shot"):
        return value
    m = _TT.match(str(value))
    if not m:
        raise ServiceError(422, "invalid_parameter", f"white must be estimate, as-shot or TEMPERATURE/TINT "
                           f"(e.g. 5200/+10), not {value!r}")
    t, tint = float(m.group(1)), float(m.group(2))
    (t0, t1), (n0, n1) = TEMPERATURE_RANGE, TINT_RANGE
    if not (t0 <= t <= t1 and n0 <= tint <= n1):
        raise ServiceError(422, "invalid_parameter", f"white {value!r}: the temperature must be in {t0:.0f}..{t1:.0f} "
                           f"K and the tint in {n0:+.0f}..{n1:+.0f}")
    return t, tint


def check_white(value, name, choices):
    """The ``white`` option's check (:mod:`service.schemas.fields`): the
    value as given, once :func:`parse_white` accepts it."""
    parse_white(value)
    return value


def white_from_temperature_tint(decoded, run, temperature: float, tint: float):
    """The camera's response (C,) to the white of ``temperature``/``tint``
    (module docstring: the file's matrices, else the camera's sensitivities)."""
    import numpy as np
    from recovery.dng_color import temperature_tint_to_xy, xy_to_xyz, xyz_to_camera

    from recovery.api import resolve_model

    from .pipeline import profile_of

    xy = temperature_tint_to_xy(temperature, tint)
    profile = profile_of(decoded)
    cam = run.camera
    if profile is not None and cam.channels == 3:
        cm, *_ = xyz_to_camera(profile, xy)
        return np.asarray(cm @ xy_to_xyz(xy), float)
    from models import observer

    wl = cam.wavelengths
    B = resolve_model("daylight", "light", 3, wl).basis               # (N, 3)
    A = observer("XYZ", wl).T @ B                                      # XYZ of each basis light
    w = np.linalg.solve(A, xy_to_xyz(xy))
    return np.asarray(cam.response(B @ w), float)


def with_white(decoded, run, white: str):
    """The run whose light renders the image: ``run`` itself (the estimate,
    or the user's neutral surface), the file's own as-shot white (422
    ``no_as_shot_white`` without a usable one), or a Temperature/Tint
    (:func:`white_from_temperature_tint`)."""
    import numpy as np

    from .pipeline import run_with_white

    w = parse_white(white)
    if w == "estimate":
        return run
    if w == "as-shot":
        if decoded.as_shot_neutral is None:
            why = getattr(decoded, "as_shot_problem", None) or "the file records no as-shot white balance"
            raise ServiceError(422, "no_as_shot_white", f"white=as-shot: {why}")
        return run_with_white(run, decoded.as_shot_neutral, "as-shot")
    rgb = white_from_temperature_tint(decoded, run, *w)
    if not (np.all(np.isfinite(rgb)) and np.all(rgb > 0)):
        raise ServiceError(422, "invalid_parameter", f"white {white!r}: this camera has no positive response to "
                           "that white; choose a temperature and tint nearer the daylight locus")
    out = run_with_white(run, rgb, "temperature-tint")
    out.white = white
    return out


def as_shot_temperature_tint(decoded, run) -> dict:
    """The file's as-shot white as Temperature/Tint (``{}`` when the file
    records none or it is far from the Planckian locus): the same
    conversion as the estimate's (:func:`service.pipeline.temperature_tint`)."""
    import numpy as np

    from .pipeline import run_with_white, temperature_tint

    asn = decoded.as_shot_neutral
    if asn is None or not np.all(np.isfinite(asn)) or not np.all(np.asarray(asn, float) > 0):
        return {}
    try:
        tt = temperature_tint(decoded, run_with_white(run, asn, "as-shot"))
    except ServiceError:
        return {}
    return {"temperature": tt["temperature"], "tint": tt["tint"], "xy": tt.get("xy")}
