"""Camera Raw XMP sidecars of the command line (``wandell white-balance
--xmp``, ``wandell batch --xmp``): where editors look for them
(:func:`sidecar_path`), written as a new file only, or beside the output
when the RAW's folder cannot be written (:func:`_sidecar_job`). Split from
:mod:`service.cli`, which re-exports these names (issue 29)."""

from __future__ import annotations

import os

from . import jobs


def sidecar_path(raw: str, name: str = "stem") -> str:
    """Where editors look for a RAW's XMP sidecar: beside it, named
    ``IMG_0001.xmp`` (``stem``: Adobe's convention, Lightroom and Camera Raw)
    or ``IMG_0001.dng.xmp`` (``full``: darktable's and digiKam's)."""
    base = os.path.basename(raw)
    return os.path.join(os.path.dirname(os.path.abspath(raw)),
                        (os.path.splitext(base)[0] if name == "stem" else base) + ".xmp")


def _sidecar_text(src: str, illuminant: dict, opts, limits) -> tuple[str, dict]:
    """The Camera Raw sidecar of a finished item (its estimated light's
    camera RGB through the file's colour matrices, pipeline.xmp_sidecar);
    ``limits``: the decoding limits (``max_pixels``, ``estimation_pixels``)."""
    from . import pipeline

    with open(src, "rb") as f:
        decoded, cam, warns, _ = pipeline.open_image(f.read(), os.path.basename(src), limits, opts.camera)
    run = pipeline.EstimateRun(jobs._estimate_from_json(illuminant, cam), cam, warns)  # the item's own light
    text, tt, summary = pipeline.xmp_sidecar(decoded, run)
    raw = None
    if decoded.kind == "raw":      # what a DNG made of another RAW format needs (service.dngwrite.raw_as_dng)
        raw = {"make": decoded.make, "model": decoded.model, "color_matrix": decoded.color_matrix}
    return text, {**tt, "camera_rgb": summary["camera_rgb"], "raw": raw}


def dng_copy_message(sc: dict) -> str:
    """What the command line says of a DNG's copy (``dng``, ``dng_kept`` or ``dng_error``)."""
    if sc.get("dng"):
        return f"DNG with the white balance inside (for Lightroom): {sc['dng']}"
    if sc.get("dng_kept"):
        return f"DNG copy {sc['dng_kept']} exists: kept as it is (--xmp-overwrite replaces it)"
    return str(sc.get("dng_error", ""))


def dng_copy_path(sidecar: str, src: str) -> str:
    """Where a DNG's copy with the white balance inside goes: beside its
    sidecar, ``IMG_0001.wandell.dng`` (never the original's name), a long
    name cut as a batch's outputs are (:func:`service.cli_paths.dng_copy_name`)."""
    from .cli_paths import dng_copy_name

    return os.path.join(os.path.dirname(os.path.abspath(sidecar)),
                        dng_copy_name(os.path.splitext(os.path.basename(src))[0]))


def _write_dng_copy(src: str, text: str, neutral, target: str, overwrite: bool, raw: dict | None = None) -> dict:
    """For a DNG input: a copy of it with the sidecar's XMP packet and
    AsShotNeutral inside (:func:`service.dngxmp.dng_with_white`; what
    Lightroom reads for a DNG) at ``target``; for another camera RAW
    (``raw``: its make, model and colour matrix) a DNG made of its raw data
    with the same inside (:func:`service.dngwrite.raw_as_dng`); the original
    is only read. ``{}`` for any other input (TIFF, PNG); ``dng`` (the
    path), ``dng_kept`` or ``dng_error`` otherwise."""
    from .dngwrite import raw_as_dng
    from .dngxmp import NotADng, dng_with_white

    with open(src, "rb") as f:
        data = f.read()
    try:
        copy = dng_with_white(data, text, neutral)
    except NotADng:
        if raw is None:
            return {}
        try:
            copy = raw_as_dng(data, text, neutral, **raw)
        except ValueError as e:          # NotConvertible among them: why this RAW cannot be a DNG
            return {"dng_error": f"no DNG made of this RAW: {e}"}
    except ValueError as e:
        return {"dng_error": f"no DNG copy: {e}"}
    if os.path.abspath(target) == os.path.abspath(src):
        return {"dng_error": "no DNG copy: it would replace the original"}

    def write(p):
        with open(p, "wb") as f:
            f.write(copy)

    try:
        if overwrite:
            jobs.atomic_write(target, write)
        else:
            with open(target, "xb") as f:
                f.write(copy)
    except FileExistsError:
        return {"dng_kept": target}
    except OSError as e:
        return {"dng_error": f"no DNG copy: cannot write {target}: {e.strerror or e}"}
    return {"dng": target}


