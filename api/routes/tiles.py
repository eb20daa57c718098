"""XYZ tiles and TileJSON of a job's rasters, read with rio-tiler from that job's own COGs only.

Three kinds of raster have tiles: a mosaic job's mosaic, each load step's rectified specimen of a crack survey
(a load step: one entry of the survey's ``options.stages``, so named apart from the pipeline's stages; the
former ``/tiles/{job}/stages/{stage}/...`` paths still answer the same, hidden from the schema), and a stereo
DEM's layers (``dsm``: its DSM as shaded relief, ``disparity``: its disparity map, colour-ramped), with a point
query of the value under a position (``/tiles/{job}/dsm/point``, ``/tiles/{job}/disparity/point``); an ortho
mosaic job's DSM (the surface its frames were projected onto) answers on the same ``dsm`` routes. The routes
name a job (and a load step or layer), never a path; they share the tile and TileJSON code below.

A georeferenced raster is served in WebMercatorQuad. A raster without map coordinates (a mosaic without
GPS: no CRS; a specimen: a local engineering CRS in mm, neither geographic nor projected) is served in
rio-tiler's local pixel grid (``ImageReader``), and its TileJSON says so, so the viewer shows it in a
plain pixel plane instead of pretending it lies somewhere on Earth.

Reading is :mod:`api.tiler`'s: each COG opened once per process, rendered tiles kept in a bounded cache, a
strong ETag per tile and version of its COG (``If-None-Match`` answered 304). ``Cache-Control`` is ``private``
unless ops turned on public read (tiles then need a token), and lets a browser reuse a tile without asking only
once its job has succeeded: until then a retry may rewrite the raster, so the browser revalidates every time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi import Path as PathParam
from sqlalchemy import select

from api import job_service
from api.auth import Viewer, job_signature, link_signature
from api.deps import DbDep, JobId, SettingsDep, TileIndex
from api.dsm_volume import dsm_volume as volume_inside
from api.errors import ConflictError, NotFoundError
from api.models import VolumeRequest
from api.tiler import TILE_SIZE, CogIdentity, TileNotFoundError, Tiler
from api.wmts import SUPPORTED_TMS, WmtsLayer, capabilities
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.workspace import job_workspace

router = APIRouter(prefix="/tiles", tags=["tiles"])
PNG: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {}}},
    304: {"description": "the tile named by ``If-None-Match`` is unchanged"},
}  # OpenAPI: tiles are PNG
WMTS_XML: dict[int | str, dict[str, Any]] = {200: {"content": {"application/xml": {}}}}


def get_tiler(request: Request) -> Tiler:
    """The app's tiler (``create_app`` makes one per process and app)."""
    return request.app.state.tiler  # type: ignore[no-any-return]


TilerDep = Annotated[Tiler, Depends(get_tiler)]
IfNoneMatch = Annotated[str | None, Header(include_in_schema=False)]
TmsId = Annotated[str, PathParam(max_length=64, description="the tile matrix set: WebMercatorQuad")]


# -- Which COG a route serves --------------------------------------------------------------------


class Cog:
    """The COG a route serves, the version found now, and whether its job has succeeded (it will not change)."""

    def __init__(self, path: Path, final: bool, missing: str) -> None:
        try:
            self.identity = CogIdentity.of(path)
        except FileNotFoundError:
            raise ConflictError(missing) from None
        self.final = final


def _job_status(db: Database, job_id: int, kind: JobKind | None, noun: str) -> str:
    """The job's status; 404 naming it a ``noun`` when there is none (of that ``kind``)."""
    return _job_kind_status(db, job_id, None if kind is None else (kind,), noun)[1]


def _job_kind_status(db: Database, job_id: int, kinds: tuple[JobKind, ...] | None, noun: str) -> tuple[str, str]:
    """The job's kind and status; 404 naming it a ``noun`` when there is none (of one of ``kinds``). Two columns
    on a bare connection, not the ORM record: this runs for every tile (~0.2 ms instead of ~0.9 ms)."""
    with db.engine.connect() as conn:
        row = conn.execute(select(Job.kind, Job.status).where(Job.id == job_id)).first()
    if row is None or (kinds is not None and row.kind not in kinds):
        raise NotFoundError(f"{noun} {job_id} not found")
    return str(row.kind), str(row.status)


