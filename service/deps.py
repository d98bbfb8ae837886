"""Request dependencies: size-limited upload reading (option validation,
free of the web stack, is :mod:`service.options`)."""

from __future__ import annotations

from fastapi import UploadFile

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
