"""What the output files carry so other tools read them right (issue 13,
item 3): an ICC profile of the output space, the source's EXIF facts and the
estimate; and an XMP sidecar with the white balance as Camera Raw's
Temperature/Tint.

ICC profiles (ICC.1:2001-04, version 2.1 display profiles, matrix/TRC) are
generated deterministically by :func:`icc_profile` and shipped as package
data (``service/icc/*.icc``, written by ``python -m service.outputs``); a
test checks the shipped bytes equal a fresh generation and that LittleCMS
(Pillow's ImageCms) reads them and maps colours as colour-science does.

EXIF (CIPA DC-008) is written as a little-endian TIFF structure (encoded
by Pillow's TIFF directory writer, :func:`exif_block`): IFD0 with
Make, Model, Orientation (always 1: the pixels are already rotated, so the
orientation is applied once), Software, DateTime, the source's own
ImageDescription if it had one (never the estimate: photo managers show
ImageDescription as the caption), and an EXIF sub-IFD with the exposure
facts of the source. JPEG gets it as APP1 ``Exif``, PNG as ``eXIf`` (PNG 1.5 extension),
TIFF as tags of its own IFD0. EXIF and TIFF text fields are 7-bit ASCII:
text that is not (a photographer named José, a camera model in another
script) is written there transliterated (:func:`ascii_text`) and whole, in
UTF-8, in an XMP packet (:func:`xmp_facts`: JPEG APP1
``http://ns.adobe.com/xap/1.0/``, PNG iTXt ``XML:com.adobe.xmp``, TIFF tag
700), so no metadata ever fails an image. The same packet carries the
estimate under the ``wandell:`` namespace (:data:`WANDELL_NS`: method,
camera RGB, multipliers, xy, CCT, Duv, confidence, and the whole summary as
JSON in ``wandell:Estimate``).
"""

from __future__ import annotations

import json
import struct
import zlib
from importlib import resources

import numpy as np

__all__ = ["icc_profile", "shipped_icc", "ICC_FOR_OUTPUT", "exif_block", "embed", "xmp_sidecar", "ascii_text",
           "xmp_facts", "XMP_KEY", "WANDELL_NS", "read_wandell_xmp"]

D50_XYZ = (0.9642, 1.0, 0.8249)      # the ICC PCS white (s15Fixed16 rounding of D50)

#: output name -> (ICC file, description, primaries, transfer). Primaries
#: ``display:NAME`` are a spectral display of :mod:`models.displays`: its
#: guns' CIE 1931 XYZ (:func:`recovery.synthesis.output_space` on the
#: default 400..700 nm grid, white Y = 1), its white their sum. Those
#: outputs hold linear gun intensities (no encoding, no tone curve:
#: :func:`recovery.synthesis.correction_matrix`), so their TRC is the
#: identity (gamma 1.0), whatever gamma a real CRT's drive values have.
ICC_SPACES = {
    "sRGB": ("sRGB.icc", "sRGB IEC61966-2.1 (wandell)", "sRGB", "srgb"),
    "linear-sRGB": ("linear-sRGB.icc", "Linear sRGB (wandell)", "sRGB", "linear"),
    "Display P3": ("DisplayP3.icc", "Display P3 (wandell)", "Display P3", "srgb"),
    "Typical CRT Brainard 1997": ("TypicalCRT-Brainard1997.icc", "Typical CRT Brainard 1997, linear (wandell)",
                                  "display:Typical CRT Brainard 1997", "linear"),
    "Apple Studio Display": ("AppleStudioDisplay.icc", "Apple Studio Display, linear (wandell)",
                             "display:Apple Studio Display", "linear"),
}
ICC_FOR_OUTPUT = {k: v[0] for k, v in ICC_SPACES.items()}


def _s15(v: float) -> bytes:
    return struct.pack(">i", int(round(v * 65536.0)))


def _xyz_tag(xyz) -> bytes:
    return b"XYZ " + b"\0" * 4 + b"".join(_s15(v) for v in xyz)


