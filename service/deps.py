"""Request dependencies: size-limited upload reading (option validation,
free of the web stack, is :mod:`service.options`)."""

from __future__ import annotations

import os

from fastapi import UploadFile
from starlette.concurrency import run_in_threadpool

from .errors import ServiceError
from .settings import Settings


async def read_upload(file: UploadFile | None, settings: Settings, field: str = "file") -> bytes:
    """The upload's bytes, refusing more than the configured limit (413)."""
    if file is None:
        raise ServiceError(422, "missing_file", f"multipart field {field!r} is required")
    data = await file.read(settings.max_upload_bytes + 1)
    if len(data) > settings.max_upload_bytes:
        raise ServiceError(413, "file_too_large",
                       f"{field} exceeds the upload limit of {settings.max_upload_bytes} bytes")
    return data


class Upload:
    """An upload checked against the size limit whose bytes are read only by
    :meth:`read`, which :func:`service.workers.run_heavy` calls in its worker
    thread once the request holds a work slot. Until then the file stays in
    the temporary file the multipart parser spooled it to (TMPDIR, past
    1 MB), so a request queued behind others holds no copy of it in memory
    (probe round 9: 16 queued 60 MB TIFFs held 0.9 GB of the server's
    memory while they waited; the default connection limit allows hundreds)."""

    def __init__(self, file: UploadFile):
        self._file = file
        self.filename = file.filename

    def read(self) -> bytes:
        """The whole file (blocking: call it off the event loop)."""
        f = self._file.file
        f.seek(0)
        return f.read()


async def checked_upload(file: UploadFile | None, settings: Settings, field: str = "file") -> Upload:
    """The upload, unread (:class:`Upload`), refusing more than the configured
    limit (413) as :func:`read_upload` does."""
    if file is None:
        raise ServiceError(422, "missing_file", f"multipart field {field!r} is required")
    size = file.size
    if size is None:        # the parser always sets it; measured otherwise
        size = await run_in_threadpool(lambda: file.file.seek(0, os.SEEK_END))
    if size > settings.max_upload_bytes:
        raise ServiceError(413, "file_too_large",
                           f"{field} exceeds the upload limit of {settings.max_upload_bytes} bytes")
    return Upload(file)
