"""Whether an upload's pixels are display-referred, from its colour tags: the ICC profile
embedded in a TIFF (tag 34675) or a PNG (``iCCP``), and a PNG's ``sRGB``, ``gAMA`` and
``cICP`` chunks; and the linearisation of such pixels through their own tone curves.

The service estimates the light from *linear* camera RGB. A rendered file (the
service's own 16-bit sRGB TIFF, an editor's export) carries a profile whose tone
reproduction curves (TRC) say its code values are gamma encoded; read as linear,
such a file gave 2725 K with only a generic warning (issue 19, item 12).

Only as much of the profile is read as that decision needs: the header (size, class,
colour space, PCS, ``acsp``), the tag table, ``rTRC``/``gTRC``/``bTRC``
(``curv`` or ``para``), ``rXYZ``/``gXYZ``/``bXYZ`` and ``desc``. A TRC maps a
device code value to a value linear in light (the matrix/TRC model: PCS XYZ =
``[rXYZ gXYZ bXYZ] @ [rTRC(R), gTRC(G), bTRC(B)]``), so linearising applies the
curve itself (what a colour-management module does going device -> PCS); the
inverse curve is the encoding that made the file.

Policy (:func:`display_referred_policy`, the ``display_referred`` option):

* linear (every TRC the identity to :data:`LINEAR_TOLERANCE`, ``gAMA`` 1.0,
  ``cICP`` transfer 8): decoded as before, and said to be linear by its profile;
* display-referred, ``linearise`` (the default): the code values are put through
  the profile's TRC, and the warnings say so, naming the profile, and that an
  estimate from rendered (already white-balanced, tone-mapped) data is not a
  camera measurement;
* display-referred, ``refuse``: 415 ``display_referred_input`` naming the
  profile and how to send linear data instead;
* a profile that cannot be linearised (no TRCs, e.g. a LUT-based profile; not
  RGB): 415 ``display_referred_input``, whatever the option; a damaged one:
  422 ``corrupt_icc_profile``.

The primaries (``rXYZ``, ``gXYZ``, ``bXYZ``, taken back from D50 through ``chad``)
are applied the way a DNG's ColorMatrix is: the decoded image's ``color_matrix`` is
the profile's XYZ -> RGB (:meth:`Encoding.xyz_to_rgb`; sRGB's for a PNG ``sRGB``
chunk), for a linear profile as for a linearised one. The pixels are not converted:
the service takes a TIFF/PNG's RGB as the camera RGB of the camera the request names
(``camera=``) or the file's Make/Model (:mod:`recovery.cameras`), and without a
measured camera it now derives one from that matrix ("approximate: derived from
colour matrix") instead of the generic camera. That is what the profile says the RGB
means; the generic camera reads sRGB as a camera's RGB: the service's own sRGB
render of ``Blackmagic.dng`` (4590 K, CIE xy (0.361, 0.379)) read that way gave
1710 K linearised and 2136 K not, against 5198 K (xy 0.026 away) linearised with the
profile's matrix (``tests/test_display_referred_input.py``). ``camera=...`` still
overrides it.

References
----------
ICC.1:2001-04 (profile version 2.4): clause 6.1 (profile header), 6.2 (tag table),
6.4 (tag definitions: rTRC, rXYZ, profileDescriptionTag), 6.5 (tag types: curveType,
textDescriptionType, XYZType).
ICC.1:2010 (version 4.3): clause 7.2 (header), 7.3 (tag table), 9.2 (tag
definitions), 10 (tag types: curveType, parametricCurveType with its function types
0-4 and their parameters g, a, b, c, d, e, f, multiLocalizedUnicodeType, XYZType).
W3C PNG Specification (Third Edition): 11.3.2 (``cICP``, ``gAMA``, ``iCCP``, ``sRGB``
and their precedence: ``cICP`` over ``iCCP`` over ``sRGB`` over ``gAMA``).
IEC 61966-2-1:1999 (sRGB transfer function). ITU-T H.273 (coding-independent code
points: TransferCharacteristics 8 linear, 13 sRGB).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import ServiceError

__all__ = ["Encoding", "POLICIES", "LINEAR_TOLERANCE", "parse_icc", "png_encoding", "tiff_encoding",
           "display_referred_policy", "linearise", "srgb_to_linear"]

#: Values of the ``display_referred`` option.
POLICIES = ("linearise", "refuse")
#: A curve within this of the identity on [0, 1] (code value scale) is linear.
LINEAR_TOLERANCE = 1e-3
#: Largest embedded profile read (real RGB matrix/TRC profiles are a few KiB;
#: LUT profiles a few hundred KiB).
MAX_PROFILE_BYTES = 4 * 1024 * 1024
#: Samples of a curve evaluated for float input (between them: linear interpolation).
_FLOAT_GRID = 4096

_HOW_TO_LINEARISE = ("send the camera RAW, or a linear 16-bit or float TIFF/PNG (e.g. exported with a linear "
                     "profile such as linear sRGB)")


@dataclass
class Encoding:
    """What an upload's colour tags say about its code values.

    Attributes
    ----------
    source : str
        Where it was read: ``"ICC profile"``, ``"PNG sRGB chunk"``, ``"PNG gAMA chunk"``,
        ``"PNG cICP chunk"``.
    name : str
        The profile's description (``desc``), or what the chunk says.
    curves : list of callable
        One per channel: a code value in [0, 1] (array) to a linear value;
        ``None`` if the tags give no curve to linearise with.
    linear : bool
        Every curve is the identity to :data:`LINEAR_TOLERANCE`.
    info : dict
        Facts for the diagnostics (profile class, colour space, PCS, version,
        the TRC kinds, the primaries as PCS XYZ columns).
    """

    source: str
    name: str
    curves: list | None
    linear: bool
    info: dict = field(default_factory=dict)

    def xyz_to_rgb(self) -> np.ndarray | None:
        """The profile's XYZ -> RGB matrix for its own white (the colorants,
        PCS XYZ adapted to D50, taken back through ``chad``, else Bradford from
        the D65 of sRGB-like profiles), ``None`` without colorants."""
        prim = self.info.get("primaries_pcs_xyz")
        if prim is None:
            if self.source in ("PNG sRGB chunk", "PNG cICP chunk") and self.curves is not None:
                from recovery.dng_color import rgb_to_xyz_matrix   # sRGB / BT.709 primaries, D65

                return np.linalg.inv(rgb_to_xyz_matrix("sRGB"))
            return None
        m = np.array(prim, dtype=np.float64).T            # columns: rXYZ, gXYZ, bXYZ
        chad = self.info.get("chad")
        if chad is not None:
            m = np.linalg.solve(np.array(chad, dtype=np.float64), m)
        else:
            from recovery.dng_color import D50_XY, PRIMARIES, bradford

            m = bradford(D50_XY, PRIMARIES["sRGB"][1]) @ m
        if not np.all(np.isfinite(m)) or abs(np.linalg.det(m)) < 1e-9:
            return None
        return np.linalg.inv(m)

    def describe(self) -> dict:
        """The encoding as plain data for the result's diagnostics."""
        return {"source": self.source, "name": self.name, "linear": self.linear, **self.info}


