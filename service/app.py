"""FastAPI application (``service.app:app``): a thin shell around
:mod:`recovery`. OpenAPI at ``/docs``."""

from __future__ import annotations

from fastapi import FastAPI

from . import __doc__ as _doc
from .errors import install_error_handlers
from .routers import analysis, batches, info, render, web

app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=_doc,
              lifespan=batches.lifespan)
install_error_handlers(app)
app.include_router(info.router)
app.include_router(analysis.router)
app.include_router(batches.router)
app.include_router(render.router)
app.include_router(web.router)


# the upload limit, for declared and for streamed (chunked) bodies alike
from .limits import UploadLimitMiddleware  # noqa: E402

app.add_middleware(UploadLimitMiddleware)

# outermost: Host and Origin are checked before anything else runs
from .security import HostOriginMiddleware  # noqa: E402

app.add_middleware(HostOriginMiddleware)
