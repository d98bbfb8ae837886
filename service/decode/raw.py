"""Camera RAWs through LibRaw (rawpy): the pixel limit from ``raw.sizes`` before any pixel is
unpacked, black and white levels, the estimation image by binning each 2x2 CFA cell (no
demosaic), and the full-resolution demosaic (OpenCV's edge-aware Bayer interpolation, or a
LibRaw algorithm) on the same scale.
"""

from __future__ import annotations

import io
import math
import os

import numpy as np

from ..errors import ServiceError
from .formats import camera_label
from .tiffbytes import tiff_file
from .image import DecodedImage, FLIP_OPS, SATURATION_FRACTION, _uint16_to_unit_float, as_shot_problem


def _librawmsg(exc) -> str:
    msg = exc.args[0] if exc.args else ""
    return msg.decode("utf-8", "replace") if isinstance(msg, bytes) else str(msg)


def _oriented_shape(h: int, w: int, flip: int, pixel_aspect: float = 1.0) -> tuple[int, int]:
    if pixel_aspect and abs(pixel_aspect - 1.0) > 1e-6:
        # LibRaw's stretch(): non-square pixels are resampled to square ones
        if pixel_aspect < 1:
            h = int(h / pixel_aspect + 0.5)
        else:
            w = int(w * pixel_aspect + 0.5)
    return (w, h) if flip & 4 else (h, w)


def _bayer_channels(raw, sizes) -> list[tuple[int, int, int, int]] | None:
    """``[(dy, dx, colour index, channel 0/1/2), ...]`` for the four sites of
    the 2x2 cell at the visible origin, or ``None`` if the sensor is not a
    2x2 R, G, G, B Bayer."""
    pattern = raw.raw_pattern
    if pattern is None or pattern.shape != (2, 2):
        return None
    desc = raw.color_desc.decode("latin-1")
    sites = []
    for dy in (0, 1):
        for dx in (0, 1):
            idx = int(pattern[(dy + sizes.top_margin) % 2, (dx + sizes.left_margin) % 2])
            if idx >= len(desc) or desc[idx] not in "RGB":
                return None
            sites.append((dy, dx, idx, "RGB".index(desc[idx])))
    if sorted(s[3] for s in sites) != [0, 1, 1, 2]:
        return None
    return sites