def _curv(kind: str) -> bytes:
    if kind == "linear":
        return b"curv" + b"\0" * 4 + struct.pack(">I", 0)       # count 0: identity
    x = np.linspace(0.0, 1.0, 1024)
    y = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)   # IEC 61966-2-1 decoding
    table = np.rint(y * 65535.0).astype(">u2").tobytes()
    return b"curv" + b"\0" * 4 + struct.pack(">I", 1024) + table


def _desc(text: str) -> bytes:
    a = text.encode("ascii") + b"\0"
    return (b"desc" + b"\0" * 4 + struct.pack(">I", len(a)) + a + struct.pack(">II", 0, 0)
            + struct.pack(">HB", 0, 0) + b"\0" * 67)


def _text(text: str) -> bytes:
    return b"text" + b"\0" * 4 + text.encode("ascii") + b"\0"


def display_rgb_to_xyz(prim: str) -> tuple[np.ndarray, tuple[float, float]]:
    """RGB -> CIE 1931 XYZ (columns, white Y = 1) and the white's xy of an
    :data:`ICC_SPACES` primaries entry: an RGB space of
    :data:`recovery.dng_color.PRIMARIES`, or ``display:NAME``, a spectral
    display (its guns through the CIE 1931 observer on the default grid)."""
    from recovery.dng_color import PRIMARIES, rgb_to_xyz_matrix

    if prim.startswith("display:"):
        from models.grid import DEFAULT_WAVELENGTHS
        from recovery.synthesis import output_space

        G = np.asarray(output_space(prim[len("display:"):], DEFAULT_WAVELENGTHS).Gamma, float)
        w = G.sum(axis=1)
        return G, (float(w[0] / w.sum()), float(w[1] / w.sum()))
    return rgb_to_xyz_matrix(prim), PRIMARIES[prim][1]


def icc_profile(output: str) -> bytes:
    """A v2.1 RGB display profile (matrix/TRC) for ``output`` (a key of
    :data:`ICC_SPACES`): colorants are the space's RGB -> XYZ columns adapted
    from its white to D50 by Bradford (as the ICC requires), media white D50,
    ``chad`` the adaptation, TRC the sRGB curve (1024 entries) or identity.
    Byte-for-byte deterministic (fixed date, no profile ID)."""
    from recovery.dng_color import D50_XY, bradford

    _, desc, prim, trc = ICC_SPACES[output]
    rgb_xyz, white = display_rgb_to_xyz(prim)
    chad = bradford(white, D50_XY)
    M = chad @ rgb_xyz
    curv = _curv(trc)
    sf32 = b"sf32" + b"\0" * 4 + b"".join(_s15(v) for v in chad.ravel())
    tags = [(b"desc", _desc(desc)), (b"cprt", _text("No copyright, use freely")),
            (b"wtpt", _xyz_tag(D50_XYZ)), (b"chad", sf32),
            (b"rXYZ", _xyz_tag(M[:, 0])), (b"gXYZ", _xyz_tag(M[:, 1])), (b"bXYZ", _xyz_tag(M[:, 2])),
            (b"rTRC", curv), (b"gTRC", curv), (b"bTRC", curv)]
    table_len = 4 + 12 * len(tags)
    offset = 128 + table_len
    entries, blobs, seen = [], [], {}
    for sig, data in tags:
        if data in seen:                       # the three TRCs share one curve
            entries.append((sig, *seen[data]))
            continue
        pad = (-offset) % 4
        blobs.append(b"\0" * pad)
        offset += pad
        seen[data] = (offset, len(data))
        entries.append((sig, offset, len(data)))
        blobs.append(data)
        offset += len(data)
    body = struct.pack(">I", len(tags)) + b"".join(struct.pack(">4sII", s, o, n) for s, o, n in entries) \
        + b"".join(blobs)
    size = 128 + len(body)
    size += (-size) % 4
    header = (struct.pack(">I", size) + b"\0" * 4 + struct.pack(">I", 0x02100000) + b"mntrRGB XYZ "
              + struct.pack(">6H", 2025, 1, 1, 0, 0, 0) + b"acsp" + b"\0" * 4 + struct.pack(">I", 0)
              + b"\0" * 8 + b"\0" * 8 + struct.pack(">I", 0)
              + b"".join(_s15(v) for v in D50_XYZ) + b"\0" * 4 + b"\0" * 16 + b"\0" * 28)
    assert len(header) == 128
    prof = header + body
    return prof + b"\0" * (size - len(prof))


