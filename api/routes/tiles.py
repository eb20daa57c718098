"""XYZ tiles and TileJSON of a job's rasters, read with rio-tiler from that job's own COGs only.

Two rasters have tiles: a mosaic job's mosaic, and each load step's rectified specimen of a crack survey (a
load step: one entry of the survey's ``options.stages``, so named apart from the pipeline's stages; the former
``/tiles/{job}/stages/{stage}/...`` paths still answer the same, hidden from the schema). Both routes name a job
(and a load step), never a path; they share the tile and TileJSON code below.

A georeferenced raster is served in WebMercatorQuad. A raster without map coordinates (a mosaic without
GPS: no CRS; a specimen: a local engineering CRS in mm, neither geographic nor projected) is served in
rio-tiler's local pixel grid (``ImageReader``), and its TileJSON says so, so the viewer shows it in a
plain pixel plane instead of pretending it lies somewhere on Earth.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from fastapi import APIRouter, Request, Response
from morecantile import Tile
from rio_tiler.constants import WGS84_CRS
from rio_tiler.errors import TileOutsideBounds
from rio_tiler.io import ImageReader, Reader
from rio_tiler.models import ImageData

from api import job_service
from api.deps import DbDep, JobId, SettingsDep, TileIndex
from api.errors import ConflictError, NotFoundError
from api.photo_jobs import job_of_kind
from core.kinds import JobKind
from workers.workspace import job_workspace

router = APIRouter(prefix="/tiles", tags=["tiles"])
TILE_SIZE = 256
MAX_ZOOM = 26
PNG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/png": {}}}}  # OpenAPI: tiles are PNG


# -- Which COG a route serves --------------------------------------------------------------------


def _mosaic_cog(db: Any, settings: Any, job_id: int) -> Path:
    job = job_service.get_job(db, job_id)  # 404 for an unknown job
    path = job_workspace(settings.data_dir, job_id).mosaic_path()
    if not path.exists():
        raise ConflictError(f"job {job_id} has no mosaic yet (status: {job.status})")
    return path


def _load_step_cog(db: Any, settings: Any, job_id: int, step: int) -> Path:
    job = job_of_kind(db, job_id, (JobKind.crack_survey,), "crack survey")  # 404 for any other job
    ws = job_workspace(settings.data_dir, job_id)
    count = len(ws.load_config().get("stages", [])) if ws.has_config() else 0  # options.stages
    if not 0 <= step < count:
        raise NotFoundError(f"crack survey {job_id} has no load step {step} (it has {count})")
    path = ws.load_step_cog_path(step)
    if not path.exists():
        raise ConflictError(f"load step {step} of crack survey {job_id} is not rectified yet (status: {job.status})")
    return path


# -- Routes --------------------------------------------------------------------------------------


@router.get("/{job_id}/{z}/{x}/{y}.png", responses=PNG)
def tile(job_id: JobId, z: TileIndex, x: TileIndex, y: TileIndex, db: DbDep, settings: SettingsDep) -> Response:
    """A 256 px PNG tile, transparent outside the mosaic; 404 outside the bounds its TileJSON gives."""
    return _tile_response(_mosaic_cog(db, settings, job_id), z, x, y, f"the mosaic of job {job_id}")


@router.get("/{job_id}/tilejson.json")
def tilejson(job_id: JobId, request: Request, db: DbDep, settings: SettingsDep) -> dict[str, Any]:
    """TileJSON 2.2.0 of the job's mosaic; ``georeferenced: false`` means a local pixel grid."""
    path = _mosaic_cog(db, settings, job_id)
    return _tilejson(path, request.url_for("tile", job_id=job_id, z=0, x=0, y=0), f"job {job_id} mosaic")


@router.get("/{job_id}/load-steps/{step}/{z}/{x}/{y}.png", responses=PNG)
def load_step_tile(
    job_id: JobId, step: TileIndex, z: TileIndex, x: TileIndex, y: TileIndex, db: DbDep, settings: SettingsDep
) -> Response:
    """A 256 px PNG tile of load step ``step`` (0-based, the order of ``options.stages``) of a crack survey,
    rectified onto the specimen."""
    path = _load_step_cog(db, settings, job_id, step)
    return _tile_response(path, z, x, y, f"load step {step} of crack survey {job_id}")