def _bin_bayer(img: np.ndarray, sites, blacks, white: float, rows_per_chunk: int | None = None):
    """Bin 2x2 CFA cells: ``(d - b_c) / (w - b_c)`` per site, greens
    averaged, and the cell's saturation flag, in row chunks (temporaries
    stay small whatever the image size)."""
    H, W = img.shape
    h2, w2 = H // 2, W // 2
    est = np.empty((h2, w2, 3), np.float32)
    sat = np.zeros((h2, w2), bool)
    rows = rows_per_chunk or max(1, (1 << 19) // max(1, w2))
    plan = []
    for dy, dx, idx, ch in sites:
        b = float(blacks[idx])
        scale = np.float32(1.0 / (white - b))
        thr = math.ceil(b + SATURATION_FRACTION * (white - b))
        plan.append((img[dy:2 * h2:2, dx:2 * w2:2], ch, np.float32(b), scale, thr))
    for r0 in range(0, h2, rows):
        r1 = min(h2, r0 + rows)
        green = None
        for view, ch, b, scale, thr in plan:
            v = view[r0:r1]
            sat[r0:r1] |= v >= thr
            a = v.astype(np.float32)
            a -= b
            a *= scale
            if ch == 1:
                if green is None:
                    green = a
                else:
                    green += a
                    green *= np.float32(0.5)
            else:
                est[r0:r1, :, ch] = a
        est[r0:r1, :, 1] = green
    return est, sat


def _bin_bayer_area(img: np.ndarray, sites, blacks, white: float, f: int):
    """Bin ``2f x 2f`` CFA blocks: each CFA plane averaged over ``f x f``
    sites (OpenCV ``INTER_AREA``, the exact block mean for an integer
    factor, rounded to whole digital numbers), then ``(d - b_c)/(w - b_c)``,
    greens averaged; a block is saturated if any of its sites is.

    The two sites of a mosaic row are read as the two channels of one
    image (every other row, no copy), so each row of the cell is one
    ``INTER_AREA`` and one ``inRange`` instead of a gathered copy of each
    plane (issue 19: the same numbers, in about half the time)."""
    import cv2

    H, W = img.shape
    hh, ww = (H // 2) // f, (W // 2) // f
    if f == 2:
        # OpenCV's 2x2 area mean of one channel (SIMD) rounds halves up, of two
        # channels (the generic code) to even: plane by plane, as defined
        return _bin_bayer_planes(img, sites, blacks, white, f)
    est = np.zeros((hh, ww, 3), np.float32)
    sat = None
    for dy in (0, 1):
        rows = img[dy:2 * hh * f:2, :2 * ww * f].reshape(hh * f, ww * f, 2)   # channel k: the site at dx = k
        row_sites = sorted((s for s in sites if s[0] == dy), key=lambda s: s[1])
        mean = cv2.resize(rows, (ww, hh), interpolation=cv2.INTER_AREA).astype(np.float32)
        thr = [min(math.ceil(blacks[idx] + SATURATION_FRACTION * (white - blacks[idx])), 65535)
               for _, _, idx, _ in row_sites]
        unsat = cv2.inRange(rows, (0, 0), (thr[0] - 1, thr[1] - 1))       # 255 where neither site is saturated
        hit = cv2.resize(cv2.bitwise_not(unsat), (ww, hh), interpolation=cv2.INTER_AREA) > 0
        sat = hit if sat is None else (sat | hit)
        for k, (_, _, idx, ch) in enumerate(row_sites):
            b = float(blacks[idx])
            m = mean[..., k] - np.float32(b)
            m *= np.float32(1.0 / (white - b))
            est[..., ch] += m * np.float32(0.5 if ch == 1 else 1.0)
    return est, sat


def _bin_bayer_planes(img: np.ndarray, sites, blacks, white: float, f: int):
    """:func:`_bin_bayer_area` one CFA plane at a time (a gathered copy of each)."""
    import cv2

    H, W = img.shape
    hh, ww = (H // 2) // f, (W // 2) // f
    est = np.zeros((hh, ww, 3), np.float32)
    sat = np.zeros((hh, ww), bool)
    for dy, dx, idx, ch in sites:
        b = float(blacks[idx])
        plane = np.ascontiguousarray(img[dy:2 * hh * f:2, dx:2 * ww * f:2])
        mean = cv2.resize(plane, (ww, hh), interpolation=cv2.INTER_AREA).astype(np.float32)
        thr = math.ceil(b + SATURATION_FRACTION * (white - b))
        hit = cv2.resize(cv2.compare(plane, min(thr, 65535), cv2.CMP_GE), (ww, hh), interpolation=cv2.INTER_AREA)
        sat |= hit > 0
        mean -= np.float32(b)
        mean *= np.float32(1.0 / (white - b))
        est[..., ch] += mean * np.float32(0.5 if ch == 1 else 1.0)
    return est, sat


def _decode_raw(raw, data: bytes, fmt: str, filename: str | None, max_pixels: int,
                info: _TiffInfo | None = None, info_error: Exception | None = None,
                estimation_pixels: int | None = None, keep_mosaic: bool = False) -> DecodedImage:
    import rawpy

    label = f"{filename!r}" if filename else "the upload"
    warnings: list[str] = []
    s = raw.sizes                         # header only: no pixel buffer yet
    declared = max(int(s.raw_height) * int(s.raw_width), int(s.height) * int(s.width))
    if declared > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"{label} declares {s.width}x{s.height} pixels ({declared:,} with margins); "
                          f"the limit is {max_pixels:,}")
    if s.height < 2 or s.width < 2:
        raise ServiceError(422, "corrupt_file", f"{label} declares an image of {s.width}x{s.height} pixels")
    aspect = float(s.pixel_aspect)
    if not (math.isfinite(aspect) and aspect > 0):
        raise ServiceError(422, "corrupt_file", f"{label} declares a pixel aspect ratio of {aspect}")
    # LibRaw stretches non-square pixels (DNG DefaultScale) to square ones when
    # demosaicking: the image it makes, not the declared one, must fit the limit
    out_h, out_w = _oriented_shape(int(s.height), int(s.width), 0, aspect)
    if out_h * out_w > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"{label} declares {s.width}x{s.height} pixels with a pixel aspect ratio of {aspect:.4g} "
                          f"(DNG DefaultScale): {out_w}x{out_h} = {out_h * out_w:,} pixels once stretched to "
                          f"square pixels; the limit is {max_pixels:,}")

    make = model = color_matrix = None
    if fmt in ("TIFF", "BigTIFF"):
        if info is None:
            warnings.append(f"TIFF tags unreadable ({type(info_error).__name__}); camera make/model unknown")
        else:
            if info.problem:
                raise ServiceError(422, "corrupt_file", f"{label}: {info.problem}")
            make, model, color_matrix = info.make, info.model, info.color_matrix
            if info.grey_guess:
                warnings.append("a single-channel TIFF without camera tags, read by LibRaw as an RGGB Bayer mosaic "
                                "(as dcraw -D writes); if it is a monochrome picture the colours are meaningless")
    else:
        warnings.append(f"{fmt} file: camera make/model are not read for this format; "
                        "give camera=... to use measured sensitivities")

    if fmt in ("TIFF", "BigTIFF") and info is not None and info.color_matrix is not None:
        # a LinearRaw (demosaiced) DNG: its samples block-averaged tile by tile, before LibRaw
        # unpacks anything (its full-size buffers: 35-42 MiB per megapixel, issue 28)
        from .linear_dng import linear_dng_estimation

        # without AsShotNeutral, LibRaw is left the file unless its AsShotWhiteXY gives the neutral
        got = linear_dng_estimation(data, int(s.height), int(s.width), estimation_pixels, label=label,
                                    need_neutral=info.white_xy_neutral is None and info.white_xy_problem is None)
        if got is not None:
            return _linear_dng_decoded(got, s, data, make, model, info.color_matrix, warnings, info=info)

    # -- pixels (unpacks; LibRawIOError etc. on truncated data)
    num_colors = int(raw.num_colors)
    if num_colors < 3:
        raise ServiceError(415, "unsupported_format",
                          f"{label} is a monochrome RAW ({num_colors} colour); colour analysis needs R, G, B")
    blacks = [float(b) for b in raw.black_level_per_channel]
    white = float(raw.white_level)
    if raw.raw_type != rawpy.RawType.Flat and white <= 255 and raw.raw_pattern is None:
        # e.g. a Nikon Coolscan NEF: 8-bit RGB per pixel, no sensor mosaic, no colour matrix
        who = camera_label(make, model)
        raise ServiceError(415, "not_camera_raw",
                          f"{label} is not a camera RAW: a scanned 8-bit RGB image"
                          + (f" ({who})" if who else "") + "; it carries no linear sensor data to analyse")
    if not white > max(blacks):
        raise ServiceError(422, "corrupt_file",
                          f"{label}: white level {white:g} is not above the black levels {blacks}")
    flip = int(s.flip) if int(s.flip) in FLIP_OPS else 0
    bmin = min(blacks)
    user_wb = [(white - bmin) / (white - b) for b in blacks]
    post = dict(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=False, use_auto_wb=False,
                user_wb=user_wb, output_color=rawpy.ColorSpace.raw, adjust_maximum_thr=0.0, bright=1.0,
                highlight_mode=rawpy.HighlightMode.Clip, user_flip=flip)

    sites = _bayer_channels(raw, s)
    if sites is not None:
        if raw.raw_type != rawpy.RawType.Flat:
            sites = None
    mosaic = None
    if sites is not None:
        img = raw.raw_image_visible
        scaler = None
        if keep_mosaic and abs(aspect - 1.0) <= 1e-6:
            # the caller renders next: the mosaic kept, already scaled for the
            # demosaic (about 2 bytes a pixel), instead of a second open and
            # unpack (70-80 ms on 24 MP, issue 19); the full-resolution image
            # drops it. Scaled on a thread straight from LibRaw's buffer while
            # this one bins the estimation image (no copy of the raw mosaic,
            # and the scaling is off the demosaic's path); joined before the
            # buffer goes (the caller closes the file)
            import threading

            box: dict = {}

            def scale():
                try:
                    box["mos"] = _scaled_mosaic(img, sites, blacks, white)
                except Exception:  # noqa: BLE001 - MemoryError and the like: the render unpacks again
                    pass

            scaler = threading.Thread(target=scale, name="wandell-scale", daemon=True)
            scaler.start()
        try:
            h2, w2 = img.shape[0] // 2, img.shape[1] // 2
            f = 1
            if estimation_pixels and h2 * w2 > estimation_pixels:
                f = int(math.ceil(math.sqrt(h2 * w2 / estimation_pixels)))
            if f > 1 and h2 // f >= 1 and w2 // f >= 1:
                est, sat = _bin_bayer_area(img, sites, blacks, white, f)
            else:
                est, sat = _bin_bayer(img, sites, blacks, white)
        finally:
            if scaler is not None:
                scaler.join()
        if scaler is not None and box.get("mos") is not None:
            mosaic = {"scaled": box["mos"], "sites": sites, "flip": flip}
        del img
        if s.height % 2 or s.width % 2:
            warnings.append("odd image size: the last row/column is not in the half-size estimation image")
        if flip:
            est = np.ascontiguousarray(FLIP_OPS[flip](est))
            sat = np.ascontiguousarray(FLIP_OPS[flip](sat))
    else:
        desc = raw.color_desc.decode("latin-1")[:num_colors]
        if sorted(desc[:3]) != ["B", "G", "R"]:
            raise ServiceError(415, "unsupported_format",
                              f"{label}: a sensor with colours {desc!r} is not supported (needs R, G, B)")
        # X-Trans, linear (demosaiced) DNG, Foveon...: LibRaw's half-size output
        rgb = raw.postprocess(half_size=True, **post)
        est = _uint16_to_unit_float(rgb[..., :3])
        sat = (rgb[..., :3] >= math.ceil(SATURATION_FRACTION * 65535)).any(axis=-1)
        del rgb
        kind = "demosaiced (linear) DNG" if raw.raw_type != rawpy.RawType.Flat else "not a 2x2 Bayer sensor"
        warnings.append(f"{kind}: the estimation image is LibRaw's own half-size output (full size for "
                        "demosaiced data), clipped at 0, saturation judged after interpolation")

    if color_matrix is None:
        m = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3]
        if m.shape == (3, 3) and np.all(np.isfinite(m)) and np.any(m):
            color_matrix = m
    neutral, asn_problem = None, None
    wb = np.asarray(raw.camera_whitebalance, dtype=np.float64)[:3]
    tagged = info.as_shot_neutral if info is not None else None
    if np.all(np.isfinite(wb)) and np.all(wb > 0):
        neutral = (1.0 / wb) / (1.0 / wb[1])
        asn_problem = as_shot_problem(neutral, "AsShotNeutral" if tagged is not None else "neutral")
    elif tagged is not None:                # LibRaw dropped the DNG's neutral (a channel under 0.001)
        asn_problem = as_shot_problem(tagged) or "LibRaw could not use the file's AsShotNeutral"
    elif info is not None:                  # AsShotWhiteXY: LibRaw puts it in its daylight multipliers only
        neutral, asn_problem = _white_xy_neutral(info)
    if asn_problem is not None:
        neutral = None
    full_shape = _oriented_shape(int(s.height), int(s.width), flip, float(s.pixel_aspect))
    if abs(float(s.pixel_aspect) - 1.0) > 1e-6:
        warnings.append(f"non-square pixels (aspect {float(s.pixel_aspect):.4g}): the full-resolution image "
                        "is resampled by LibRaw, the estimation image is not")
    frac = float(sat.mean()) if sat.size else 0.0
    if frac > 0.01:
        warnings.append(f"{100 * frac:.1f} % of the image is saturated (those cells are flagged)")
    return DecodedImage(
        kind="raw", estimation=est, saturated=sat, full_shape=full_shape, make=make, model=model,
        color_matrix=None if color_matrix is None else np.array(color_matrix, dtype=np.float64),
        as_shot_neutral=neutral, as_shot_problem=asn_problem, black_level=float(np.mean(blacks)), white_level=white,
        warnings=warnings, _source=data, _postprocess=post, _mosaic=mosaic,
    )


