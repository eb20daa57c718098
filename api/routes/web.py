"""The static viewer, its vendored libraries, offline API docs, health and viewer configuration."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from sqlalchemy import text

from api.deps import DbDep, SettingsDep

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


@router.get("/api/health", tags=["service"])
def health(db: DbDep) -> dict[str, Any]:
    with db.session() as s:
        s.execute(text("SELECT 1"))
    return {"status": "ok", "database": "ok"}


@router.get("/api/config", tags=["service"])
def viewer_config(settings: SettingsDep) -> dict[str, Any]:
    """What the viewer needs to know: an optional basemap URL template (empty: no basemap)."""
    return {"basemap_url": settings.basemap_url}