def _mosaic_cog(db: Database, settings: Settings, job_id: int) -> Cog:
    status = _job_status(db, job_id, None, "job")  # any kind: a mosaic's tiles are found by the file
    path = job_workspace(settings.data_dir, job_id).mosaic_path()
    return Cog(path, status == JobStatus.succeeded, f"job {job_id} has no mosaic yet (status: {status})")


def _load_step_cog(db: Database, settings: Settings, job_id: int, step: int) -> Cog:
    status = _job_status(db, job_id, JobKind.crack_survey, "crack survey")  # 404 for any other job
    ws = job_workspace(settings.data_dir, job_id)
    count = len(ws.load_config().get("stages", [])) if ws.has_config() else 0  # options.stages
    if not 0 <= step < count:
        raise NotFoundError(f"crack survey {job_id} has no load step {step} (it has {count})")
    missing = f"load step {step} of crack survey {job_id} is not rectified yet (status: {status})"
    return Cog(ws.load_step_cog_path(step), status == JobStatus.succeeded, missing)


StereoLayer = Literal["dsm", "disparity"]  # a stereo DEM's shaded DSM, or its colour-ramped disparity map
STEREO_LAYER = "dsm: the DSM as hillshaded, colour-ramped relief; disparity: the left view's disparity map"


def _stereo_layer_cog(db: Database, settings: Settings, job_id: int, layer: StereoLayer) -> Cog:
    ws = job_workspace(settings.data_dir, job_id)
    path = ws.dsm_view_path() if layer == "dsm" else ws.disparity_view_path()
    return _stereo_file(db, settings, job_id, path, "DSM" if layer == "dsm" else "disparity map")


def _stereo_file(db: Database, settings: Settings, job_id: int, path: Path, what: str) -> Cog:
    """One of stereo DEM ``job_id``'s rasters, or an ortho mosaic job's DSM (the surface its frames went onto): 404
    for another kind of job, and when the finished job has none (only an RPC pair, or an ortho job projected onto
    a surface with map coordinates, has a DSM); 409 while it may still come."""
    kinds = (JobKind.stereo_dem, JobKind.mosaic) if what == "DSM" else (JobKind.stereo_dem,)
    kind, status = _job_kind_status(db, job_id, kinds, "stereo DEM" if len(kinds) == 1 else "job with a DSM")
    noun = f"stereo DEM {job_id}" if kind == JobKind.stereo_dem else f"job {job_id}"
    if status == JobStatus.succeeded and not path.exists():
        raise NotFoundError(f"{noun} has no {what}" + (f" ({NO_DSM[kind]})" if what == "DSM" else ""))
    return Cog(path, status == JobStatus.succeeded, f"{noun} has no {what} yet (status: {status})")


NO_DSM: dict[str, str] = {  # why a finished job of that kind has no DSM
    JobKind.stereo_dem: "its pair has no RPCs",
    JobKind.mosaic: "only an ortho job projected onto a surface, with map coordinates, has one",
}


# -- Routes --------------------------------------------------------------------------------------


