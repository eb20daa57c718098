"""The ASGI application: ``create_app(settings)`` wires settings, database, queue and routes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles
from pydantic.json_schema import models_json_schema

from api.auth import BearerForWrites, TrustedHosts, authorize
from api.errors import install_error_handlers
from api.folder_import import ImportRunner
from api.limits import JsonBodyLimits, RequestLimits
from api.queue import CeleryQueue, JobQueue
from api.reaper import lifespan
from api.routes import (
    calibrations,
    crack_surveys,
    flights,
    imports,
    jobs,
    nodeodm,
    stereo_dems,
    tiles,
    uploads,
    users,
    web,
)
from api.routes.uploads import TusMethodOverride
from api.tiler import Tiler
from core.accounts import TokenCache
from core.db import Database
from core.settings import Settings, get_settings
from workers.config import JOB_KINDS


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
        lifespan=lifespan,  # the reaper: jobs whose worker died or whose next stage was lost are sent again
    )
    app.state.settings = settings
    app.state.db = Database(settings.resolved_database_url())
    app.state.tokens = TokenCache(app.state.db)  # who a token is, remembered a few seconds
    # open COGs and rendered tiles of this process; closed by the lifespan
    app.state.tiler = Tiler(settings.tile_cache_bytes, settings.tile_open_cogs, settings.tile_readers_per_cog)
    app.state.queue = queue or CeleryQueue(settings.redis_url, settings.celery_queue)
    app.state.imports = ImportRunner(app.state.db, settings)  # server-side folder imports; stopped by the lifespan
    install_error_handlers(app)
    app.add_middleware(JsonBodyLimits)  # size, depth and numbers of a JSON body, before it is parsed
    app.add_middleware(RequestLimits, settings=settings)  # body, file and part sizes, counted as they stream
    if settings.cors_origins:  # closed by default: the viewer is served from this origin
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "PUT", "DELETE", "PATCH", "HEAD"],  # PATCH, HEAD: tus uploads
            allow_headers=["Authorization", "Content-Type", *uploads.TUS_REQUEST_HEADERS],
            expose_headers=uploads.TUS_RESPONSE_HEADERS,
        )
    app.add_middleware(
        BearerForWrites, tokens=app.state.tokens
    )  # an anonymous write is refused before its body is read
    app.add_middleware(TrustedHosts, allowed=settings.allowed_hosts)  # before anything is read
    app.add_middleware(TusMethodOverride)  # outermost: a tus POST that says it is a PATCH is one for all the rest
    for module in (flights, uploads, imports, jobs, calibrations, crack_surveys, stereo_dems, tiles):
        app.include_router(module.router, dependencies=[Depends(authorize)])  # a token, and only one's own
    app.include_router(users.router)  # its routes say who may call them
    app.include_router(nodeodm.router)  # WebODM's processing-node API: a token as ?token=, owner checks by task
    app.include_router(web.router)  # viewer, health and configuration: open
    app.mount("/static", StaticFiles(directory=settings.web_dir), name="static")
    vendor = settings.web_dir / "node_modules"
    if (vendor / "leaflet").is_dir():
        app.mount("/vendor/leaflet", StaticFiles(directory=vendor / "leaflet" / "dist"), name="leaflet")
    if (vendor / "tus-js-client").is_dir():  # the viewer's resumable uploads
        app.mount("/vendor/tus", StaticFiles(directory=vendor / "tus-js-client" / "dist"), name="tus-js-client")
    if (vendor / "geographiclib-geodesic").is_dir():  # the map's geodesic distances and areas
        app.mount("/vendor/geodesic", StaticFiles(directory=vendor / "geographiclib-geodesic"), name="geodesic")
    if (vendor / "proj4").is_dir():  # the map's coordinates in the mosaic's CRS
        app.mount("/vendor/proj4", StaticFiles(directory=vendor / "proj4" / "dist"), name="proj4")
    if (vendor / "swagger-ui-dist").is_dir():
        app.mount("/vendor/swagger-ui", StaticFiles(directory=vendor / "swagger-ui-dist"), name="swagger-ui")
    app.openapi = _with_option_schemas(app)  # type: ignore[method-assign]
    return app


def _with_option_schemas(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """``app.openapi`` with every job kind's options (``workers.config.JOB_KINDS``: ``MosaicConfig`` and the others)
    among the schemas: the routes take options as a free JSON object (checked against the kind's model, with the
    option named in a 422), so the schema would not list them otherwise."""
    made = app.openapi

    def openapi() -> dict[str, Any]:
        first = app.openapi_schema is None
        schema = made()
        if first:
            _, defs = models_json_schema(
                [(model, "validation") for model in JOB_KINDS.values()], ref_template="#/components/schemas/{model}"
            )
            known = schema.setdefault("components", {}).setdefault("schemas", {})
            known.update({name: s for name, s in defs.get("$defs", {}).items() if name not in known})
        return schema

    return openapi
