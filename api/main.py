"""The ASGI application: ``create_app(settings)`` wires settings, database, queue and routes."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from api.errors import install_error_handlers
from api.limits import JsonBodyLimits
from api.queue import CeleryQueue, JobQueue
from api.routes import calibrations, crack_surveys, flights, jobs, tiles, web
from core.db import Database
from core.settings import Settings, get_settings


def create_app(settings: Settings | None = None, queue: JobQueue | None = None) -> FastAPI:
    """Build the service. ``queue`` defaults to Celery on ``settings.redis_url``."""
    settings = settings or get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    app = FastAPI(
        title="Fotoskhema",
        version="0.1.0",
        docs_url=None,
        redoc_url=None,
        description="Upload drone flights, run mosaic jobs, view the result as XYZ tiles.",
    )
    app.state.settings = settings
    app.state.db = Database(settings.resolved_database_url())
    app.state.queue = queue or CeleryQueue(settings.redis_url, settings.celery_queue)
    install_error_handlers(app)
    app.add_middleware(JsonBodyLimits)  # size, depth and numbers of a JSON body, before it is parsed
    for module in (flights, jobs, calibrations, crack_surveys, tiles, web):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=settings.web_dir), name="static")
    vendor = settings.web_dir / "node_modules"
    if (vendor / "leaflet").is_dir():
        app.mount("/vendor/leaflet", StaticFiles(directory=vendor / "leaflet" / "dist"), name="leaflet")
    if (vendor / "swagger-ui-dist").is_dir():
        app.mount("/vendor/swagger-ui", StaticFiles(directory=vendor / "swagger-ui-dist"), name="swagger-ui")
    return app