def shipped_icc(output: str) -> bytes | None:
    """The shipped profile for an output space or display (``None`` for an
    output without one)."""
    name = ICC_FOR_OUTPUT.get(output)
    if name is None:
        return None
    return resources.files("service").joinpath("icc", name).read_bytes()


# ---------------------------------------------------------------------------
# EXIF
# ---------------------------------------------------------------------------

_ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL = 2, 3, 4, 5, 10
#: name -> (tag, type, in EXIF sub-IFD)
_EXIF_LAYOUT = {
    "Make": (271, _ASCII, False), "Model": (272, _ASCII, False), "Orientation": (274, _SHORT, False),
    "Software": (305, _ASCII, False), "DateTime": (306, _ASCII, False), "Artist": (315, _ASCII, False),
    "ImageDescription": (270, _ASCII, False), "Copyright": (33432, _ASCII, False),
    "ExposureTime": (33434, _RATIONAL, True), "FNumber": (33437, _RATIONAL, True),
    "ISOSpeedRatings": (34855, _SHORT, True), "DateTimeOriginal": (36867, _ASCII, True),
    "ExposureBiasValue": (37380, _SRATIONAL, True), "FocalLength": (37386, _RATIONAL, True),
    "BodySerialNumber": (42033, _ASCII, True), "LensMake": (42035, _ASCII, True),
    "LensModel": (42036, _ASCII, True),
}


#: Letters NFKD does not take apart, and their usual ASCII spelling.
_TRANSLIT = {"ß": "ss", "Æ": "AE", "æ": "ae", "Ø": "O", "ø": "o", "Œ": "OE", "œ": "oe", "Ł": "L", "ł": "l",
             "Đ": "D", "đ": "d", "Þ": "Th", "þ": "th", "ð": "d", "©": "(c)", "®": "(R)", "™": "(TM)",
             "\u2018": "'", "\u2019": "'", "\u201c": '"', "\u201d": '"', "\u2013": "-", "\u2014": "-"}


def ascii_text(text) -> str:
    """``text`` for a TIFF/EXIF ASCII field (7-bit only): accents dropped
    (NFKD: "José Müller" -> "Jose Muller"), a few letters spelt out (ß ->
    ss, © -> (c)), control characters and anything else outside ASCII as
    ``?``. The full text goes into the file's XMP (:func:`xmp_facts`).

    >>> ascii_text("(c) José Müller, Straße"), ascii_text("写真")
    ('(c) Jose Muller, Strasse', '??')
    """
    import unicodedata

    out = []
    for ch in str(text):
        if " " <= ch <= "~":
            out.append(ch)
            continue
        if ch in _TRANSLIT:
            out.append(_TRANSLIT[ch])
            continue
        base = "".join(c for c in unicodedata.normalize("NFKD", ch) if not unicodedata.combining(c))
        out.append(base if base and all(" " <= c <= "~" for c in base) else "?")
    return "".join(out)


#: Facts carried in the XMP packet when their text is not ASCII: name ->
#: (namespace prefix, property, kind); ``lang``/``seq`` are the rdf:Alt /
#: rdf:Seq the Dublin Core properties take (XMP Specification Part 1 and 2).
_XMP_FACTS = {
    "Artist": ("dc", "creator", "seq"), "Copyright": ("dc", "rights", "lang"),
    "Make": ("tiff", "Make", "text"), "Model": ("tiff", "Model", "text"),
    "LensMake": ("exifEX", "LensMake", "text"), "LensModel": ("exifEX", "LensModel", "text"),
    "BodySerialNumber": ("exifEX", "BodySerialNumber", "text"),
    "ImageDescription": ("dc", "description", "lang"),
}
_XMP_NS = {"dc": "http://purl.org/dc/elements/1.1/", "tiff": "http://ns.adobe.com/tiff/1.0/",
           "exifEX": "http://cipa.jp/exif/1.0/"}