def _write_sidecar(path: str, text: str, overwrite: bool) -> None:
    """``text`` to ``path``: a new file only (``FileExistsError`` if one is
    there: never a sidecar an editor wrote) unless ``overwrite``, then
    replaced whole (a temporary renamed into place)."""
    if not overwrite:
        with open(path, "x", encoding="utf-8") as f:
            f.write(text)
        return
    jobs.atomic_write(path, lambda p: jobs.write_text(p, text))


#: errno values that mean "this folder cannot be written" (permission, read-only file system).
_NOT_WRITABLE = (1, 13, 30)


def _sidecar_job(src: str, illuminant: dict, opts, target: str, fallback: str | None, overwrite: bool,
                 limits) -> dict:
    """Write one RAW's sidecar to ``target``; when its folder cannot be
    written, to ``fallback`` (a folder) if given. An existing sidecar is
    kept unless ``overwrite``. Returns ``xmp`` (the path written, or
    ``None``), ``kept`` (an existing one left alone), ``note`` (in words,
    when it went elsewhere or was kept), ``error`` (why there is none),
    ``temperature``/``tint``. Runs in a batch's workers; ``limits``: the
    decoding limits."""
    def exists(p):
        return os.path.lexists(p) and not overwrite

    out: dict = {"xmp": None}
    if exists(target):
        return {**out, "kept": target, "note": f"XMP sidecar {target} exists: kept as it is (--xmp-overwrite "
                                               "replaces it)"}
    try:
        text, tt = _sidecar_text(src, illuminant, opts, limits)
    except Exception as e:  # noqa: BLE001 - the image is written; say why the sidecar is not
        return {**out, "error": str(getattr(e, "detail", e)), "note": f"no XMP sidecar: {getattr(e, 'detail', e)}"}
    out.update(temperature=tt["temperature"], tint=tt["tint"])
    folder = os.path.dirname(os.path.abspath(target))
    try:
        if not os.access(folder, os.W_OK):
            raise PermissionError(13, "permission denied", folder)
        _write_sidecar(target, text, overwrite)
        return {**out, "xmp": target, **_write_dng_copy(src, text, tt["camera_rgb"], dng_copy_path(target, src),
                                                       overwrite, tt.get("raw"))}
    except FileExistsError:
        return {**out, "kept": target, "note": f"XMP sidecar {target} exists: kept as it is (--xmp-overwrite "
                                               "replaces it)"}
    except OSError as e:
        if fallback is None or e.errno not in _NOT_WRITABLE:
            return {**out, "error": f"cannot write {target}: {e.strerror or e}",
                    "note": f"no XMP sidecar: cannot write {target}: {e.strerror or e}"}
        reason = e.strerror or str(e)
    alt = os.path.join(fallback, os.path.basename(target))
    why = f"the RAW's folder {folder} is not writable ({reason})"
    if exists(alt):
        return {**out, "kept": alt, "note": f"{why}, and {alt} exists: kept as it is (--xmp-overwrite replaces it)"}
    try:
        os.makedirs(fallback, exist_ok=True)
        _write_sidecar(alt, text, overwrite)
    except FileExistsError:
        return {**out, "kept": alt, "note": f"{why}, and {alt} exists: kept as it is (--xmp-overwrite replaces it)"}
    except OSError as e:
        return {**out, "error": f"{why}, nor {fallback} ({e.strerror or e})",
                "note": f"no XMP sidecar: {why}, nor {fallback} ({e.strerror or e})"}
    return {**out, "xmp": alt, **_write_dng_copy(src, text, tt["camera_rgb"], dng_copy_path(alt, src), overwrite,
                                                  tt.get("raw")),
            "note": f"{why}: XMP sidecar written to {alt} instead; editors look for it beside "
                                       "the RAW, so move it there"}