def _white_xy_neutral(info) -> tuple:
    """``(neutral, problem)`` of a DNG's AsShotWhiteXY (:class:`_TiffInfo`'s
    derivation through the colour matrices), checked as an AsShotNeutral
    is; ``(None, None)`` without the tag."""
    neutral, problem = info.white_xy_neutral, info.white_xy_problem
    if neutral is not None:
        problem = as_shot_problem(neutral, "AsShotNeutral derived from AsShotWhiteXY")
    return (None if problem else neutral), problem


def _linear_dng_decoded(got, s, data, make, model, color_matrix, warnings, tagged=None, info=None) -> DecodedImage:
    """The :class:`DecodedImage` of a LinearRaw DNG read by
    :func:`service.decode.linear_dng.linear_dng_estimation` (``got``): the
    estimation image oriented as LibRaw would (``s.flip``); the full-
    resolution image is read from the same samples too
    (:func:`service.decode.linear_dng.linear_dng_full`, through
    :func:`_raw_full_linear`), not by LibRaw. Without an AsShotNeutral the
    as-shot white is the one of the file's AsShotWhiteXY (``info``), if any."""
    est, sat, f, neutral, black, white = got
    if neutral is None and tagged is not None:       # a tag, but not positive numbers
        asn_problem = as_shot_problem(tagged) or "the file's AsShotNeutral cannot be read"
    elif neutral is None and info is not None:
        neutral, asn_problem = _white_xy_neutral(info)
    else:
        asn_problem = None if neutral is None else as_shot_problem(neutral)
    if asn_problem is not None:
        neutral = None
    flip = int(s.flip) if int(s.flip) in FLIP_OPS else 0
    if flip:
        est = np.ascontiguousarray(FLIP_OPS[flip](est))
        sat = np.ascontiguousarray(FLIP_OPS[flip](sat))
    warnings.append("demosaiced (linear) DNG: the estimation image is the file's own samples"
                    + (f" averaged over {f}x{f} blocks" if f > 1 else "") + ", saturation judged on the samples")
    post = dict(user_flip=flip)            # the orientation (DefaultCrop, the loader); LibRaw renders nothing
    full_shape = _oriented_shape(int(s.height), int(s.width), flip, float(s.pixel_aspect))
    frac = float(sat.mean()) if sat.size else 0.0
    if frac > 0.01:
        warnings.append(f"{100 * frac:.1f} % of the image is saturated (those cells are flagged)")
    return DecodedImage(
        kind="raw", estimation=est, saturated=sat, full_shape=full_shape, make=make, model=model,
        color_matrix=np.array(color_matrix, dtype=np.float64), as_shot_neutral=neutral, as_shot_problem=asn_problem,
        black_level=float(np.mean(black)), white_level=float(np.mean(white)),
        warnings=warnings, _source=data, _postprocess=post, _mosaic=None,
        _linear_raw=(int(s.height), int(s.width)),
    )