@router.get("/{job_id}/{z}/{x}/{y}.png", responses=PNG)
def tile(
    job_id: JobId,
    z: TileIndex,
    x: TileIndex,
    y: TileIndex,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """A 256 px PNG tile, transparent outside the mosaic; 404 outside the bounds its TileJSON gives."""
    cog = _mosaic_cog(db, settings, job_id)
    return _tile_response(tiler, settings, cog, (z, x, y), if_none_match, f"the mosaic of job {job_id}")


@router.get("/{job_id}/tilejson.json")
def tilejson(job_id: JobId, request: Request, db: DbDep, settings: SettingsDep, tiler: TilerDep) -> dict[str, Any]:
    """TileJSON 2.2.0 of the job's mosaic; ``georeferenced: false`` means a local pixel grid."""
    cog = _mosaic_cog(db, settings, job_id)
    data = _tilejson(tiler, cog, request.url_for("tile", job_id=job_id, z=0, x=0, y=0), f"job {job_id} mosaic")
    return _signed_tiles(data, db, settings, job_id)


@router.get("/{job_id}/load-steps/{step}/{z}/{x}/{y}.png", responses=PNG)
def load_step_tile(
    job_id: JobId,
    step: TileIndex,
    z: TileIndex,
    x: TileIndex,
    y: TileIndex,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """A 256 px PNG tile of load step ``step`` (0-based, the order of ``options.stages``) of a crack survey,
    rectified onto the specimen."""
    cog = _load_step_cog(db, settings, job_id, step)
    what = f"load step {step} of crack survey {job_id}"
    return _tile_response(tiler, settings, cog, (z, x, y), if_none_match, what)


@router.get("/{job_id}/load-steps/{step}/tilejson.json")
def load_step_tilejson(
    job_id: JobId, step: TileIndex, request: Request, db: DbDep, settings: SettingsDep, tiler: TilerDep
) -> dict[str, Any]:
    """TileJSON 2.2.0 of one load step's rectified specimen, a local pixel grid (``georeferenced: false``):
    its pixel (col, row) spans [col, col + 1] x [row, row + 1] and is centred on the specimen point
    (X, Y) = (col, row) * mm_per_px, mm (``report.json``)."""
    cog = _load_step_cog(db, settings, job_id, step)
    template = request.url_for("load_step_tile", job_id=job_id, step=step, z=0, x=0, y=0)
    data = _tilejson(tiler, cog, template, f"crack survey {job_id} load step {step}")
    return _signed_tiles(data, db, settings, job_id)


# under "stereo/": a bare ``/{job}/{layer}/{z}/{x}/{y}.png`` would take the tile matrix set routes' paths
@router.get("/{job_id}/stereo/{layer}/{z}/{x}/{y}.png", responses=PNG)
def stereo_tile(
    job_id: JobId,
    layer: Annotated[StereoLayer, PathParam(description=STEREO_LAYER)],
    z: TileIndex,
    x: TileIndex,
    y: TileIndex,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """A 256 px PNG tile of a stereo DEM's layer: the DSM in WebMercatorQuad, the disparity in its pixels."""
    cog = _stereo_layer_cog(db, settings, job_id, layer)
    return _tile_response(tiler, settings, cog, (z, x, y), if_none_match, f"the {layer} of stereo DEM {job_id}")


@router.get("/{job_id}/{layer}/tilejson.json")
def stereo_tilejson(
    job_id: JobId,
    layer: Annotated[StereoLayer, PathParam(description=STEREO_LAYER)],
    request: Request,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
) -> dict[str, Any]:
    """TileJSON 2.2.0 of a stereo DEM's layer; the disparity map is a local pixel grid
    (``georeferenced: false``, the rectified left view)."""
    cog = _stereo_layer_cog(db, settings, job_id, layer)
    template = request.url_for("stereo_tile", job_id=job_id, layer=layer, z=0, x=0, y=0)
    data = _tilejson(tiler, cog, template, f"stereo DEM {job_id} {layer}")
    return _signed_tiles(data, db, settings, job_id)


Longitude = Annotated[float, Query(ge=-180.0, le=180.0, allow_inf_nan=False, description="degrees east")]
Latitude = Annotated[float, Query(ge=-90.0, le=90.0, allow_inf_nan=False, description="degrees north")]
PixelCoordinate = Annotated[float, Query(ge=-1e9, le=1e9, allow_inf_nan=False, description="left view pixels")]
STATES = {0: None, 1: "measured", 2: "filled"}  # dsm_mask.tif's codes


@router.get("/{job_id}/dsm/point")
def dsm_point(
    job_id: JobId, lon: Longitude, lat: Latitude, db: DbDep, settings: SettingsDep, tiler: TilerDep
) -> dict[str, Any]:
    """The DSM's elevation (m: above the WGS 84 ellipsoid for a stereo DEM; in the datum of the photos' GPS
    altitudes, or of the control points, for an ortho job) at a longitude and latitude, and whether that cell
    was measured or filled; ``elevation_m`` null outside the DSM or where it has none."""
    ws = job_workspace(settings.data_dir, job_id)
    elevation = tiler.sample(_stereo_file(db, settings, job_id, ws.dsm_path(), "DSM").identity, lon, lat, True)
    state = None
    if elevation is not None:
        mask = _stereo_file(db, settings, job_id, ws.dsm_mask_path(), "DSM")
        state = STATES.get(int(tiler.sample(mask.identity, lon, lat, True) or 0))
    return {"lon": lon, "lat": lat, "elevation_m": elevation, "state": state}


@router.post("/{job_id}/dsm/volume")
def dsm_volume(job_id: JobId, body: VolumeRequest, db: DbDep, settings: SettingsDep) -> dict[str, Any]:
    """The volume of the DSM above and below a base inside a polygon (lon/lat), m³ on the DSM's grid: a plane
    through the surface along the polygon's edge (``fit``, the default), its lowest point there, or an elevation;
    with the polygon's area, the share of its cells that have a value and were measured (not filled)."""
    ws = job_workspace(settings.data_dir, job_id)
    _stereo_file(db, settings, job_id, ws.dsm_path(), "DSM")  # 404 / 409 as the other DSM routes
    return volume_inside(ws.dsm_path(), ws.dsm_mask_path(), list(body.polygon), body.base)


@router.get("/{job_id}/disparity/point")
def disparity_point(
    job_id: JobId, x: PixelCoordinate, y: PixelCoordinate, db: DbDep, settings: SettingsDep, tiler: TilerDep
) -> dict[str, Any]:
    """The disparity (px) and its confidence at a pixel (x, y) of the rectified left view (pixel (col, row)
    spans [col, col + 1) x [row, row + 1)); ``disparity_px`` null outside the map or where it has none, and
    ``confidence`` 0 where the value was filled."""
    ws = job_workspace(settings.data_dir, job_id)
    value = tiler.sample(_stereo_file(db, settings, job_id, ws.disparity_path(), "disparity map").identity, x, y, False)
    confidence = None
    if value is not None:
        conf = _stereo_file(db, settings, job_id, ws.confidence_path(), "confidence map")
        confidence = tiler.sample(conf.identity, x, y, False)
    return {"x": x, "y": y, "disparity_px": value, "confidence": confidence}


def _signed_tiles(tilejson: dict[str, Any], db: Any, settings: Any, job_id: int) -> dict[str, Any]:
    """The TileJSON with its tile URLs signed: a map's image tags cannot send a token."""
    signature = job_signature(settings, job_id, job_service.get_job(db, job_id).created_at)
    return {**tilejson, "tiles": [f"{url}?{signature}" for url in tilejson["tiles"]]}


# The same tiles under the id of their OGC tile matrix set, as TiTiler and OGC API - Tiles name them
# (``/tiles/{job}/WebMercatorQuad/{z}/{x}/{y}``, with or without ``.png``), and the WMTS capabilities of the job's
# mosaic in that set, which QGIS reads to add it as a layer.


# the suffixed path first: routes match in the order they are added, and the decorator nearest the function adds
# its route first (a bare ``{y}`` would take "3.png" and refuse it)
@router.get("/{job_id}/{tms_id}/{z}/{x}/{y}", responses=PNG, name="tms_tile")
@router.get("/{job_id}/{tms_id}/{z}/{x}/{y}.png", responses=PNG, name="tms_tile_png")
def tms_tile(
    job_id: JobId,
    tms_id: TmsId,
    z: TileIndex,
    x: TileIndex,
    y: TileIndex,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
    if_none_match: IfNoneMatch = None,
) -> Response:
    """The tile of ``/tiles/{job}/{z}/{x}/{y}.png``, named by its tile matrix set (only WebMercatorQuad), with or
    without the suffix."""
    _check_tms(tms_id)
    return tile(job_id, z, x, y, db, settings, tiler, if_none_match)


@router.get("/{job_id}/{tms_id}/WMTSCapabilities.xml", name="wmts_capabilities", responses=WMTS_XML)
def wmts_capabilities(
    job_id: JobId, tms_id: TmsId, request: Request, viewer: Viewer, db: DbDep, settings: SettingsDep, tiler: TilerDep
) -> Response:
    """OGC WMTS 1.0.0 GetCapabilities (RESTful) of the job's mosaic, one layer ``job-{id}``: paste this URL
    into QGIS (Layer > Add WMS/WMTS Layer). Its tile template is signed (for ``FOTOSKHEMA_SIGNED_URL_SECONDS``);
    opened by a signed URL, it hands on that signature."""
    _check_tms(tms_id)
    cog = _mosaic_cog(db, settings, job_id)
    info = tiler.info(cog.identity)
    if not info.georeferenced:
        raise ConflictError(f"job {job_id}'s mosaic has no map coordinates (no GPS): it has no WMTS layer")
    job = job_service.get_job(db, job_id)
    signature = link_signature(request, viewer, settings, job_id, job.created_at)
    zero = str(request.url_for("tms_tile_png", job_id=job_id, tms_id=tms_id, z=0, x=0, y=0))
    template = zero.removesuffix("/0/0/0.png") + "/{TileMatrix}/{TileCol}/{TileRow}.png" + f"?{signature}"
    layer = WmtsLayer(
        f"job-{job_id}", _layer_title(db, job_id, job.flight_id), info.bounds, info.minzoom, info.maxzoom, template
    )
    body = capabilities("Fotoskhema", [layer], str(request.url))
    return Response(body, media_type="application/xml", headers={"Cache-Control": "private, no-cache"})


def _check_tms(tms_id: str) -> None:
    if tms_id not in SUPPORTED_TMS:
        raise NotFoundError(f"tile matrix set {tms_id[:64]!r} is not served; use one of {', '.join(SUPPORTED_TMS)}")


def _layer_title(db: Database, job_id: int, flight_id: int | None) -> str:
    name = job_service.flight_name(db, flight_id)
    return f"{name} (job {job_id})" if name else f"Mosaic of job {job_id}"


# The former paths of the two routes above (a load step was called a stage), kept for links and clients made
# before the rename and hidden from the schema; their TileJSON points at the load-steps tiles.


@router.get("/{job_id}/stages/{stage}/{z}/{x}/{y}.png", include_in_schema=False)
def stage_tile(
    job_id: JobId,
    stage: TileIndex,
    z: TileIndex,
    x: TileIndex,
    y: TileIndex,
    db: DbDep,
    settings: SettingsDep,
    tiler: TilerDep,
    if_none_match: IfNoneMatch = None,
) -> Response:
    return load_step_tile(job_id, stage, z, x, y, db, settings, tiler, if_none_match)


@router.get("/{job_id}/stages/{stage}/tilejson.json", include_in_schema=False)
def stage_tilejson(
    job_id: JobId, stage: TileIndex, request: Request, db: DbDep, settings: SettingsDep, tiler: TilerDep
) -> dict[str, Any]:
    return load_step_tilejson(job_id, stage, request, db, settings, tiler)


# -- Answers -------------------------------------------------------------------------------------


def _tile_response(
    tiler: Tiler, settings: Settings, cog: Cog, zxy: tuple[int, int, int], if_none_match: str | None, what: str
) -> Response:
    z, x, y = zxy
    etag = cog.identity.tile_etag(z, x, y)
    scope = "public" if settings.public_read else "private"
    # A job that has not succeeded may still rewrite its raster (a retry): the browser asks every time.
    freshness = f"max-age={settings.tile_max_age_seconds}" if cog.final else "no-cache"
    headers = {"ETag": etag, "Cache-Control": f"{scope}, {freshness}"}
    if if_none_match is not None and _etag_matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    try:
        png = tiler.tile(cog.identity, z, x, y)
    except TileNotFoundError as missing:
        where = "does not exist" if missing.off_grid else f"is outside {what}"
        raise NotFoundError(f"tile {z}/{x}/{y} {where}") from None
    return Response(png, media_type="image/png", headers=headers)


def _etag_matches(if_none_match: str, etag: str) -> bool:
    """RFC 9110's weak comparison, as ``If-None-Match`` asks: any listed tag, ``W/`` or not. (``*`` is not
    honoured: whether the tile exists is known only once it is read, so it is answered in full.)"""
    return etag in (t.strip().removeprefix("W/") for t in if_none_match.split(","))


def _tilejson(tiler: Tiler, cog: Cog, tile_zero: Any, name: str) -> dict[str, Any]:
    """TileJSON of the COG; ``tile_zero`` is the URL of its tile 0/0/0."""
    template = str(tile_zero).removesuffix("/0/0/0.png") + "/{z}/{x}/{y}.png"
    info = tiler.info(cog.identity)
    west, south, east, north = info.bounds
    return {
        "tilejson": "2.2.0",
        "name": name,
        "scheme": "xyz",
        "tiles": [template],
        "bounds": [west, south, east, north],
        "minzoom": info.minzoom,
        "maxzoom": info.maxzoom,
        "center": [(west + east) / 2, (south + north) / 2, max(info.minzoom, info.maxzoom - 2)],
        "georeferenced": info.georeferenced,
        "tile_size": TILE_SIZE,
    }
