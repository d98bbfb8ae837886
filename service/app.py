"""FastAPI application (``service.app:app``): a thin shell around
:mod:`recovery`. OpenAPI at ``/docs``."""

from __future__ import annotations

from fastapi import FastAPI, Request

from . import __doc__ as _doc
from .errors import error_response, install_error_handlers
from .routers import analysis, batches, info
from .settings import get_settings

app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=_doc,
              lifespan=batches.lifespan)
install_error_handlers(app)
app.include_router(info.router)
app.include_router(analysis.router)
app.include_router(batches.router)


@app.middleware("http")
async def limit_body_size(request: Request, call_next):
    """Refuse a declared body over the upload limit before reading it (413)."""
    settings = get_settings()
    limit = settings.max_upload_bytes
    if request.url.path == "/v1/batches":  # several files: the per-file limit is checked as each is saved
        limit *= settings.max_batch_items
    length = request.headers.get("content-length")
    if length is not None:
        try:
            n = int(length)
        except ValueError:
            return error_response(400, "bad_content_length", "Content-Length is not an integer")
        if n > limit + 1024 * 1024:  # multipart framing on top of the file
            return error_response(413, "file_too_large", f"request body of {n} bytes exceeds the upload "
                                  f"limit of {limit} bytes")
    return await call_next(request)