#: EXIF/TIFF Orientation (1..8) -> LibRaw's ``sizes.flip`` code (:data:`FLIP_OPS`)
_ORIENTATION_FLIP = {1: 0, 2: 1, 3: 3, 4: 2, 5: 4, 6: 6, 7: 7, 8: 5}


def decode_linear_dng_without_libraw(data: bytes, filename: str | None, max_pixels: int,
                                     estimation_pixels: int | None = None) -> DecodedImage | None:
    """A LinearRaw DNG LibRaw does not open (this build refuses compression
    32946, deflate, for them) read from its samples alone: the size, the
    orientation (IFD0's Orientation, as LibRaw maps it to ``flip``), Make,
    Model and ColorMatrix from the tags, the estimation image and the full-
    resolution one by :mod:`service.decode.linear_dng`, exactly as for a
    file LibRaw opens (:func:`_linear_dng_decoded`). ``None`` when the file
    is not a LinearRaw DNG in that module's plain layout with a colour
    matrix (the caller goes on as before).

    Raises
    ------
    ServiceError
        413 ``too_many_pixels`` past ``max_pixels``; 422 ``corrupt_file``
        for a damaged strip or tile, or tags the structure check refuses.
    """
    import types

    from .linear_dng import _raw_page, linear_dng_estimation
    from .structure import _check_tiff_structure, _tiff_structured
    from .tags import _tiff_info

    label = f"{filename!r}" if filename else "the upload"
    try:
        with tiff_file(data) as tf:
            page = _raw_page(tf)
            if page is None:
                return None
            H, W = int(page.imagelength), int(page.imagewidth)
            p0 = tf.pages.first if hasattr(tf.pages, "first") else tf.pages[0]
            orient = p0.tags.get(274)
            orient = int(orient.value) if orient is not None else 1
        info = _tiff_info(data)
    except Exception:  # noqa: BLE001 - not readable as such: the caller's path decides
        return None
    if info.color_matrix is None or H < 2 or W < 2:
        return None
    if H * W > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"{label} declares {W}x{H} = {H * W:,} pixels; the limit is {max_pixels:,}")
    if info.problem:
        raise ServiceError(422, "corrupt_file", f"{label}: {info.problem}")
    if _tiff_structured(data):
        _check_tiff_structure(data)
    # no AsShotNeutral: read with the as-shot white of AsShotWhiteXY if any, else without one
    got = linear_dng_estimation(data, H, W, estimation_pixels, label=label, need_neutral=False)
    if got is None:
        return None
    s = types.SimpleNamespace(height=H, width=W, flip=_ORIENTATION_FLIP.get(orient, 0), pixel_aspect=1.0)
    warnings = ["LibRaw does not open this DNG (its compression or sample type): it is read by tifffile alone"]
    return _linear_dng_decoded(got, s, data, info.make, info.model, info.color_matrix, warnings,
                               tagged=info.as_shot_neutral, info=info)


