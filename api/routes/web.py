"""The static viewer, its vendored libraries, offline API docs, health and viewer configuration."""

from __future__ import annotations

from typing import Any
from urllib.parse import urlsplit

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from api.deps import DbDep, QueueDep, SettingsDep
from api.job_service import form_options
from api.queue import MonitoredQueue
from core.db import Database
from core.settings import OSM_TILES

router = APIRouter()


@router.get("/", include_in_schema=False)
def index(settings: SettingsDep) -> FileResponse:
    return FileResponse(settings.web_dir / "index.html", media_type="text/html")


@router.get("/docs", include_in_schema=False)
def docs(request: Request) -> HTMLResponse:
    """Swagger UI from the npm package installed at set-up (no CDN: the machines are offline)."""
    return get_swagger_ui_html(
        openapi_url=str(request.app.openapi_url),
        title="Fotoskhema API",
        swagger_js_url="/vendor/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url="/vendor/swagger-ui/swagger-ui.css",
        swagger_favicon_url="/static/favicon.svg",
    )


@router.get(
    "/api/health",
    tags=["service"],
    responses={503: {"description": "the database, the broker or every worker is down"}},
)
def health(db: DbDep, queue: QueueDep, settings: SettingsDep) -> JSONResponse:
    """Database, broker (Redis) and workers (a beacon in the last three beacon periods); 503 when any is down.
    Each probe is bounded (a fraction of a second), so a monitor gets its answer within a second."""
    checks = {"database": _database_state(db)}
    if isinstance(queue, MonitoredQueue):  # a queue that stands in for Celery in tests has none to check
        checks.update(queue.liveness(worker_max_age=3 * settings.worker_beacon_seconds))
    healthy = all(state == "ok" for state in checks.values())
    body = {"status": "ok" if healthy else "unavailable", **checks}
    return JSONResponse(body, status_code=200 if healthy else 503)


def _database_state(db: Database) -> str:
    try:
        with db.session() as s:
            s.execute(text("SELECT 1"))
    except SQLAlchemyError:
        return "down"
    return "ok"


@router.get("/api/config", tags=["service"])
def viewer_config(settings: SettingsDep) -> dict[str, Any]:
    """What the viewer needs to know: the basemap URL template (OpenStreetMap unless ops set another, empty when
    they turned it off) and its name, whether reads need no token, the upload limits it splits a big selection of
    photos by, from what size it sends a photo by resumable upload, how many import directories there are, and
    the mosaic options its form offers with their defaults per mode."""
    basemap = settings.basemap()
    return {
        "basemap_url": basemap,
        "basemap_name": "OpenStreetMap"
        if basemap == OSM_TILES
        else (urlsplit(basemap).hostname or "")
        if basemap
        else "",
        "public_read": settings.public_read,
        "max_upload_bytes": settings.max_upload_bytes,
        "max_request_bytes": settings.max_request_bytes,
        "max_files_per_request": settings.max_files_per_request,
        # files this large go by resumable (tus) upload, in PATCHes of resumable_chunk_bytes
        "resumable_upload_bytes": settings.resumable_upload_bytes,
        "resumable_chunk_bytes": settings.resumable_chunk_bytes,
        "import_dirs": len(settings.import_dirs),  # how many; server-side import is off when 0
        "mosaic_options": form_options(),
    }
