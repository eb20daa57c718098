"""XYZ tiles and TileJSON of a job's mosaic, read with rio-tiler from that job's COG only.

A georeferenced mosaic is served in WebMercatorQuad. A mosaic without GPS has no map coordinates:
it is served in rio-tiler's local pixel grid (``ImageReader``), and its TileJSON says so, so the
viewer shows it in a plain pixel plane instead of pretending it lies somewhere on Earth.
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
from api.deps import DbDep, SettingsDep
from api.errors import ConflictError, NotFoundError
from workers.workspace import job_workspace

router = APIRouter(prefix="/tiles", tags=["tiles"])
TILE_SIZE = 256
MAX_ZOOM = 26


def _cog_path(db: Any, settings: Any, job_id: int) -> Path:
    job = job_service.get_job(db, job_id)  # 404 for an unknown job
    path = job_workspace(settings.data_dir, job_id).mosaic_file()
    if not path.exists():
        raise ConflictError(f"job {job_id} has no mosaic yet (status: {job.status})")
    return path


def _open(path: Path) -> Reader:
    with rasterio.open(path) as src:
        georeferenced = src.crs is not None
    return Reader(str(path)) if georeferenced else ImageReader(str(path))


@router.get("/{job_id}/{z}/{x}/{y}.png", responses={200: {"content": {"image/png": {}}}})
def tile(job_id: int, z: int, x: int, y: int, db: DbDep, settings: SettingsDep) -> Response:
    """A 256 px PNG tile, transparent outside the mosaic; 404 outside the bounds its TileJSON gives."""
    path = _cog_path(db, settings, job_id)
    if not 0 <= z <= MAX_ZOOM or x < 0 or y < 0:
        raise NotFoundError(f"tile {z}/{x}/{y} does not exist")
    with _open(path) as reader:
        georeferenced = reader.crs is not None
        # The local pixel grid of a mosaic without GPS has more than 2**z columns at a zoom level.
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
                raise NotFoundError(f"tile {z}/{x}/{y} is outside the mosaic of job {job_id}") from None
            png = _empty_png()
    return Response(png, media_type="image/png", headers={"Cache-Control": "public, max-age=3600"})


def _meets_geographic_bounds(reader: Reader, x: int, y: int, z: int) -> bool:
    west, south, east, north = reader.get_geographic_bounds(WGS84_CRS)
    t_west, t_south, t_east, t_north = reader.tms.bounds(Tile(x, y, z))
    return bool(t_west < east and t_east > west and t_south < north and t_north > south)


@lru_cache(maxsize=1)
def _empty_png() -> bytes:
    return bytes(ImageData(np.ma.masked_all((3, TILE_SIZE, TILE_SIZE), dtype="uint8")).render(img_format="PNG"))


@router.get("/{job_id}/tilejson.json")
def tilejson(job_id: int, request: Request, db: DbDep, settings: SettingsDep) -> dict[str, Any]:
    """TileJSON 2.2.0 of the job's mosaic; ``georeferenced: false`` means a local pixel grid."""
    path = _cog_path(db, settings, job_id)
    template = str(request.url_for("tile", job_id=job_id, z=0, x=0, y=0)).replace("/0/0/0.png", "/{z}/{x}/{y}.png")
    with _open(path) as reader:
        georeferenced = reader.crs is not None
        if georeferenced:
            west, south, east, north = reader.get_geographic_bounds(WGS84_CRS)
        else:  # pixel plane, y pointing down as rows do: Leaflet's CRS.Simple shows it with y negated
            west, south, east, north = 0.0, -float(reader.height), float(reader.width), 0.0
        minzoom, maxzoom = int(reader.minzoom), int(reader.maxzoom)
    return {
        "tilejson": "2.2.0", "name": f"job {job_id} mosaic", "scheme": "xyz", "tiles": [template],
        "bounds": [west, south, east, north], "minzoom": minzoom, "maxzoom": maxzoom,
        "center": [(west + east) / 2, (south + north) / 2, max(minzoom, maxzoom - 2)],
        "georeferenced": georeferenced, "tile_size": TILE_SIZE,
    }