#: OpenCV conversion codes for each 2x2 Bayer cell (measured: a constant
#: colour mosaicked with each pattern comes back unchanged).
_OPENCV_BAYER = {"RGGB": "COLOR_BayerBG2RGB_EA", "BGGR": "COLOR_BayerRG2RGB_EA",
                 "GRBG": "COLOR_BayerGB2RGB_EA", "GBRG": "COLOR_BayerGR2RGB_EA"}

#: Demosaicking choices: ``rcd`` (ratio-corrected demosaicing,
#: :mod:`recovery.demosaic`, on the black-subtracted mosaic), ``fast``
#: (OpenCV's edge-aware bilinear on it) or a LibRaw algorithm name. RCD is the
#: default: within a few tenths of a decibel of LibRaw's best on mosaicked
#: photographs where the bilinear is 4-6 dB behind (``python -m benchmarks.demosaic``).
DEMOSAIC_DEFAULT = "rcd"
#: the demosaics made from the kept (or re-read) mosaic, not by LibRaw
MOSAIC_DEMOSAICS = ("rcd", "fast")


def demosaic_for(quality: str | None) -> str:
    """The demosaic of a ``quality`` preset: ``fast`` for ``quality=fast``
    (today's bilinear), :data:`DEMOSAIC_DEFAULT` otherwise."""
    return "fast" if quality == "fast" else DEMOSAIC_DEFAULT


