"""A ``tifffile.TiffFile`` over an upload's bytes that lets go of them when closed.

``tifffile.TiffFile(io.BytesIO(data))`` leaves the ``BytesIO`` open when the
TiffFile is closed (tifffile closes only the files it opened itself), and the
TiffFile's pages point back to it: a reference cycle that keeps the
``BytesIO``, and through it the whole upload, alive until Python's cyclic
garbage collector next runs a full pass. On a busy server that was the
memory of several uploads at once: 16 requests of a 60 MB TIFF sent together
left two or three of them (57 MiB each) in the process after every answer
had gone (``python -m benchmarks.request_costs --arenas``; ``docs/limits.md``).
:func:`tiff_file` closes the ``BytesIO`` with the TiffFile, so what the cycle
keeps is a few kB of tags.
"""

from __future__ import annotations

import io

__all__ = ["tiff_file"]


def tiff_file(data):
    """``tifffile.TiffFile`` reading ``data`` (bytes or a buffer); its ``close()`` (and the end of
    its ``with`` block) also closes the stream under it, releasing ``data``. Raises what
    ``TiffFile`` raises, having closed the stream."""
    import tifffile

    stream = io.BytesIO(data)
    try:
        tf = tifffile.TiffFile(stream)
    except BaseException:
        stream.close()
        raise
    tifffile_close = tf.close

    def close() -> None:
        try:
            tifffile_close()
        finally:
            stream.close()

    tf.close = close
    return tf
