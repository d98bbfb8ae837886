"""FastAPI application (``service.app:app``): a thin shell around
:mod:`recovery`. OpenAPI at ``/docs``."""

from __future__ import annotations

import contextlib
import logging

from fastapi import Depends, FastAPI

from .errors import install_error_handlers
from .routers import analysis, batches, info, render, web
from .schemas.forms import reject_unknown_fields

#: The API's description on /docs (Markdown, as Swagger UI renders it).
DESCRIPTION = """\
Estimate the **light** of a photograph and the **reflectances** of its surfaces from camera RAW data
(Wandell 1985; Maloney & Wandell), and render a white-balanced image.

* `POST /v1/analyze`: the light (camera RGB, multipliers, spectrum, CCT/Duv, Camera Raw Temperature/Tint).
* `POST /v1/white-balance`: the corrected image (TIFF, PNG, JPEG) or an XMP sidecar; the estimate in the
  `X-Illuminant` header, or the estimate alone with `response=json`.
* `POST /v1/surfaces`: reflectance spectra at points, rectangles or a grid.
* `POST /v1/batches`: many files at once; follow `GET /v1/batches/{id}`, download the results, `DELETE` to
  cancel and then remove.
* `POST /v1/render`, `GET /v1/sampling`: spectral data rendered with a chosen wavelength sampling.

Uploads are the multipart field `file`; options are form fields, and an empty one (`metamers=`) is not
given: it takes its default. Every error is JSON
`{"error": code, "detail": text}`: 413 over a limit, 415 not a format the service reads, 422 a bad or
unknown option (named in the detail). The limits are in `GET /health`.
"""



@contextlib.asynccontextmanager
async def lifespan(app):
    """Cap the malloc arenas before the first worker thread (``python -m service`` has done it
    already; this is for ``uvicorn service.app:app``), then run the batch runner's lifespan."""
    from .workers import MALLOC_ARENAS, limit_malloc_arenas

    logging.getLogger("service").debug("malloc arenas at most %d: %s", MALLOC_ARENAS, limit_malloc_arenas())
    async with batches.lifespan(app):
        yield


app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=DESCRIPTION,
              lifespan=lifespan, docs_url=None, redoc_url=None,
              dependencies=[Depends(reject_unknown_fields)])
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