def _pattern(sites) -> str | None:
    """The 2x2 cell (``RGGB``...) of :func:`_bayer_channels`' sites, or
    ``None`` when it is not one of the four Bayer phases."""
    letters = [""] * 4
    for dy, dx, idx, ch in sites:
        letters[dy * 2 + dx] = "RGB"[ch]
    pattern = "".join(letters)
    return pattern if pattern in _OPENCV_BAYER else None


def _opencv_full_linear(img: DecodedImage, method: str = "fast") -> np.ndarray | None:
    """Full-resolution linear RGB demosaicked from the mosaic by ``method``
    (``fast``: OpenCV's edge-aware Bayer interpolation; ``rcd``:
    :func:`recovery.demosaic.rcd`).

    Each CFA site is scaled ``(d - b_c) / (w - b_c) * 65535`` (the
    estimation image's scale) into one uint16 mosaic, then demosaicked and
    oriented like LibRaw's output. ``None`` when the sensor is not a plain
    2x2 Bayer with square pixels (then LibRaw demosaics). The mosaic the
    decode kept (``img._mosaic``) is used, and dropped, when there is one;
    else the file is opened and unpacked again."""
    import rawpy

    kept, img._mosaic = img._mosaic, None
    if kept is not None:
        return _demosaic_scaled(kept.pop("scaled"), kept["sites"], kept["flip"], method)
    try:
        with rawpy.imread(io.BytesIO(img._source)) as raw:
            s = raw.sizes
            sites = _bayer_channels(raw, s)
            if sites is None or raw.raw_type != rawpy.RawType.Flat or abs(float(s.pixel_aspect) - 1) > 1e-6:
                return None
            flip = int(s.flip) if int(s.flip) in FLIP_OPS else 0
            blacks = [float(b) for b in raw.black_level_per_channel]
            white = float(raw.white_level)
            mos = _scaled_mosaic(raw.raw_image_visible, sites, blacks, white)
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"LibRaw failed to read the pixels ({type(exc).__name__}: {_librawmsg(exc)})") from None
    return _demosaic_scaled(mos, sites, flip, method)


