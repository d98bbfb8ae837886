"""The per-pixel correction of the white-balance pipeline: one 3x3 matrix per
pixel (Wandell 1985, Fig. 6: for a fixed light, camera RGB to display RGB is
one matrix), the highlight blend and shoulder (:mod:`recovery.highlights`),
the tone curve and the display encoding as one lookup table, fused in chunks
on a thread pool (OpenCV releases the GIL).

Moved out of :mod:`service.pipeline` (issue 18: one concept a module); the
pipeline re-exports these names, and ``_encoding_lut`` keeps its cache key
``service.pipeline._encoding_lut`` in ``models/data/colour_cache.npz``.
"""

from __future__ import annotations

import numpy as np

from recovery.synthesis import display_curve, highlight_white

from models._colour import cached


@cached("service.pipeline._encoding_lut")
def _encoding_lut(encoding: str | None, bits: int, curve: str | None = None) -> np.ndarray:
    """16-bit linear code -> encoded ``bits``-bit code, through
    colour-science's ``cctf_encoding`` of the colourspace, after the tone
    curve ``curve`` (``"libraw"``: :func:`display_curve`) if given."""
    import colour

    x = np.arange(65536) / 65535.0
    if curve == "libraw":
        x = display_curve(x)
    elif curve is not None:
        raise ValueError(f"unknown tone curve {curve!r}")
    y = x if encoding is None else np.asarray(colour.RGB_COLOURSPACES[encoding].cctf_encoding(x), float)
    top = 65535.0 if bits == 16 else 255.0
    return np.rint(np.clip(y, 0, 1) * top).astype(np.uint16 if bits == 16 else np.uint8)


#: Pixels per chunk of :func:`apply_matrix_inplace`: a chunk's float32
#: buffers (about 30 bytes a pixel) stay within a core's share of the cache
#: while the per-chunk Python overhead stays small against the arithmetic.
CHUNK_PIXELS = 1 << 16


def _highlight_code(start: float) -> int:
    """The largest uint16 code whose ``code / 65535`` (float32, as
    :func:`recovery.highlights.balance_highlights` computes it) is not above
    ``start``: pixels whose every channel is at most this code are only
    white-balanced."""
    c = np.arange(65536, dtype=np.float32) * np.float32(1.0 / 65535.0)
    return int(np.count_nonzero(c <= np.float32(start))) - 1


#: Whether :func:`apply_matrix_inplace` takes the one-transform path on the
#: chunks where the highlight blend and the clip change nothing (a switch for
#: the tests that compare it with the step-by-step path).
FUSED = True


def _plain_chunk(chunk: np.ndarray, hi: tuple, mask: np.ndarray) -> bool:
    """Whether every pixel of ``chunk`` (h, W, 3) has each channel at most
    ``hi`` (the codes below the highlight start whose white-balanced value
    is below 1: the blend and the clip change nothing), by ``cv2.inRange``
    into ``mask`` (h, W) and a count."""
    import cv2

    m = cv2.inRange(chunk, (0, 0, 0), hi, dst=mask)
    return cv2.countNonZero(m) == m.size