# --------------------------------------------------------------------------- curves
def srgb_to_linear(v):
    """The sRGB decoding (IEC 61966-2-1): code value in [0, 1] to linear."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _gamma(g: float):
    return lambda x: np.power(np.clip(x, 0.0, None), g)


def _sampled(table: np.ndarray):
    grid = np.linspace(0.0, 1.0, table.size)
    return lambda x: np.interp(x, grid, table)


def _parametric(ftype: int, p: list):
    """parametricCurveType function ``ftype`` (ICC.1:2010, clause 10, table of
    function types 0-4) with parameters ``g, a, b, c, d, e, f``."""
    g = p[0]

    def powpart(x, a, b):
        return np.power(np.clip(a * x + b, 0.0, None), g)

    if ftype == 0:
        return lambda x: np.power(np.clip(x, 0.0, None), g)
    a, b = p[1], p[2]
    if a == 0:
        raise ValueError("parametric curve with a = 0")
    if ftype == 1:
        return lambda x: np.where(x >= -b / a, powpart(x, a, b), 0.0)
    if ftype == 2:
        c = p[3]
        return lambda x: np.where(x >= -b / a, powpart(x, a, b) + c, c)
    if ftype == 3:
        c, d = p[3], p[4]
        return lambda x: np.where(x >= d, powpart(x, a, b), c * x)
    c, d, e, f = p[3], p[4], p[5], p[6]
    return lambda x: np.where(x >= d, powpart(x, a, b) + e, c * x + f)


def _is_identity(curve) -> bool:
    x = np.linspace(0.0, 1.0, 1025)
    with np.errstate(all="ignore"):
        y = np.asarray(curve(x), dtype=np.float64)
    return bool(np.all(np.isfinite(y)) and np.max(np.abs(y - x)) <= LINEAR_TOLERANCE)


# --------------------------------------------------------------------------- ICC profile
def _bad(detail: str) -> ServiceError:
    return ServiceError(422, "corrupt_icc_profile", f"the embedded ICC profile is damaged: {detail}; remove it "
                        "or embed a valid one")


def _text(tag: bytes) -> str | None:
    """``desc`` as textDescriptionType (v2) or multiLocalizedUnicodeType (v4)."""
    from .tags import file_string

    kind = tag[:4]
    if kind == b"desc" and len(tag) >= 12:
        n = struct.unpack(">I", tag[8:12])[0]
        return file_string(tag[12:12 + min(n, 256)].split(b"\0")[0].decode("latin-1"))
    if kind == b"mluc" and len(tag) >= 16:
        count, size = struct.unpack(">II", tag[8:16])
        if count >= 1 and size >= 12 and len(tag) >= 28:
            length, offset = struct.unpack(">II", tag[20:28])
            raw = tag[offset:offset + min(length, 512)]
            return file_string(raw.decode("utf-16-be", errors="replace"))
    if kind == b"text":
        return file_string(tag[8:8 + 256].split(b"\0")[0].decode("latin-1"))
    return None


def _curve(tag: bytes, sig: str):
    """A TRC tag (curveType or parametricCurveType) to ``(callable, kind)``."""
    kind = tag[:4]
    if kind == b"curv":
        if len(tag) < 12:
            raise _bad(f"{sig} is shorter than its header")
        n = struct.unpack(">I", tag[8:12])[0]
        if len(tag) < 12 + 2 * n:
            raise _bad(f"{sig} declares {n} entries and holds {(len(tag) - 12) // 2}")
        if n == 0:
            return (lambda x: np.asarray(x, dtype=np.float64)), "identity"
        if n == 1:
            g = struct.unpack(">H", tag[12:14])[0] / 256.0       # u8Fixed8Number
            if g <= 0:
                raise _bad(f"{sig} has gamma {g}")
            return _gamma(g), f"gamma {g:.4g}"
        table = np.frombuffer(tag, ">u2", n, 12).astype(np.float64) / 65535.0
        return _sampled(table), f"{n}-entry table"
    if kind == b"para":
        if len(tag) < 12:
            raise _bad(f"{sig} is shorter than its header")
        ftype = struct.unpack(">H", tag[8:10])[0]
        nparams = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}.get(ftype)
        if nparams is None:
            raise _bad(f"{sig} has parametric function type {ftype} (0-4 exist)")
        if len(tag) < 12 + 4 * nparams:
            raise _bad(f"{sig} (function type {ftype}) lacks its {nparams} parameters")
        p = [v / 65536.0 for v in struct.unpack(f">{nparams}i", tag[12:12 + 4 * nparams])]   # s15Fixed16
        if not p[0] > 0:
            raise _bad(f"{sig} has gamma {p[0]}")
        try:
            return _parametric(ftype, p), f"parametric type {ftype} (gamma {p[0]:.4g})"
        except ValueError as exc:
            raise _bad(f"{sig}: {exc}") from None
    raise _bad(f"{sig} is of type {kind!r}, not curv or para")


def parse_icc(profile: bytes) -> Encoding:
    """Read an ICC profile's header, tag table, TRCs, colorants and description.

    Parameters
    ----------
    profile : bytes
        The profile as embedded (TIFF tag 34675, a PNG's decompressed ``iCCP``).

    Returns
    -------
    Encoding
        ``curves`` is ``None`` when the profile has no ``rTRC``/``gTRC``/``bTRC``
        (a LUT-based or grey profile): nothing here can linearise it.

    Raises
    ------
    ServiceError
        422 ``corrupt_icc_profile``: shorter than its header or its declared size,
        no ``acsp`` signature, a tag outside the profile, a malformed TRC.
    """
    n = len(profile)
    if n < 132:
        raise _bad(f"{n} bytes, shorter than the 128-byte header and tag count")
    size, = struct.unpack(">I", profile[:4])
    if profile[36:40] != b"acsp":
        raise _bad("no 'acsp' signature at byte 36")
    if size > n:
        raise _bad(f"the header declares {size} bytes and {n} are embedded (truncated)")
    version = f"{profile[8]}.{profile[9] >> 4}"
    pclass = profile[12:16].decode("latin-1").strip()
    space = profile[16:20].decode("latin-1").strip()
    pcs = profile[20:24].decode("latin-1").strip()
    count, = struct.unpack(">I", profile[128:132])
    if 132 + 12 * count > n:
        raise _bad(f"its tag table declares {count} tags, more than the profile holds")
    tags = {}
    for i in range(count):
        sig, off, length = struct.unpack(">4sII", profile[132 + 12 * i:144 + 12 * i])
        if off + length > n or length < 8:
            raise _bad(f"tag {sig.decode('latin-1')!r} at bytes {off}..{off + length} lies outside the "
                       f"{n}-byte profile")
        tags[sig] = profile[off:off + length]
    name = (_text(tags[b"desc"]) if b"desc" in tags else None) or "unnamed ICC profile"
    info = {"profile_class": pclass, "color_space": space, "pcs": pcs, "version": version}
    prim = []
    for sig in (b"rXYZ", b"gXYZ", b"bXYZ"):
        t = tags.get(sig)
        if t is not None and t[:4] == b"XYZ " and len(t) >= 20:
            prim.append([v / 65536.0 for v in struct.unpack(">3i", t[8:20])])
    if len(prim) == 3:
        info["primaries_pcs_xyz"] = prim
    t = tags.get(b"chad")
    if t is not None and t[:4] == b"sf32" and len(t) >= 44:
        info["chad"] = (np.array(struct.unpack(">9i", t[8:44]), dtype=np.float64) / 65536.0).reshape(3, 3).tolist()
    trcs = [tags.get(s) for s in (b"rTRC", b"gTRC", b"bTRC")]
    if space != "RGB" or any(t is None for t in trcs):
        info["trc"] = None
        return Encoding("ICC profile", name, None, False, info)
    curves, kinds = zip(*(_curve(t, s) for t, s in zip(trcs, ("rTRC", "gTRC", "bTRC"))))
    info["trc"] = list(kinds)
    return Encoding("ICC profile", name, list(curves), all(_is_identity(c) for c in curves), info)


# --------------------------------------------------------------------------- TIFF and PNG
def tiff_encoding(page) -> Encoding | None:
    """The encoding a TIFF page's ICC profile (tag 34675) declares, ``None`` without one."""
    t = page.tags.get(34675)
    if t is None:
        return None
    value = t.value
    if isinstance(value, (tuple, list, np.ndarray)):
        value = bytes(np.asarray(value, np.uint8))
    if not isinstance(value, (bytes, bytearray)):
        raise _bad(f"TIFF tag 34675 holds {type(value).__name__}, not bytes")
    return parse_icc(bytes(value))


def png_encoding(chunks: dict) -> Encoding | None:
    """The encoding a PNG's colour chunks declare (``cICP`` over ``iCCP`` over
    ``sRGB`` over ``gAMA``, PNG Third Edition 11.3.2), ``None`` without any.

    Parameters
    ----------
    chunks : dict
        Chunk type (bytes) -> its data (bytes), the first of each type.
    """
    if b"cICP" in chunks and len(chunks[b"cICP"]) >= 2:
        tc = chunks[b"cICP"][1]
        if tc == 8:
            return Encoding("PNG cICP chunk", "cICP transfer 8 (linear)", [lambda x: x] * 3, True)
        if tc == 13:
            return Encoding("PNG cICP chunk", "cICP transfer 13 (sRGB)", [srgb_to_linear] * 3, False)
        return Encoding("PNG cICP chunk", f"cICP transfer characteristics {tc}", None, False)
    if b"iCCP" in chunks:
        data = chunks[b"iCCP"]
        nul = data.find(b"\0", 0, 80)
        if nul < 1 or len(data) < nul + 2 or data[nul + 1] != 0:
            raise _bad("the PNG iCCP chunk has no profile name or an unknown compression method")
        try:
            z = zlib.decompressobj()
            profile = z.decompress(data[nul + 2:], MAX_PROFILE_BYTES + 1)
        except zlib.error as exc:
            raise _bad(f"the PNG iCCP chunk does not inflate ({exc})") from None
        if len(profile) > MAX_PROFILE_BYTES:
            raise _bad(f"the PNG iCCP profile inflates to more than {MAX_PROFILE_BYTES} bytes")
        return parse_icc(profile)
    if b"sRGB" in chunks:
        return Encoding("PNG sRGB chunk", "sRGB", [srgb_to_linear] * 3, False)
    if b"gAMA" in chunks and len(chunks[b"gAMA"]) == 4:
        g = struct.unpack(">I", chunks[b"gAMA"])[0] / 100000.0
        if g <= 0:
            raise ServiceError(422, "corrupt_file", "the PNG gAMA chunk declares gamma 0")
        # gAMA is the encoding exponent: sample = linear ** g, so linear = sample ** (1 / g)
        linear = abs(g - 1.0) <= 0.01
        curve = (lambda x: x) if linear else _gamma(1.0 / g)
        return Encoding("PNG gAMA chunk", f"gamma {g:.5g}", [curve] * 3, linear,
                        {"gamma": g})
    return None


# --------------------------------------------------------------------------- policy
def display_referred_policy(enc: Encoding | None, policy: str, label: str) -> list[str]:
    """Apply the ``display_referred`` policy to an upload's encoding (before its
    pixels are decoded): the warnings to attach, or the refusal.

    Raises
    ------
    ServiceError
        415 ``display_referred_input``: display-referred and ``policy`` is
        ``refuse``, or display-referred with no curve to linearise with.
    """
    if enc is None:
        return []
    if enc.linear:
        return []
    if enc.curves is None:
        why = ("it has no rTRC/gTRC/bTRC tone curves (a LUT-based or non-RGB profile)"
               if enc.source == "ICC profile" else "its transfer function is not one the service decodes")
        raise ServiceError(415, "display_referred_input",
                           f"{label} carries {enc.source} {enc.name!r}, which says its values are display-"
                           f"referred (rendered), and {why}, so it cannot be linearised here; {_HOW_TO_LINEARISE}")
    if policy == "refuse":
        raise ServiceError(415, "display_referred_input",
                           f"{label} is display-referred: its {enc.source} {enc.name!r} has a non-linear tone "
                           "curve (gamma-encoded, rendered values), and display_referred=refuse; "
                           f"{_HOW_TO_LINEARISE}, or send display_referred=linearise to decode it through "
                           "its own tone curve")
    kinds = enc.info.get("trc")
    curves = "" if not kinds else f" ({kinds[0] if len(set(kinds)) == 1 else ', '.join(kinds)})"
    return [f"display-referred input: linearised through the tone curve of its {enc.source} {enc.name!r}"
            f"{curves}; "
            "the light estimated from rendered data (already white-balanced and tone-mapped by whatever "
            "made the file, in the profile's RGB rather than a camera's) is not a camera measurement"]


def linearise(arr: np.ndarray, enc: Encoding, out: np.ndarray) -> None:
    """Put an image's code values through ``enc``'s curves, into ``out``
    (``(h, w, 3)`` float32): uint16 through a 65536-entry table per channel,
    float by interpolation on :data:`_FLOAT_GRID` samples of [0, 1] (values
    outside it clamped to the curve's ends)."""
    h = arr.shape[0]
    if arr.dtype == np.uint16:
        x = np.arange(65536, dtype=np.float64) / 65535.0
        luts = [np.asarray(c(x), dtype=np.float32) for c in enc.curves]
        for ch, lut in enumerate(luts):
            for r in range(0, h, 256):
                out[r:r + 256, :, ch] = lut[arr[r:r + 256, :, ch]]
        return
    grid = np.linspace(0.0, 1.0, _FLOAT_GRID)
    for ch, c in enumerate(enc.curves):
        ys = np.asarray(c(grid), dtype=np.float64)
        for r in range(0, h, 256):
            out[r:r + 256, :, ch] = np.interp(arr[r:r + 256, :, ch], grid, ys)