@router.get("/{job_id}/load-steps/{step}/tilejson.json")
def load_step_tilejson(
    job_id: JobId, step: TileIndex, request: Request, db: DbDep, settings: SettingsDep
) -> dict[str, Any]:
    """TileJSON 2.2.0 of one load step's rectified specimen, a local pixel grid (``georeferenced: false``):
    its pixel (col, row) spans [col, col + 1] x [row, row + 1] and is centred on the specimen point
    (X, Y) = (col, row) * mm_per_px, mm (``report.json``)."""
    path = _load_step_cog(db, settings, job_id, step)
    template = request.url_for("load_step_tile", job_id=job_id, step=step, z=0, x=0, y=0)
    return _tilejson(path, template, f"crack survey {job_id} load step {step}")


# The former paths of the two routes above (a load step was called a stage), kept for links and clients made
# before the rename and hidden from the schema; their TileJSON points at the load-steps tiles.


@router.get("/{job_id}/stages/{stage}/{z}/{x}/{y}.png", include_in_schema=False)
def stage_tile(
    job_id: JobId, stage: TileIndex, z: TileIndex, x: TileIndex, y: TileIndex, db: DbDep, settings: SettingsDep
) -> Response:
    return load_step_tile(job_id, stage, z, x, y, db, settings)


@router.get("/{job_id}/stages/{stage}/tilejson.json", include_in_schema=False)
def stage_tilejson(
    job_id: JobId, stage: TileIndex, request: Request, db: DbDep, settings: SettingsDep
) -> dict[str, Any]:
    return load_step_tilejson(job_id, stage, request, db, settings)


# -- Reading a COG -------------------------------------------------------------------------------


def _open(path: Path) -> Reader:
    """rio-tiler's reader: on the Earth for a geographic or projected CRS, the pixel grid otherwise."""
    with rasterio.open(path) as src:
        mapped = src.crs is not None and (src.crs.is_geographic or src.crs.is_projected)
    return Reader(str(path)) if mapped else ImageReader(str(path))


def _tile_response(path: Path, z: int, x: int, y: int, what: str) -> Response:
    if not 0 <= z <= MAX_ZOOM or x < 0 or y < 0:
        raise NotFoundError(f"tile {z}/{x}/{y} does not exist")
    with _open(path) as reader:
        georeferenced = reader.crs is not None
        # The local pixel grid of a raster without map coordinates has more than 2**z columns at a zoom level.
        if georeferenced and not (x < 2**z and y < 2**z):
            raise NotFoundError(f"tile {z}/{x}/{y} does not exist")
        try:
            if not reader.tile_exists(x, y, z):
                raise TileOutsideBounds
            png = reader.tile(x, y, z, tilesize=TILE_SIZE).render(img_format="PNG")
        except TileOutsideBounds:
            # A UTM mosaic is slightly rotated inside its lon/lat box, so rio-tiler calls tiles at the
            # box's corners outside; they are inside the advertised bounds: answer them empty, not 404.
            if not (georeferenced and _meets_geographic_bounds(reader, x, y, z)):
                raise NotFoundError(f"tile {z}/{x}/{y} is outside {what}") from None
            png = _empty_png()
    return Response(png, media_type="image/png", headers={"Cache-Control": "public, max-age=3600"})


def _meets_geographic_bounds(reader: Reader, x: int, y: int, z: int) -> bool:
    west, south, east, north = reader.get_geographic_bounds(WGS84_CRS)
    t_west, t_south, t_east, t_north = reader.tms.bounds(Tile(x, y, z))
    return bool(t_west < east and t_east > west and t_south < north and t_north > south)


@lru_cache(maxsize=1)
def _empty_png() -> bytes:
    return bytes(ImageData(np.ma.masked_all((3, TILE_SIZE, TILE_SIZE), dtype="uint8")).render(img_format="PNG"))


def _tilejson(path: Path, tile_zero: Any, name: str) -> dict[str, Any]:
    """TileJSON of the COG at ``path``; ``tile_zero`` is the URL of its tile 0/0/0."""
    template = str(tile_zero).removesuffix("/0/0/0.png") + "/{z}/{x}/{y}.png"
    with _open(path) as reader:
        georeferenced = reader.crs is not None
        if georeferenced:
            west, south, east, north = reader.get_geographic_bounds(WGS84_CRS)
        else:  # pixel plane, y pointing down as rows do: Leaflet's CRS.Simple shows it with y negated
            west, south, east, north = 0.0, -float(reader.height), float(reader.width), 0.0
        minzoom, maxzoom = int(reader.minzoom), int(reader.maxzoom)
    return {
        "tilejson": "2.2.0",
        "name": name,
        "scheme": "xyz",
        "tiles": [template],
        "bounds": [west, south, east, north],
        "minzoom": minzoom,
        "maxzoom": maxzoom,
        "center": [(west + east) / 2, (south + north) / 2, max(minzoom, maxzoom - 2)],
        "georeferenced": georeferenced,
        "tile_size": TILE_SIZE,
    }