#: The namespace of the estimate in XMP (embedded packets and sidecars).
WANDELL_NS = "https://github.com/wandell-recovery/ns/1.0/"
#: Summary key -> (``wandell:`` property, kind): ``real``, ``text``, ``bool`` (XMP's ``True``/``False``) or
#: ``seq`` (an rdf:Seq of reals).
_WANDELL_FIELDS = {
    "method": ("Method", "text"), "camera": ("Camera", "text"), "camera_rgb": ("CameraRGB", "seq"),
    "wb_multipliers": ("WBMultipliers", "seq"), "xy": ("LightXY", "seq"), "cct": ("CCT", "real"),
    "duv": ("Duv", "real"), "confidence": ("Confidence", "real"), "low_confidence": ("LowConfidence", "bool"),
    "temperature": ("Temperature", "real"),
    "tint": ("Tint", "real"), "white": ("White", "text"), "target": ("Target", "text"),
    "output": ("Output", "text"), "lights": ("Lights", "text"), "lights_reason": ("LightsReason", "text"),
    "light_held": ("LightHeld", "text"),
}


def _wandell_props(estimate: dict, indent: str = "   ") -> list[str]:
    """The estimate as ``wandell:`` XMP properties (elements): the fields
    of :data:`_WANDELL_FIELDS` it has, the rendering's name, and the whole
    summary as JSON in ``wandell:Estimate``."""
    import math
    from xml.sax.saxutils import escape

    def real(v):
        return repr(float(v)) if isinstance(v, (int, float)) and math.isfinite(v) else None

    out = []
    for key, (prop, kind) in _WANDELL_FIELDS.items():
        v = estimate.get(key)
        if v is None:
            continue
        if kind == "text":
            out.append(f"{indent}<wandell:{prop}>{escape(str(v))}</wandell:{prop}>")
        elif kind == "bool" and isinstance(v, bool):     # XMP Boolean: True / False
            out.append(f"{indent}<wandell:{prop}>{v}</wandell:{prop}>")
        elif kind == "real" and real(v) is not None:
            out.append(f"{indent}<wandell:{prop}>{real(v)}</wandell:{prop}>")
        elif kind == "seq" and isinstance(v, (list, tuple)) and all(real(x) is not None for x in v):
            items = "".join(f"<rdf:li>{real(x)}</rdf:li>" for x in v)
            out.append(f"{indent}<wandell:{prop}><rdf:Seq>{items}</rdf:Seq></wandell:{prop}>")
    rendering = estimate.get("rendering")
    if isinstance(rendering, dict) and rendering.get("rendering"):
        out.append(f"{indent}<wandell:Rendering>{escape(str(rendering['rendering']))}</wandell:Rendering>")
    from .jsonsafe import clean

    text = json.dumps(clean(estimate), separators=(",", ":"))
    out.append(f"{indent}<wandell:Estimate>{escape(text)}</wandell:Estimate>")
    return out


def read_wandell_xmp(packet: str | bytes) -> dict:
    """The ``wandell:`` properties of an XMP packet (what :func:`xmp_facts`
    and :func:`xmp_sidecar` write) as ``{property: value}``: reals as
    floats, sequences as lists, ``Estimate`` as the parsed JSON."""
    import xml.etree.ElementTree as ET

    if isinstance(packet, bytes):
        packet = packet.decode("utf-8")
    body = packet.split("?>", 1)[1].rsplit("<?xpacket", 1)[0] if packet.lstrip().startswith("<?xpacket") else packet
    root = ET.fromstring(body.strip())
    ns = "{" + WANDELL_NS + "}"
    kinds = {prop: kind for prop, kind in _WANDELL_FIELDS.values()}
    out: dict = {}
    for d in root.iter("{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description"):
        for k, v in d.attrib.items():
            if k.startswith(ns):
                out[k[len(ns):]] = v
        for el in d:
            if not el.tag.startswith(ns):
                continue
            name = el.tag[len(ns):]
            kind = kinds.get(name, "text")
            if kind == "seq":
                out[name] = [float(li.text) for li in el.iter("{http://www.w3.org/1999/02/22-rdf-syntax-ns#}li")]
            elif kind == "real":
                out[name] = float(el.text)
            elif kind == "bool":
                out[name] = (el.text or "").strip() == "True"
            else:
                out[name] = el.text or ""
    if "Estimate" in out:
        out["Estimate"] = json.loads(out["Estimate"])
    return out


