"""Former name of :mod:`service.decode` (uploads to linear camera RGB), kept for the callers
that import it: every name of the modules it was split into, re-exported.
"""

from __future__ import annotations

from .decode.formats import (  # noqa: F401
    _NOT_RAW, _extension, _is_text, _sniff, camera_label,
)
from .decode.image import (  # noqa: F401
    DecodedImage, FLIP_OPS, RAW_EXTENSIONS, SATURATION_FRACTION, _uint16_to_unit_float,
)
from .decode.linear import (  # noqa: F401
    LINEAR_TIFF_COMPRESSIONS, _LINEAR_NOTE, _NEEDS_IMAGECODECS, _NOT_LINEAR, _check_linear_compression,
    _decode_png, _decode_tiff, _linear_image, _png_chunks,
)
from .decode.raw import (  # noqa: F401
    DEMOSAIC_DEFAULT, _OPENCV_BAYER, _bayer_channels, _bin_bayer, _bin_bayer_area, _decode_raw, _librawmsg,
    _opencv_full_linear, _oriented_shape, _raw_full_linear,
)
from .decode.structure import (  # noqa: F401
    _ENTRY_LIMIT, _IFD_LIMIT, _JPEG_SOF, _PHOTOMETRIC_RAW, _STRUCTURE_TAGS, _TAG_NAMES, _TIFF_TYPE_SIZES,
    _Unverifiable, _check_image_ifd, _check_jpeg, _check_tiff_structure, _ifd_values, _one, _read_ifd,
    _tags_present, _tiff_structured,
)
from .decode.tags import (  # noqa: F401
    MAX_FILE_STRING, _TiffInfo, _ascii_tag, _iter_ifds, _srational_matrix, _tag, _tiff_info, file_string,
)
from .decode.upload import (  # noqa: F401
    _decode_raw_or_tiff, decode_upload,
)

__all__ = ['DecodedImage', 'decode_upload', 'SATURATION_FRACTION', 'FLIP_OPS']
