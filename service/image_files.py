"""Image files of the corrected image: 16-bit TIFF, 8/16-bit PNG and JPEG
with their ICC profile, EXIF and XMP, as bytes or straight to a path
(:mod:`service.pipeline` re-exports every name)."""

from __future__ import annotations

import io

import numpy as np

from .errors import ServiceError


def encode_image(img: np.ndarray, fmt: str, path: str | None = None, meta: dict | None = None,
                 threads: int | None = None) -> bytes | None:
    """PNG (8-bit or 16-bit), 16-bit TIFF or 8-bit JPEG of an RGB image, as
    bytes, or written to ``path`` (TIFF straight from the array, no copy).
    PNG and JPEG are encoded in strips on ``threads`` threads
    (:func:`service.encode.png_encode`, :func:`service.encode.jpeg_encode`;
    default: one per CPU).

    ``meta`` (:func:`output_meta`): ``icc`` (profile bytes), ``facts`` (EXIF
    facts, :func:`service.outputs.output_facts`) and ``text`` (PNG text) are
    embedded so other tools read the colours and the source right."""
    meta = meta or {}
    if fmt == "tiff":
        import tifffile

        kw = _tiff_kwargs(meta)
        if path is not None:
            tifffile.imwrite(path, img, photometric="rgb", **kw)
            return None
        buf = io.BytesIO()
        tifffile.imwrite(buf, img, photometric="rgb", **kw)
        return buf.getvalue()
    if fmt == "png" and img.ndim == 3 and img.shape[2] == 3 and img.size:
        from .encode import png_encode

        data = png_encode(img, threads)
    elif fmt == "jpeg" and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.size:
        from .encode import jpeg_encode

        try:
            data = jpeg_encode(img, 95, threads)
        except ValueError:
            raise ServiceError(422, "encode_failed", "could not encode jpeg") from None
    else:
        import cv2

        bgr = np.ascontiguousarray(img[..., ::-1])
        ok, enc = cv2.imencode(".png" if fmt == "png" else ".jpg", bgr,
                               [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise ServiceError(422, "encode_failed", f"could not encode {fmt}")
        data = enc.tobytes()
    data = _with_meta(data, fmt, meta)
    if path is not None:
        with open(path, "wb") as f:
            f.write(data)
        return None
    return data


def _with_meta(data: bytes, fmt: str, meta: dict | None) -> bytes:
    """A PNG or JPEG's bytes with ``meta``'s ICC profile, EXIF facts and PNG
    text embedded (:func:`service.outputs.embed`)."""
    from . import outputs

    meta = meta or {}
    icc, facts = meta.get("icc"), meta.get("facts")
    if icc or facts or meta.get("text"):
        data = outputs.embed(data, fmt, icc, outputs.exif_block(facts) if facts else None, meta.get("text"))
    return data


def _tiff_kwargs(meta: dict) -> dict:
    """tifffile's keywords for an output TIFF carrying ``meta`` (:func:`encode_image`)."""
    from . import outputs

    icc, facts = meta.get("icc"), meta.get("facts")
    kw = {}
    if icc:
        kw["iccprofile"] = icc
    if facts:
        kw["extratags"] = outputs.tiff_extratags(facts)
        kw["metadata"] = None          # no tifffile shape JSON in ImageDescription (photo tools show it)
        if facts.get("ImageDescription"):   # the source's own caption only; the estimate is in the XMP
            kw["description"] = outputs.ascii_text(facts["ImageDescription"])
        kw["software"] = facts.get("Software", "wandell-recovery")
    return kw


class _SparseFile:
    """A seekable file that keeps what is written and only the size of what
    is skipped (tifffile's ``write_empty``: a seek and one zero byte)."""

    def __init__(self):
        self.pos = self.size = 0
        self.parts: list[tuple[int, bytes]] = []

    def write(self, b) -> int:
        b = bytes(b)
        self.parts.append((self.pos, b))
        self.pos += len(b)
        self.size = max(self.size, self.pos)
        return len(b)

    def seek(self, off: int, whence: int = 0) -> int:
        self.pos = off if whence == 0 else self.pos + off if whence == 1 else self.size + off
        return self.pos

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def seekable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True


def tiff_head(img: np.ndarray, meta: dict | None = None) -> bytes | None:
    """The bytes of the TIFF :func:`encode_image` writes for ``img``, up to
    where its pixels start: the file is these bytes then ``img``'s bytes in
    C order (uncompressed, one strip, pixels last), so an answer can send
    the image from memory instead of a 144 MB file written and read back
    (issue 19). Made by tifffile with the pixels left empty; ``None`` when
    its layout is not header-then-pixels (then write the file)."""
    import tifffile

    f = _SparseFile()
    tifffile.imwrite(f, shape=img.shape, dtype=img.dtype, photometric="rgb", **_tiff_kwargs(meta or {}))
    start = f.size - img.nbytes
    head = bytearray(start)
    for off, b in f.parts:
        if off + len(b) <= start:
            head[off:off + len(b)] = b
        elif not (off == f.size - 1 and b == b"\x00"):      # anything but the pixels' one zero byte
            return None
    return bytes(head)