#: PNG iTXt keyword (and, with the ``http://ns.adobe.com/xap/1.0/`` APP1
#: header, the JPEG carrier) of an XMP packet.
XMP_KEY = "XML:com.adobe.xmp"


def xmp_facts(facts: dict, estimate: dict | None = None) -> str | None:
    """An XMP packet with the text facts that are not ASCII (so cannot go
    into EXIF/TIFF ASCII fields whole), in UTF-8 as XMP requires, and the
    estimate (``wandell:`` properties, :func:`_wandell_props`); ``None``
    when every text fact is ASCII and there is no estimate. The ASCII
    fields carry :func:`ascii_text` of the same values."""
    from xml.sax.saxutils import escape

    props = []
    for name, (ns, prop, kind) in _XMP_FACTS.items():
        v = facts.get(name)
        if not isinstance(v, str) or v.isascii():
            continue
        v = "".join(c for c in v if c.isprintable() or c == " ")      # no control characters in XML 1.0
        if kind == "seq":
            props.append(f"   <{ns}:{prop}><rdf:Seq><rdf:li>{escape(v)}</rdf:li></rdf:Seq></{ns}:{prop}>")
        elif kind == "lang":
            props.append(f'   <{ns}:{prop}><rdf:Alt><rdf:li xml:lang="x-default">{escape(v)}</rdf:li></rdf:Alt>'
                         f"</{ns}:{prop}>")
        else:
            props.append(f"   <{ns}:{prop}>{escape(v)}</{ns}:{prop}>")
    if estimate is not None:
        props += _wandell_props(estimate)
    if not props:
        return None
    xmlns = "".join(f'\n   xmlns:{k}="{u}"' for k, u in {**_XMP_NS, "wandell": WANDELL_NS}.items())
    body = "\n".join(props)
    return (f'<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            f'<x:xmpmeta xmlns:x="adobe:ns:meta/" x:xmptk="wandell-recovery">\n'
            f' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            f'  <rdf:Description rdf:about=""{xmlns}>\n{body}\n  </rdf:Description>\n'
            f' </rdf:RDF>\n</x:xmpmeta>\n<?xpacket end="w"?>')


def _rational(v, signed=False):
    if isinstance(v, (tuple, list)) and len(v) == 2:
        return int(v[0]), int(v[1]) or 1
    from fractions import Fraction

    f = Fraction(float(v)).limit_denominator(1_000_000)
    return f.numerator, f.denominator


def _exif_value(typ, v):
    """A fact as Pillow's TIFF writer takes it for a field of type ``typ``."""
    from PIL.TiffImagePlugin import IFDRational

    if typ == _ASCII:
        return ascii_text(v)                          # 7-bit: the full text is in the XMP
    if typ == _SHORT:
        vals = tuple(int(x) & 0xFFFF for x in (v if isinstance(v, (tuple, list)) else [v]))
        return vals if len(vals) > 1 else vals[0]
    if typ == _LONG:
        return int(v)
    return IFDRational(*_rational(v, typ == _SRATIONAL))


