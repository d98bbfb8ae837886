"""Which camera took an image: the sensor functions :math:`R_k(\\lambda)` of
Wandell (1985), eq. 12, from what is known about it.

Constructors: a measured camera (:meth:`recovery.Camera.named`), sensitivities
derived from an XYZ -> camera colour matrix (:func:`camera_from_matrix`), a
generic camera (:func:`generic_camera`), an uploaded CSV of sensitivities
(:func:`camera_from_csv`); and the choice among them for an image
(:func:`resolve_camera`), saying which and how approximate. Every refusal is
an :class:`~recovery.errors.InputError` whose ``code`` names the rule
(``bad_color_matrix``, ``bad_csv``, ``unknown_camera``, ``no_color_matrix``).

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12 and Fig. 6.
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, chapter 6 (ColorMatrix
maps XYZ to the camera's reference space).
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .errors import InputError
from .tables import read_csv_table

__all__ = ["camera_from_matrix", "generic_camera", "camera_from_csv", "resolve_camera"]



def _grid(wavelengths) -> np.ndarray:
    from models import DEFAULT_WAVELENGTHS

    return DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=np.float64)


def camera_from_matrix(color_matrix: np.ndarray, wavelengths=None, name: str = "matrix-derived"):
    """Sensitivities implied by an XYZ -> camera matrix.

    If the camera were colorimetric, :math:`c = M\\,XYZ` for every colour
    signal, i.e. :math:`R_k(\\lambda) = \\sum_j M_{kj}\\,\\bar{x}_j(\\lambda)`
    with the CIE 1931 2° colour matching functions; as arrays
    ``R = cmfs @ M.T`` (``(N, 3)``). No real camera is colorimetric, so this
    is an approximation (Wandell 1985, Fig. 6: analysis needs the camera's
    own sensors): negative lobes, which no sensor has, are clipped to 0 and
    the amount removed is reported in ``Camera.notes``. The channel balance
    of the matrix is kept; the whole is scaled so the largest value is 1.

    Parameters
    ----------
    color_matrix : (3, 3) array_like
        XYZ -> camera (rows camera R, G, B), e.g. DNG ColorMatrix1.
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm.
    name : str

    Returns
    -------
    recovery.Camera
        ``source="matrix-derived"``.

    Raises
    ------
    InputError
        ``bad_color_matrix`` for a matrix that is not 3x3, finite and
        invertible, or that leaves a channel with no positive sensitivity.

    Examples
    --------
    >>> cam = camera_from_matrix(np.eye(3))
    >>> cam.source, cam.sensitivities.shape
    ('matrix-derived', (31, 3))
    """
    from models import observer

    m = np.asarray(color_matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InputError(f"colour matrix must be a finite 3x3 array, got {m.shape}", code="bad_color_matrix")
    if abs(np.linalg.det(m)) < 1e-12 * max(1.0, float(np.abs(m).max()) ** 3):
        raise InputError("colour matrix is singular", code="bad_color_matrix")
    wl = _grid(wavelengths)
    cmfs = observer("CIE 1931 2 Degree Standard Observer", wl)
    r = cmfs @ m.T
    pos = np.clip(r, 0.0, None)
    if np.any(pos.max(axis=0) <= 0):
        raise InputError("colour matrix gives a channel with no positive sensitivity anywhere",
                         code="bad_color_matrix")
    removed = np.abs(r - pos).sum(axis=0) / np.maximum(np.abs(r).sum(axis=0), 1e-300)
    pos = pos / pos.max()
    notes = (
        "sensitivities derived from an XYZ->camera colour matrix and the CIE 1931 2 degree CMFs "
        "(R = cmfs @ M.T); approximate: real cameras are not colorimetric",
        "negative lobes clipped to 0 (fraction of each channel's absolute area removed: "
        + ", ".join(f"{c} {100 * f:.1f} %" for c, f in zip("RGB", removed)) + ")",
    )
    return Camera(wl, pos, name, "matrix-derived", notes, m)


def generic_camera(wavelengths=None):
    """A generic RGB camera: the mean of the three measured cameras.

    :math:`R_k = \\frac{1}{3}\\sum_{cam} R_k^{cam}` with each measured
    camera's channels as :func:`models.camera_sensitivities` gives them
    (peak 1 per channel on the default grid): Nikon 5100 (NPL), Sigma
    SDMerill (NPL), Canon EOS 5D Mark II. Used when nothing says what camera
    took the image; estimates with it are approximate.

    Parameters
    ----------
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm.

    Returns
    -------
    recovery.Camera
        ``name="generic"``, ``source="generic"``.

    Examples
    --------
    >>> generic_camera().sensitivities.shape
    (31, 3)
    """
    from models import camera_names, camera_sensitivities

    wl = _grid(wavelengths)
    names = camera_names()
    r = np.mean([camera_sensitivities(n, wl) for n in names], axis=0)
    return Camera(wl, r, "generic", "generic",
                  (f"generic camera: channel-wise mean of the measured sensitivities of {', '.join(names)} "
                   "(each channel peak-normalised); approximate for any real camera",))


#: Most channel columns a sensitivities CSV may have: a 2,000,000-column CSV
#: of 12 MB (inside the CSV's value limit) took 20 s and 1.9 GB before the
#: image's 3 channels refused it (probe round 6).
MAX_CSV_CHANNELS = 64


def camera_from_csv(data: bytes, wavelengths=None, name: str = "uploaded"):
    """A camera from an uploaded CSV of spectral sensitivities.

    Format: one row per wavelength, first column the wavelength in nm
    (strictly increasing, covering the analysis grid, default 400-700 nm),
    then one column per channel (at least 3, at most :data:`MAX_CSV_CHANNELS`); an optional header row of
    names; separators ``,``, ``;`` (decimal commas allowed then), tab or
    spaces; blank lines and lines starting with ``#`` are skipped. The
    columns are resampled to the grid (``models.resample``), negative values
    (noise) clipped to 0, and the whole scaled so the largest value is 1
    (the channel balance is kept).

    Parameters
    ----------
    data : bytes or str
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm.
    name : str

    Returns
    -------
    recovery.Camera
        ``source="uploaded"``.

    Raises
    ------
    InputError
        ``bad_csv`` naming the line and column at fault: not text,
        non-numeric values, fewer than 3 channels, ragged rows, NaN/Inf,
        wavelengths not strictly increasing or not covering the grid, a
        channel zero everywhere on the grid.

    Examples
    --------
    >>> rows = ["nm,r,g,b"] + [f"{w},{max(0, 1 - abs(w - 600) / 100)},{max(0, 1 - abs(w - 530) / 100)},"
    ...                        f"{max(0, 1 - abs(w - 450) / 100)}" for w in range(380, 790, 10)]
    >>> camera_from_csv("\\n".join(rows).encode()).channels
    3
    """
    from models import resample

    table = read_csv_table(data, "the sensitivities CSV")
    wl_grid = _grid(wavelengths)
    header = table.header
    arr = np.column_stack([table.wavelengths, table.values])
    if arr.shape[1] < 4:
        raise InputError(f"need a wavelength column and at least 3 channel columns; found {arr.shape[1] - 1} "
                         "channel column(s)", code="bad_csv")
    if arr.shape[1] - 1 > MAX_CSV_CHANNELS:
        raise InputError(f"{arr.shape[1] - 1} channel columns, more than {MAX_CSV_CHANNELS}: give one column "
                         "per camera channel (an RGB camera has 3) after the wavelength column", code="bad_csv")
    if arr.shape[0] < 2:
        raise InputError("need at least two wavelengths", code="bad_csv")
    wl = arr[:, 0]
    d = np.diff(wl)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise InputError(f"wavelengths must be strictly increasing: {wl[i + 1]:g} nm follows {wl[i]:g} nm "
                         f"(data row {i + 2})", code="bad_csv")
    lo, hi = float(wl_grid[0]), float(wl_grid[-1])
    if wl[0] > lo + 1e-9 or wl[-1] < hi - 1e-9:
        hint = " (micrometres? give nanometres)" if wl[-1] < 10 else ""
        raise InputError(f"wavelengths span {wl[0]:g}-{wl[-1]:g} nm{hint}; they must cover {lo:g}-{hi:g} nm",
                         code="bad_csv")
    sens = arr[:, 1:]
    labels = (header[1:] if header and len(header) == arr.shape[1]
              else [f"channel {k + 1}" for k in range(sens.shape[1])])
    notes = []
    if np.any(sens < 0):
        notes.append(f"{int((sens < 0).sum())} negative value(s) clipped to 0")
    clipped = np.clip(sens, 0.0, None)
    if arr.shape[0] >= 6:      # colour-science's Sprague/spline interpolation needs 6 points
        on_grid = resample(wl, clipped, wl_grid)
    else:
        on_grid = np.stack([np.interp(wl_grid, wl, clipped[:, k]) for k in range(clipped.shape[1])], 1)
    on_grid = np.clip(on_grid, 0.0, None)
    zero = [labels[k] for k in range(sens.shape[1]) if not np.any(on_grid[:, k] > 0)]
    if zero:
        raise InputError(f"channel(s) {', '.join(map(str, zero))} are zero at every wavelength in "
                         f"{lo:g}-{hi:g} nm", code="bad_csv")
    on_grid = on_grid / on_grid.max()
    notes.insert(0, f"uploaded sensitivities: {sens.shape[1]} channels ({', '.join(map(str, labels))}), "
                    f"{wl[0]:g}-{wl[-1]:g} nm, {arr.shape[0]} rows, resampled to {wl_grid.size} wavelengths")
    return Camera(wl_grid, on_grid, name, "uploaded", tuple(notes))


def resolve_camera(image=None, camera: str | None = None,
                   sensitivities_csv: bytes | None = None, wavelengths=None):
    """Choose the camera model for an image, and say how approximate it is.

    Priority:

    1. ``sensitivities_csv`` (:func:`camera_from_csv`), ``source="uploaded"``;
    2. ``camera``: a measured camera name (``models.camera_names()`` or an
       alias), ``"generic"`` or ``"matrix"`` (needs a colour matrix in the
       file); ``"auto"``, ``""`` or ``None`` mean choose automatically;
    3. the measured camera matching the file's Make + Model
       (``models.canonical_camera_name``);
    4. sensitivities derived from the file's colour matrix
       (:func:`camera_from_matrix`), with the warning
       ``"approximate: derived from colour matrix"``;
    5. :func:`generic_camera`, with a warning.

    Parameters
    ----------
    image : object or None
        What the file says about its camera: any object with ``make``,
        ``model`` and ``color_matrix`` attributes (missing ones count as
        unknown), e.g. the service's decoded upload.
    camera : str, optional
    sensitivities_csv : bytes, optional
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm.

    Returns
    -------
    (recovery.Camera, list of str)
        The camera and the warnings to show the user.

    Raises
    ------
    InputError
        ``unknown_camera`` (the detail lists the accepted names),
        ``no_color_matrix`` (``camera="matrix"`` for a file without one),
        ``bad_csv``, ``bad_color_matrix``.
    """
    from models import camera_names, canonical_camera_name

    wl = _grid(wavelengths)
    warnings: list[str] = []
    make = getattr(image, "make", None)
    model = getattr(image, "model", None)
    ident = " ".join(x for x in (make, model) if x) or None
    file_canon = None
    if ident:
        file_canon = canonical_camera_name(ident) or (canonical_camera_name(model) if model else None)
    cm = getattr(image, "color_matrix", None)
    choice = (camera or "").strip()

    if sensitivities_csv is not None and len(sensitivities_csv) > 0:
        cam = camera_from_csv(sensitivities_csv, wl)
        if choice and choice.lower() != "auto":
            warnings.append(f"camera {choice!r} ignored: the uploaded sensitivities take precedence")
        return cam, warnings

    if choice and choice.lower() != "auto":
        low = choice.lower()
        if low == "generic":
            warnings.append("approximate: generic camera (mean of the measured cameras' sensitivities)")
            return generic_camera(wl), warnings
        if low == "matrix":
            if cm is None:
                raise InputError("camera='matrix' needs an XYZ->camera colour matrix, and this image has none "
                                 "(DNG ColorMatrix, or a camera model LibRaw knows)", code="no_color_matrix")
            cam = camera_from_matrix(cm, wl, _matrix_name(ident))
            warnings.append("approximate: derived from colour matrix")
            return cam, warnings
        canon = canonical_camera_name(choice)
        if canon is None:
            accepted = camera_names() + ["generic", "matrix", "auto"]
            raise InputError(f"unknown camera {choice!r}; accepted: {', '.join(accepted)} (or upload a "
                             "sensitivities CSV)", code="unknown_camera")
        if ident and file_canon != canon:
            warnings.append(f"camera {canon!r} was requested but the file says {ident!r}")
            return Camera.named(canon, wl), warnings
        # the file's own matrix goes with its measured camera (the learnt estimator's canonical space)
        return Camera.named(canon, wl).with_color_matrix(cm), warnings

    if file_canon is not None:
        return Camera.named(file_canon, wl).with_color_matrix(cm), warnings
    if cm is not None:
        try:
            cam = camera_from_matrix(cm, wl, _matrix_name(ident))
        except InputError as exc:
            warnings.append(f"the file's colour matrix is unusable ({exc.detail})")
        else:
            warnings.append("approximate: derived from colour matrix")
            return cam, warnings
    who = repr(ident) if ident else "this image (no make/model)"
    warnings.append(f"approximate: no measured sensitivities or colour matrix for {who}; using a generic camera "
                    "(mean of the measured cameras' sensitivities); give camera=... or upload sensitivities")
    return generic_camera(wl), warnings


def _matrix_name(ident: str | None) -> str:
    return f"{ident} (matrix-derived)" if ident else "matrix-derived"