def chunk_rows(width: int) -> int:
    """Rows per chunk of an image ``width`` pixels wide (:data:`CHUNK_PIXELS`)."""
    return max(1, CHUNK_PIXELS // max(int(width), 1))


class Correction:
    """The per-pixel correction of :func:`apply_matrix_inplace`, set up once
    for an image (its matrix, light, shoulder and table) and applied a chunk
    of rows at a time: :meth:`linear` (the 16-bit linear display values, in
    a buffer of the calling thread) then :meth:`encode` (the table, into the
    output). A chunk is at most ``rows_per_chunk`` rows; which path a chunk
    takes (:func:`_plain_chunk`) depends on its pixels only, so the same
    chunks give the same values whoever cuts the image into them
    (:mod:`service.strips` renders strips of whole chunks)."""

    def __init__(self, M: np.ndarray, encoding: str | None, bits: int, *, neutral=None,
                 shoulder: dict | None = None, curve: str | None = None, rows_per_chunk: int = 1,
                 bgr: bool = False):
        import threading

        self.lut = _encoding_lut(encoding, bits, curve)
        self.bits, self.rows, self.bgr = bits, max(1, int(rows_per_chunk)), bgr
        # bgr: the output channels in OpenCV's order (the matrices' rows and the
        # shoulder's luminance weights reversed: the same values, swapped)
        order = slice(None, None, -1) if bgr else slice(None)
        self.Mt = np.ascontiguousarray(np.asarray(M, np.float32)[order])
        self.neutral, self.shoulder = neutral, shoulder
        if neutral is not None:
            from recovery.highlights import HIGHLIGHT_START

            n = np.asarray(neutral, float)
            n = n / n.max()
            A64 = np.asarray(M, float) @ np.diag(n)
            self.A = np.ascontiguousarray((A64 * 65535.0).astype(np.float32)[order])
            # code -> white-balanced value in one diagonal transform: (code / 65535) / n
            self.D = np.diag(1.0 / (65535.0 * n)).astype(np.float32)
            self.top = _highlight_code(HIGHLIGHT_START)
            # the white-balanced colour the matrix sends to display white (1, 1, 1)
            # for the DNG rendering; near it for the spectral one)
            self.wb_white = highlight_white(A64)
            self.s_on = False
            if shoulder is not None:
                self.lum = np.ascontiguousarray(np.asarray(shoulder["luminance"], np.float32)[order].reshape(1, 3))
                self.knee, self.s_peak = float(shoulder["knee"]), float(shoulder["peak"])
                self.s_on = max(self.s_peak, 1.0 + 1e-6) > 1.0 + 1e-6 and self.knee < 1.0
            # the fast path of a chunk (_plain_chunk): without a shoulder, every
            # code at most top and below the one whose ``code * D`` (float32, as
            # the transform computes it) reaches 1
            self.fast = FUSED and not self.s_on
            wb_limit = np.float32(1.0) / np.diag(self.D).astype(np.float32)
            self.plain_hi = tuple(float(min(self.top, int(np.floor(float(v) * (1.0 - 1e-6))))) for v in wb_limit)
        else:
            self.fast, self.plain_hi = False, None
        self._local = threading.local()

    def _buffers(self, h: int, W: int) -> dict:
        b = getattr(self._local, "b", None)
        if b is None or b["u"].shape[1] != W:
            shape = (self.rows, W, 3)
            b = self._local.b = {"u": np.empty(shape, np.uint16)}
            if self.neutral is not None:
                b.update(f=np.empty(shape, np.float32), w=np.empty(shape, np.float32),
                         m=np.empty(shape[:2], np.uint8))
                if self.shoulder is not None:
                    b.update(y=np.empty(shape[:2], np.float32), s=np.empty(shape[:2], np.float32),
                             s3=np.empty(shape, np.float32))
        return {k: v[:h] for k, v in b.items()}

    def linear(self, chunk: np.ndarray) -> np.ndarray:
        """The 16-bit linear display values of ``chunk`` (h, W, 3) uint16,
        ``h`` at most ``rows_per_chunk``: a buffer of this thread, valid
        until its next call."""
        import cv2

        from recovery.highlights import HIGHLIGHT_FULL, HIGHLIGHT_START, blend_to_neutral, shoulder_ratio

        zero = (0.0, 0.0, 0.0, 0.0)
        b = self._buffers(chunk.shape[0], chunk.shape[1])
        u = b["u"]
        if self.neutral is None or (self.fast and _plain_chunk(chunk, self.plain_hi, b["m"])):
            # neutral: no pixel of the chunk near clipping and none whose white
            # balance reaches 1, so the blend and the clip change nothing and
            # A diag(1 / (65535 n)) is M: the same matrix as without neutral,
            # straight from the codes (one pass instead of six)
            cv2.transform(np.ascontiguousarray(chunk), self.Mt, dst=u)
            return u
        f, w = b["f"], b["w"]
        top = self.top
        np.copyto(f, chunk, casting="unsafe")
        cv2.transform(f, self.D, dst=w)                                 # c / n
        cv2.threshold(w, 1.0, 1.0, cv2.THRESH_TRUNC, dst=w)            # min(., 1)
        # a chunk whose largest code is at most top has no highlight (most
        # chunks of a photograph): one max instead of inRange's mask (1/5 of its time)
        m = None if int(chunk.max()) <= top else cv2.inRange(chunk, zero[:3], (top, top, top), dst=b["m"])
        if m is not None and cv2.countNonZero(m) < m.size:     # m: 255 where nothing is near clipping
            idx = np.flatnonzero(m.reshape(-1) == 0)
            f2 = f.reshape(-1, 3)
            ch = f2[idx] * np.float32(1.0 / 65535.0)
            peak = np.maximum(np.maximum(ch[:, 0], ch[:, 1]), ch[:, 2])
            blend_to_neutral(w.reshape(-1, 3), idx, peak, HIGHLIGHT_START, HIGHLIGHT_FULL, self.wb_white)
        lin = cv2.transform(w, self.A, dst=f)                           # f is free again
        over = None
        if self.shoulder is not None and self.s_on:
            Y = cv2.transform(lin, self.lum, dst=b["y"]).reshape(-1)
            over = np.flatnonzero(Y > self.knee * 65535.0)
        if over is not None and over.size:
            # the shoulder as a per-pixel factor (1 below the knee), applied
            # while rounding: lin * S clipped to [0, 65535] and rounded
            S = b["s"].reshape(-1)
            S.fill(1.0)
            S[over] = shoulder_ratio(Y[over], self.knee, self.s_peak, 65535.0)
            S3 = cv2.cvtColor(b["s"], cv2.COLOR_GRAY2BGR, dst=b["s3"])
            cv2.multiply(lin, S3, dst=u, dtype=cv2.CV_16U)
        else:
            cv2.add(lin, zero, dst=u, dtype=cv2.CV_16U)                 # clip to [0, 65535], round
        return u

    def encode(self, u: np.ndarray, dst: np.ndarray) -> None:
        """The table (tone curve, transfer function, bits) of :meth:`linear`'s
        values into ``dst``."""
        np.take(self.lut, u, out=dst, mode="wrap")

    def rows_into(self, src: np.ndarray, dst: np.ndarray) -> None:
        """``src`` (h, W, 3) uint16, corrected into ``dst`` (h, W, 3) chunk
        by chunk, on the calling thread."""
        for r in range(0, src.shape[0], self.rows):
            self.encode(self.linear(src[r:r + self.rows]), dst[r:r + self.rows])


def apply_matrix_inplace(rgb16: np.ndarray, M: np.ndarray, encoding: str | None, bits: int,
                         rows_per_chunk: int | None = None, threads: int | None = None,
                         neutral=None, shoulder: dict | None = None, curve: str | None = None,
                         reuse_input: bool = False) -> np.ndarray:
    """Apply ``M`` to a uint16 (H, W, 3) image whose 65535 is saturation and
    encode it, chunk by chunk on a few threads.

    OpenCV's ``transform`` applies the 3x3 matrix per pixel and saturates
    to [0, 65535] (Wandell's first gamut option: clip per pixel); a 65536-
    entry table then applies the transfer function. The 16-bit linear
    intermediate costs at most 13 codes of a 16-bit sRGB output in the
    deepest shadows (the sRGB toe has slope 12.92), nothing in 8-bit output.
    uint16 output reuses the input buffer (memory stays at one image).

    With ``neutral`` (the light's camera RGB) the pixels are first white-
    balanced with clipped highlights made neutral
    (:func:`recovery.highlights.balance_highlights`) and ``M diag(neutral)``
    applied to the result, so a sensor-clipped pixel never renders with a
    colour cast. With ``shoulder`` (``{"luminance": (3,), "knee": k}``, set
    when an exposure lifts the sensor's range above display white) the
    highlights are compressed by :func:`recovery.highlights.highlight_shoulder`
    instead of clipping flat. ``curve`` (``"libraw"``) is the tone curve
    applied before the transfer function (:func:`display_curve`).

    One fused pass per chunk of rows (:data:`CHUNK_PIXELS`), in float32
    buffers reused by each thread: uint16 -> float32, the white balance and
    ``/ 65535`` as one diagonal ``cv2.transform``, the clip at 1 as one
    ``cv2.threshold``, the blend to neutral and the shoulder only on the
    pixels they change (found with ``cv2.inRange`` on the codes, in the
    chunks whose largest code is above the highlight start, and one
    luminance ``cv2.transform``), the matrix as ``cv2.transform``, clip and
    rounding to uint16 as one saturating ``cv2.add`` (``cv2.multiply`` by the
    shoulder's per-pixel factor when it applies), then the table. The
    result equals the per-step formulas of :mod:`recovery.highlights` up to
    float32 rounding (a code or two of the 16-bit linear values, before the
    table; 8-bit sRGB output is unchanged).

    A chunk whose every code is below the highlight start and below the one
    whose white balance reaches 1 (most chunks of a photograph:
    :func:`_plain_chunk`, one ``cv2.inRange``) has nothing for the blend or
    the clip to change, and ``M diag(neutral)`` after ``diag(neutral)^-1``
    is ``M``: it goes through one ``cv2.transform`` by ``M`` from the codes,
    as without ``neutral`` (issue 19: 197 -> 165 ms of a 24-megapixel image
    on one core; the same pixels within one code of the 16-bit linear
    values, ``tests/test_correction.py``). Not with a shoulder.

    ``reuse_input`` (the caller drops ``rgb16`` after this): 8-bit output
    goes into the first half of ``rgb16``'s own memory when it is
    contiguous, instead of a new 72 MB for 24 megapixels (issue 19: new
    memory is what this VM is slow to hand out, up to 1 s for such an
    array, and the peak is one image lower). Chunk ``j``'s output bytes
    are the input of the chunks around ``j / 2``: it waits until they have
    read theirs.
    """
    import os
    import threading
    from concurrent.futures import ThreadPoolExecutor

    H, W = rgb16.shape[:2]
    shared = bits == 8 and reuse_input and rgb16.flags.c_contiguous and rgb16.dtype == np.uint16
    if bits == 16:
        out = rgb16
    elif shared:
        out = rgb16.reshape(-1).view(np.uint8)[:rgb16.size].reshape(rgb16.shape)
    else:
        out = np.empty(rgb16.shape, np.uint8)
    if rgb16.size == 0:
        return out
    if rows_per_chunk is None:
        rows_per_chunk = chunk_rows(W)
    rows_per_chunk = max(1, min(int(rows_per_chunk), max(H, 1)))
    kernel = Correction(M, encoding, bits, neutral=neutral, shoulder=shoulder, curve=curve,
                        rows_per_chunk=rows_per_chunk)

    def work(r):
        chunk = rgb16[r:r + rows_per_chunk]
        h = chunk.shape[0]
        u = kernel.linear(chunk)
        if shared:
            read[r // rows_per_chunk].set()
            for i in range(r // 2 // rows_per_chunk, min(n_chunks, -(-(r + h) // 2 // rows_per_chunk) + 1)):
                lo = i * rows_per_chunk
                if i != r // rows_per_chunk and 2 * lo < r + h and 2 * min(lo + rows_per_chunk, H) > r:
                    read[i].wait()              # its input is where this output goes
        kernel.encode(u, out[r:r + rows_per_chunk])

    n_threads = threads or min(4, os.cpu_count() or 1)
    chunks = range(0, H, rows_per_chunk)
    n_chunks = len(chunks)
    read = [threading.Event() for _ in chunks] if shared else None

    def task(r):
        try:
            work(r)
        finally:
            if shared:      # also when it failed: no chunk waits for ever
                read[r // rows_per_chunk].set()

    if n_threads == 1 or len(chunks) == 1:
        for r in chunks:
            task(r)
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(task, chunks))
    return out