def exif_block(facts: dict) -> bytes:
    """A little-endian TIFF structure (``II*\\0``) with the facts of
    :data:`_EXIF_LAYOUT` found in ``facts``; unknown keys are ignored.

    The IFDs are encoded by Pillow (``TiffImagePlugin.ImageFileDirectory_v2``:
    entries, counts, values inline or in the data area, word alignment),
    each field with the type EXIF gives it (Pillow would infer RATIONAL for
    a positive ExposureBiasValue, which EXIF types SRATIONAL). What is left
    here is the layout Pillow's own ``Image.Exif`` would infer types for:
    IFD0, then the EXIF sub-IFD at the offset IFD0's tag 34665 names."""
    from PIL.TiffImagePlugin import ImageFileDirectory_v2

    head = b"II*\0" + struct.pack("<I", 8)
    ifds = {False: ImageFileDirectory_v2(ifh=head), True: ImageFileDirectory_v2(ifh=head)}
    for name, v in facts.items():
        if name not in _EXIF_LAYOUT or v is None:
            continue
        tag, typ, in_sub = _EXIF_LAYOUT[name]
        try:
            value = _exif_value(typ, v)
        except (TypeError, ValueError, OverflowError, ZeroDivisionError):
            continue
        ifd = ifds[in_sub]
        ifd.tagtype[tag] = typ
        ifd[tag] = value
    main, sub = ifds[False], ifds[True]
    if len(sub):
        main.tagtype[34665] = _LONG
        main[34665] = 0                                   # its offset, once IFD0's size is known
        sub_at = 8 + len(main.tobytes(8))
        sub_at += sub_at % 2
        main[34665] = sub_at
    out = head + main.tobytes(8)
    if len(sub):
        out += b"\0" * (sub_at - len(out)) + sub.tobytes(sub_at)
    return out


def output_facts(source_exif: dict, estimate: dict | None, software: str = "wandell-recovery") -> dict:
    """The EXIF facts of an output: the source's (its own ImageDescription
    kept, if it had one), orientation 1 (the pixels are already rotated),
    this software, and ``XMP``: the packet with the estimate
    (:func:`xmp_facts`). The estimate is never put in ImageDescription,
    which photo managers (Lightroom, digiKam, Apple Photos...) show as the
    picture's caption."""
    facts = {k: v for k, v in source_exif.items() if k not in ("Orientation", "Software")}
    if not str(facts.get("ImageDescription") or "").strip():
        facts.pop("ImageDescription", None)
    facts["Orientation"] = 1
    facts["Software"] = software
    xmp = xmp_facts(facts, estimate)
    if xmp is not None:
        facts["XMP"] = xmp
    return facts


# ---------------------------------------------------------------------------
# Embedding into encoded files
# ---------------------------------------------------------------------------