def _scaled_mosaic(cfa: np.ndarray, sites, blacks, white: float) -> np.ndarray:
    """The CFA sites scaled to the estimation scale, one uint16 mosaic:
    ``(d - b_c) * k_c`` clipped to [0, 65535], plus one half, truncated, in
    float32. Whole rows at a time, each site's ``b_c`` and ``k_c`` from a
    table of the 2 x 2 cell repeated along the row: the same float32
    operations on every sample as one site at a time, on contiguous memory
    (issue 19: half the time of the strided per-site passes)."""
    import cv2

    H, W = cfa.shape
    mos = np.empty((H, W), np.uint16)
    rows = 2 * max(1, (1 << 17) // max(1, W))   # 1 MB of float32 per chunk and thread; even: the cell's rows
    B = np.zeros((2, W), np.float32)
    K = np.zeros((2, W), np.float32)
    for dy, dx, idx, ch in sites:        # the four sites of the cell (_bayer_channels)
        B[dy, dx::2] = np.float32(blacks[idx])
        K[dy, dx::2] = np.float32(65535.0 / (white - blacks[idx]))
    B, K = np.tile(B, (rows // 2, 1)), np.tile(K, (rows // 2, 1))
    tasks = range(0, H, rows)

    def scale(r):
        src = cfa[r:r + rows]
        h = src.shape[0]
        a = src.astype(np.float32)
        a -= B[:h]
        a *= K[:h]
        np.clip(a, 0, 65535, out=a)
        a += np.float32(0.5)
        mos[r:r + h] = a

    # numpy releases the GIL on these arrays: the row chunks run on every core
    n_threads = min(4, os.cpu_count() or 1, max(1, cv2.getNumThreads()))   # 1 in a pool worker
    if n_threads > 1 and len(tasks) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(scale, tasks))
    else:
        for t in tasks:
            scale(t)
    return mos


def _demosaic_scaled(mos: np.ndarray, sites, flip: int, method: str = "fast") -> np.ndarray | None:
    import cv2

    pattern = _pattern(sites)
    if pattern is None:
        return None
    if method == "rcd":
        from recovery.demosaic import rcd

        rgb = rcd(mos, pattern, rows=RCD_ROWS, threads=_threads())
    else:
        rgb = cv2.cvtColor(mos, getattr(cv2, _OPENCV_BAYER[pattern]))
    del mos
    if flip:
        rgb = np.ascontiguousarray(FLIP_OPS[flip](rgb))
    return rgb


#: rows of the mosaic :func:`recovery.demosaic.rcd` demosaics at a time
#: (its context, :data:`recovery.demosaic.MARGIN` rows either side, is
#: demosaicked again for each strip)
RCD_ROWS = 128


def _threads() -> int:
    """Threads for the whole image's demosaic: OpenCV's (1 in a pool
    worker), at most the cores and 4."""
    import cv2

    return min(4, os.cpu_count() or 1, max(1, cv2.getNumThreads()))


def _raw_full_linear(img: DecodedImage, demosaic: str | None) -> np.ndarray:
    import rawpy

    if img._linear_raw is not None:      # a LinearRaw DNG: its own samples, already demosaiced
        from .linear_dng import linear_dng_full

        rgb = linear_dng_full(img._source, *img._linear_raw, int(img._postprocess.get("user_flip", 0) or 0))
        if tuple(rgb.shape[:2]) != tuple(img.full_shape):
            raise ServiceError(422, "corrupt_file", f"the LinearRaw image is {rgb.shape[1]}x{rgb.shape[0]}, not "
                               f"the declared {img.full_shape[1]}x{img.full_shape[0]}")
        return rgb
    demosaic = demosaic or DEMOSAIC_DEFAULT
    if str(demosaic).lower() in MOSAIC_DEMOSAICS:
        rgb = _opencv_full_linear(img, str(demosaic).lower())
        if rgb is not None:
            return rgb
        img.warnings.append(f"not a plain Bayer sensor: demosaicked by LibRaw (AHD) instead of {demosaic}")
        demosaic = "AHD"
    params = dict(img._postprocess)
    if demosaic is not None:
        try:
            params["demosaic_algorithm"] = rawpy.DemosaicAlgorithm[str(demosaic).upper()]
        except KeyError:
            names = [a.name for a in rawpy.DemosaicAlgorithm]
            raise ValueError(f"unknown demosaic algorithm {demosaic!r}; accepted: {names}") from None
    try:
        with rawpy.imread(io.BytesIO(img._source)) as raw:
            rgb = raw.postprocess(**params)
    except (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError, MemoryError) as exc:
        raise ServiceError(413, "too_many_pixels", f"not enough memory to demosaic the image ({exc})") from None
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"LibRaw failed to demosaic the file ({type(exc).__name__}: {_librawmsg(exc)})") from None
    if rgb.shape[2] != 3:
        rgb = np.ascontiguousarray(rgb[..., :3])
    if tuple(rgb.shape[:2]) != tuple(img.full_shape):
        img.warnings.append(f"LibRaw's full-resolution image is {rgb.shape[1]}x{rgb.shape[0]}, not the declared "
                            f"{img.full_shape[1]}x{img.full_shape[0]}")
        img.full_shape = tuple(int(v) for v in rgb.shape[:2])
    return rgb
