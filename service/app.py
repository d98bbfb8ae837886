"""FastAPI application (``service.app:app``).

For now: ``GET /health``. The analysis endpoints of DESIGN.md come with
issue 3.
"""

from __future__ import annotations

from fastapi import Depends, FastAPI

from . import __doc__ as _doc
from .settings import Settings, get_settings

app = FastAPI(title="Wandell colour recovery service", version="0.1.0", description=_doc)


@app.get("/health")
def health(settings: Settings = Depends(get_settings)) -> dict:
    """Liveness: the service is up and the numerical core imports."""
    import recovery  # noqa: F401

    return {"status": "ok", "version": app.version, "max_upload_bytes": settings.max_upload_bytes}