def _png_chunk(ctype: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC-32 (PNG spec, 5.3).

    Hand-written on purpose: the image is already encoded (OpenCV or
    :mod:`service.encode`, chosen for speed), and no maintained library
    inserts chunks into an encoded PNG; Pillow writes iCCP, eXIf and iTXt
    only while it encodes the pixels itself (a second, slower encode of a
    full-resolution image). The framing is this one line."""
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data) & 0xFFFFFFFF)


def embed(encoded: bytes, fmt: str, icc: bytes | None, exif: bytes | None, text: dict | None = None) -> bytes:
    """Insert the ICC profile, EXIF and text into an encoded PNG or JPEG.

    PNG: iCCP, eXIf and iTXt chunks after IHDR (:func:`_png_chunk`). JPEG:
    APP1 ``Exif``, APP1 XMP and APP2 ``ICC_PROFILE`` segments (split in
    65,519-byte parts, ICC.1 Annex B.4) after SOI and a JFIF APP0. By hand
    for the reason :func:`_png_chunk` gives: Pillow and the other writers add
    these only while encoding the pixels themselves."""
    if fmt == "png":
        assert encoded[:8] == b"\x89PNG\r\n\x1a\n" and encoded[12:16] == b"IHDR"
        ihdr_end = 8 + 12 + struct.unpack(">I", encoded[8:12])[0]
        extra = b""
        if icc:
            extra += _png_chunk(b"iCCP", b"ICC profile\0\0" + zlib.compress(icc, 9))
        if exif:
            extra += _png_chunk(b"eXIf", exif)
        for k, v in (text or {}).items():
            extra += _png_chunk(b"iTXt", k.encode("latin-1") + b"\0\0\0\0\0" + v.encode("utf-8"))
        mv = memoryview(encoded)        # joined from views: no copy of the 22 MB tail before the result's
        return b"".join([mv[:ihdr_end], extra, mv[ihdr_end:]])
    if fmt == "jpeg":
        assert encoded[:2] == b"\xff\xd8"
        segs = b""
        if exif:
            payload = b"Exif\0\0" + exif
            if len(payload) + 2 <= 0xFFFF:
                segs += b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
        if (text or {}).get(XMP_KEY):
            payload = b"http://ns.adobe.com/xap/1.0/\0" + text[XMP_KEY].encode("utf-8")
            if len(payload) + 2 <= 0xFFFF:
                segs += b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
        if icc:
            chunk = 65519
            parts = [icc[i:i + chunk] for i in range(0, len(icc), chunk)]
            for i, p in enumerate(parts, 1):
                payload = b"ICC_PROFILE\0" + bytes([i, len(parts)]) + p
                segs += b"\xff\xe2" + struct.pack(">H", len(payload) + 2) + payload
        # after SOI and a JFIF APP0 if present
        pos = 2
        if encoded[2:4] == b"\xff\xe0":
            pos = 4 + struct.unpack(">H", encoded[4:6])[0]
        mv = memoryview(encoded)
        return b"".join([mv[:pos], segs, mv[pos:]])
    raise ValueError(f"embed: unsupported format {fmt!r}")


def tiff_extratags(facts: dict) -> list:
    """tifffile ``extratags`` for the facts (IFD0 tags of the TIFF itself)."""
    dtype = {_ASCII: "s", _SHORT: "H", _RATIONAL: "2I", _SRATIONAL: "2i"}
    out = []
    for name, v in facts.items():
        if name not in _EXIF_LAYOUT or v is None or name in ("Software", "ImageDescription"):
            continue
        tag, typ, _ = _EXIF_LAYOUT[name]
        try:
            if typ == _ASCII:
                out.append((tag, "s", 0, ascii_text(v), True))      # tifffile takes 7-bit ASCII only
            elif typ == _SHORT:
                out.append((tag, "H", 1, int(v if not isinstance(v, (list, tuple)) else v[0]), True))
            else:
                n, d = _rational(v, typ == _SRATIONAL)
                out.append((tag, dtype[typ], 1, (n, d), True))
        except (TypeError, ValueError):
            continue
    if facts.get("XMP"):
        xmp = facts["XMP"].encode("utf-8")
        out.append((700, "B", len(xmp), xmp, True))                 # TIFF's XMP tag: UTF-8 bytes
    return out


# ---------------------------------------------------------------------------
# XMP sidecar
# ---------------------------------------------------------------------------

def xmp_sidecar(temperature: float, tint: float, estimate: dict | None = None) -> str:
    """An XMP sidecar with Camera Raw settings: ``crs:WhiteBalance="Custom"``,
    ``crs:Temperature`` (K, Camera Raw's 2000..50000 range) and ``crs:Tint``
    (-150..150), which Lightroom/Camera Raw apply to a proprietary RAW of
    the same name (for a DNG they read the settings inside the DNG: README,
    "XMP sidecars and DNGs"); the estimate itself under the ``wandell:``
    namespace (:func:`_wandell_props`)."""
    t = int(round(min(max(float(temperature), 2000.0), 50000.0)))
    ti = int(round(min(max(float(tint), -150.0), 150.0)))
    body = ""
    if estimate is not None:
        body = "\n".join(_wandell_props(estimate)) + "\n"
    return f"""<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>
<x:xmpmeta xmlns:x="adobe:ns:meta/" x:xmptk="wandell-recovery">
 <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
  <rdf:Description rdf:about=""
   xmlns:crs="http://ns.adobe.com/camera-raw-settings/1.0/"
   xmlns:wandell="{WANDELL_NS}"
   crs:WhiteBalance="Custom"
   crs:Temperature="{t}"
   crs:Tint="{ti:+d}"
   crs:HasSettings="True">
{body}  </rdf:Description>
 </rdf:RDF>
</x:xmpmeta>
<?xpacket end="w"?>
"""


def main() -> None:
    """Write the ICC profiles into the package (``service/icc``)."""
    import os

    here = os.path.join(os.path.dirname(__file__), "icc")
    os.makedirs(here, exist_ok=True)
    for output, (name, *_rest) in ICC_SPACES.items():
        with open(os.path.join(here, name), "wb") as f:
            f.write(icc_profile(output))
        print(os.path.join(here, name))


if __name__ == "__main__":
    main()
