"""FastAPI application (``service.app:app``): a thin shell around
:mod:`recovery`. OpenAPI at ``/docs``."""

from __future__ import annotations

from fastapi import FastAPI

from . import __doc__ as _doc
from .errors import install_error_handlers
from .routers import analysis, batches, info, render, web

app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=_doc,
              lifespan=batches.lifespan, docs_url=None, redoc_url=None)
install_error_handlers(app)
# /docs offline: Swagger UI's assets from a package, served here; the OpenAPI completed
from .openapi_docs import install as _install_docs  # noqa: E402

_install_docs(app)
app.include_router(info.router)
app.include_router(analysis.router)
app.include_router(batches.router)
app.include_router(render.router)
app.include_router(web.router)

# HEAD answered wherever GET is (RFC 9110 9.1), not a 405
from .head import allow_head  # noqa: E402

allow_head(app)


# the upload limit, for declared and for streamed (chunked) bodies alike
from .limits import UploadLimitMiddleware  # noqa: E402

app.add_middleware(UploadLimitMiddleware)

# an answer the client stops taking is given up after WANDELL_SEND_TIMEOUT
from .limits import SendDeadlineMiddleware  # noqa: E402

app.add_middleware(SendDeadlineMiddleware)

# outermost: Host and Origin are checked before anything else runs
from .security import HostOriginMiddleware  # noqa: E402

app.add_middleware(HostOriginMiddleware)
