"""Uploaded images to linear camera RGB (decoding only; which camera took the
image is :mod:`recovery.cameras`).

:func:`decode_upload` turns the bytes of an upload into a
:class:`DecodedImage`: a half-size, black-subtracted, saturation-scaled
*estimation image* made by binning each 2x2 Bayer cell (no demosaic), a
mask of saturated cells, the metadata that says which camera took it
(Make/Model, colour matrix, as-shot neutral, black and white levels), and
a method that demosaics the full-resolution image on the same scale when
(and only when) it is needed. Every refusal is a
:class:`~service.errors.ServiceError` (413, 415 or 422).

Scale of the estimation image. For a CFA site of colour ``c`` with digital
number :math:`d`, black level :math:`b_c` and white level :math:`w`,

.. math::

    v = \frac{d - b_c}{w - b_c},

so 1.0 is saturation in every channel; a cell's red and blue are its red and
blue sites, its green the mean of its two green sites. The full-resolution
image of :meth:`DecodedImage.full_linear` is LibRaw's demosaic of the same
numbers with ``value / 65535`` equal to :math:`v` (LibRaw subtracts the
per-channel black and scales by ``65535 / (w - min_c b_c)``; the per-channel
user white balance :math:`(w - \min_c b_c)/(w - b_c)` makes its scale exactly
the one above).

What LibRaw 0.22 (``rawpy`` 0.28) does with our files is measured in
``tests/test_dngwriter.py`` and ``tests/test_rawio.py`` (see also
:mod:`testing.dngwriter`): ``raw.sizes`` is read without unpacking the pixels
(so the pixel-count limit is enforced before any pixel buffer exists), a
truncated file fails only when the pixels are unpacked, and a file one byte
short decodes silently from memory, which is why the strip/tile extents of a
TIFF-structured file are checked against its length here.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12 and Fig. 6.
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, chapter 6 (ColorMatrix
maps XYZ to the camera's reference space).

The package, one concept a module: :mod:`~service.decode.upload`
(:func:`decode_upload`, the one entry point), :mod:`~service.decode.formats`
(what an upload is, from its bytes), :mod:`~service.decode.structure` (TIFF/DNG
strips and tiles verified before LibRaw reads them), :mod:`~service.decode.tags`
(TIFF/DNG tags), :mod:`~service.decode.raw` (LibRaw, CFA binning, demosaic),
:mod:`~service.decode.linear` (linear TIFF and PNG), :mod:`~service.decode.icc` (their ICC
profiles and PNG colour chunks: display-referred input linearised or refused) and
:mod:`~service.decode.image` (:class:`DecodedImage`). ``service.rawio``, its
former name, re-exports them.
"""

from __future__ import annotations

from .image import FLIP_OPS, SATURATION_FRACTION, DecodedImage
from .upload import decode_upload

__all__ = ["DecodedImage", "decode_upload", "SATURATION_FRACTION", "FLIP_OPS"]
