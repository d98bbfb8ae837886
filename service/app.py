"""FastAPI application (``service.app:app``): a thin shell around
:mod:`recovery`. OpenAPI at ``/docs``."""

from __future__ import annotations

from fastapi import FastAPI

from . import __doc__ as _doc
from .errors import install_error_handlers
from .limits import UploadLimitMiddleware
from .routers import analysis, info

app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=_doc)
install_error_handlers(app)
app.include_router(info.router)
app.include_router(analysis.router)


# the upload limit, for declared and for streamed (chunked) bodies alike
app.add_middleware(UploadLimitMiddleware)
