"""Formats other tools read: the provenance tags of a mosaic COG; a finished job as a STAC item (validated by
pystac), its tiles under the WebMercatorQuad tile matrix set id, its WMTS capabilities (parsed by OWSLib, as
QGIS reads them) and all its outputs as one streamed ZIP. Each of them for its owner or a signed URL only.

The job's files come from the real pipeline run in-process over a small synthetic flight with GPS (UTM 15N),
copied into a job made through the API.
"""

from __future__ import annotations

import io
import re
import zipfile
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pystac
import pytest
import rasterio
from fastapi.testclient import TestClient
from owslib.wmts import WebMapTileService
from pystac.extensions.projection import ProjectionExtension
from pystac.validation.stac_validator import GetSchemaError
from rasterio.windows import Window

from core.db import Database, Job
from core.kinds import JobStatus
from tests.api.conftest import finished_job
from tests.api.test_jobs import flight_with
from tests.conftest import user_headers
from workers.raster_io import open_block_writer, translate_to_cog
from workers.workspace import job_workspace


def test_cog_tags_set_on_the_scratch_survive_the_cog_driver(tmp_path: Path) -> None:
    scratch, cog = tmp_path / "scratch.tif", tmp_path / "mosaic.tif"
    with open_block_writer(scratch, 1200, 700, 32630, [0.03, 0, 699_000, 0, -0.03, 5_630_000], compress=None) as w:
        w(Window(0, 0, 1200, 700), np.full((700, 1200, 3), 90, np.uint8), np.ones((700, 1200), bool))
    translate_to_cog(scratch, cog, "deflate", tags={"TIFFTAG_IMAGEDESCRIPTION": "Fotoskhema mosaic job, mode planar"})
    with rasterio.open(cog) as src:
        tags = src.tags()
        assert src.overviews(1) == [2, 4] and src.crs.to_epsg() == 32630
    assert tags["TIFFTAG_IMAGEDESCRIPTION"] == "Fotoskhema mosaic job, mode planar"
    assert re.fullmatch(r"Fotoskhema \d+\.\d+\.\d+\S*", tags["TIFFTAG_SOFTWARE"])
    assert re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", tags["TIFFTAG_DATETIME"])
    assert not list(tmp_path.glob("*.aux.xml"))  # real TIFF tags, not a sidecar file


def test_without_tags_the_cog_has_none_of_ours(tmp_path: Path) -> None:
    scratch, cog = tmp_path / "scratch.tif", tmp_path / "mosaic.tif"
    with open_block_writer(scratch, 300, 200, None, None, compress=None) as w:
        w(Window(0, 0, 300, 200), np.zeros((200, 300, 3), np.uint8), np.ones((200, 300), bool))
    translate_to_cog(scratch, cog, "lzw")
    with rasterio.open(cog) as src:
        assert "TIFFTAG_SOFTWARE" not in src.tags()


# -- A finished job --------------------------------------------------------------------------------------------


def set_status(api_settings, job_id: int, status: JobStatus) -> None:
    with Database(api_settings.resolved_database_url()).session() as s:
        s.get(Job, job_id).status = status


def local(url: str) -> str:
    """The path and query of a URL the API answered (TestClient's host is testserver)."""
    parts = urlsplit(url)
    return f"{parts.path}?{parts.query}" if parts.query else parts.path


def anonymous(client: TestClient) -> dict[str, str]:
    return {"Authorization": ""}


@pytest.fixture
def job_id(client: TestClient, api_settings, processed: dict) -> int:
    return finished_job(client, api_settings, processed)


# -- STAC ------------------------------------------------------------------------------------------------------


def test_the_stac_item_is_valid_stac_with_the_mosaic_grid(client: TestClient, api_settings, job_id: int) -> None:
    response = client.get(f"/api/jobs/{job_id}/stac.json")
    assert response.status_code == 200 and response.headers["content-type"] == "application/geo+json"
    data = response.json()
    pystac.validation.validate_dict(data, extensions=[])  # the core item schema (bundled with pystac)
    item = pystac.Item.from_dict(data)
    ws = job_workspace(api_settings.data_dir, job_id)
    with rasterio.open(ws.mosaic_path()) as src:
        proj = ProjectionExtension.ext(item)
        assert proj.code == f"EPSG:{src.crs.to_epsg()}" == "EPSG:32615"
        assert proj.shape == [src.height, src.width]
        assert proj.bbox == pytest.approx(list(src.bounds))
        assert proj.transform == pytest.approx(list(src.transform)[:6])
    report = ws.load_report()
    west, south, east, north = item.bbox
    for frame in report["frames_used"]:  # every photo's GPS position is within the item's box
        assert west < frame["gps"]["lon"] < east and south < frame["gps"]["lat"] < north
    assert item.properties["gsd"] == pytest.approx(report["gsd_m"])
    assert item.datetime is not None and item.common_metadata.created is not None
    assert {"visual", "report-json", "footprints"} <= set(item.assets) and "dsm" not in item.assets
    visual = item.assets["visual"]
    assert visual.media_type == pystac.MediaType.COG and "visual" in (visual.roles or [])
    mosaic = client.get(local(visual.href), headers=anonymous(client))  # signed: opens without the token
    assert mosaic.status_code == 200 and mosaic.content == ws.mosaic_path().read_bytes()
    assert {link.rel for link in item.links} >= {"self", "alternate", "xyz", "wmts"}


def test_the_stac_item_passes_the_projection_extension_schema(client: TestClient, job_id: int) -> None:
    data = client.get(f"/api/jobs/{job_id}/stac.json").json()
    try:
        pystac.validation.validate_dict(data)  # core and every extension the item names
    except GetSchemaError as exc:
        pytest.skip(f"the projection extension's JSON schema cannot be fetched here (offline): {exc}")


def test_a_dsm_is_an_asset_with_its_own_grid(client: TestClient, api_settings, job_id: int, tmp_path: Path) -> None:
    dsm = job_workspace(api_settings.data_dir, job_id).dsm_path()
    with open_block_writer(tmp_path / "s.tif", 64, 48, 32615, [0.5, 0, 271_000, 0, -0.5, 3_294_000]) as w:
        w(Window(0, 0, 64, 48), np.full((48, 64, 3), 7, np.uint8), np.ones((48, 64), bool))
    translate_to_cog(tmp_path / "s.tif", dsm, "deflate")
    item = pystac.Item.from_dict(client.get(f"/api/jobs/{job_id}/stac.json").json())
    asset = item.assets["dsm"]
    assert asset.media_type == pystac.MediaType.COG and asset.extra_fields["proj:shape"] == [48, 64]
    assert "dsm.tif" in {o["name"] for o in client.get(f"/api/jobs/{job_id}/outputs").json()["outputs"]}


def test_a_mosaic_jobs_dsm_answers_the_dsm_routes(client: TestClient, api_settings, job_id: int) -> None:
    """An ortho job's DSM (what ``orthorectify_frames`` writes, through the same ``write_dsm``) is served by the
    stereo DEM's DSM routes: its tiles, the elevation under a point, a volume; a mosaic without one is 404, saying
    which jobs have one."""
    from pyproj import Transformer

    from workers.raster_io import write_dsm

    missing = client.get(f"/tiles/{job_id}/dsm/tilejson.json")
    assert missing.status_code == 404 and "only an ortho job" in missing.json()["detail"]
    assert client.get(f"/tiles/{job_id}/disparity/tilejson.json").status_code == 404  # a stereo DEM's alone
    ws = job_workspace(api_settings.data_dir, job_id)
    height = np.full((40, 60), 12.5, np.float32)
    height[:, :10] = np.nan  # 5 m along the west edge without a value
    state = np.where(np.isfinite(height), 1, 0).astype(np.uint8)
    paths = (ws.dsm_path(), ws.dsm_mask_path(), ws.dsm_view_path(), ws.view_scratch_path("dsm"))
    relief = np.full((40, 60, 3), 90, np.uint8)
    place = {"transform": (0.5, 0.0, 271_000.0, 0.0, -0.5, 3_294_000.0), "epsg": 32615}
    write_dsm(paths, height, state, relief, **place, compression="deflate", description="a test DSM")
    assert client.get(f"/tiles/{job_id}/dsm/tilejson.json").json()["georeferenced"] is True
    to_lonlat = Transformer.from_crs(32615, 4326, always_xy=True)
    lon, lat = to_lonlat.transform(271_015.0, 3_293_990.0)
    point = client.get(f"/tiles/{job_id}/dsm/point", params={"lon": lon, "lat": lat}).json()
    assert point["elevation_m"] == pytest.approx(12.5) and point["state"] == "measured"
    square = [to_lonlat.transform(x, y) for x, y in ((271_010, 3_293_990), (271_020, 3_293_990), (271_020, 3_293_985))]
    square.append(to_lonlat.transform(271_010, 3_293_985))
    volume = client.post(f"/tiles/{job_id}/dsm/volume", json={"polygon": square, "base": 10.0}).json()
    assert volume["volume_above_m3"] == pytest.approx(50 * 2.5, rel=0.05) and volume["crs"] == "EPSG:32615"


def test_stac_needs_a_finished_mosaic_and_its_owner(client: TestClient, api_settings, job_id: int) -> None:
    bob = user_headers(client, "bob")
    assert client.get(f"/api/jobs/{job_id}/stac.json", headers=bob).status_code == 404
    assert client.get(f"/api/jobs/{job_id}/stac.json", headers=anonymous(client)).status_code == 401
    set_status(api_settings, job_id, JobStatus.running)
    refused = client.get(f"/api/jobs/{job_id}/stac.json")
    assert refused.status_code == 409 and "no finished mosaic" in refused.json()["detail"]


def test_a_signed_stac_item_hands_on_its_own_signature(client: TestClient, job_id: int) -> None:
    signature = client.get(f"/api/jobs/{job_id}").json()["signature"]
    item = client.get(f"/api/jobs/{job_id}/stac.json?{signature}", headers=anonymous(client))
    assert item.status_code == 200
    hrefs = [a["href"] for a in item.json()["assets"].values()]
    assert hrefs and all(urlsplit(h).query == signature for h in hrefs)
    forged = signature.replace("sig=", "sig=0")
    assert client.get(f"/api/jobs/{job_id}/stac.json?{forged}", headers=anonymous(client)).status_code == 401


# -- Tiles by tile matrix set, WMTS ------------------------------------------------------------------------


def some_tile(client: TestClient, job_id: int) -> tuple[int, int, int]:
    """A tile of the mosaic at its finest zoom (the centre of its TileJSON bounds)."""
    import morecantile

    tilejson = client.get(f"/tiles/{job_id}/tilejson.json").json()
    west, south, east, north = tilejson["bounds"]
    t = morecantile.tms.get("WebMercatorQuad").tile((west + east) / 2, (south + north) / 2, tilejson["maxzoom"])
    return t.z, t.x, t.y


def test_tiles_under_their_tile_matrix_set_id_are_the_same_tiles(client: TestClient, job_id: int) -> None:
    z, x, y = some_tile(client, job_id)
    old = client.get(f"/tiles/{job_id}/{z}/{x}/{y}.png")
    assert old.status_code == 200
    for path in (f"/tiles/{job_id}/WebMercatorQuad/{z}/{x}/{y}", f"/tiles/{job_id}/WebMercatorQuad/{z}/{x}/{y}.png"):
        new = client.get(path)
        assert new.status_code == 200 and new.headers["content-type"] == "image/png"
        assert new.content == old.content and new.headers["etag"] == old.headers["etag"]
    other = client.get(f"/tiles/{job_id}/WorldCRS84Quad/{z}/{x}/{y}")
    assert other.status_code == 404 and "WebMercatorQuad" in other.json()["detail"]
    assert (
        client.get(f"/tiles/{job_id}/WebMercatorQuad/{z}/{x}/{y}", headers=user_headers(client, "eve")).status_code
        == 404
    )
    assert client.get(f"/tiles/{job_id}/WebMercatorQuad/{z}/{x}/{y}", headers=anonymous(client)).status_code == 401
    signature = client.get(f"/api/jobs/{job_id}").json()["signature"]
    signed = client.get(f"/tiles/{job_id}/WebMercatorQuad/{z}/{x}/{y}?{signature}", headers=anonymous(client))
    assert signed.status_code == 200 and signed.content == old.content


def test_wmts_capabilities_parse_as_qgis_reads_them(client: TestClient, job_id: int) -> None:
    response = client.get(f"/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml")
    assert response.status_code == 200 and response.headers["content-type"].startswith("application/xml")
    url = f"http://testserver/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml"
    wmts = WebMapTileService(url, xml=response.content)  # OWSLib: QGIS's own reader is GDAL/OWS-compatible
    assert wmts.identification.type == "OGC WMTS" and list(wmts.contents) == [f"job-{job_id}"]
    layer = wmts.contents[f"job-{job_id}"]
    tilejson = client.get(f"/tiles/{job_id}/tilejson.json").json()
    assert layer.boundingBoxWGS84 == pytest.approx(tuple(tilejson["bounds"]))
    matrices = wmts.tilematrixsets["WebMercatorQuad"].tilematrix
    assert len(matrices) == tilejson["maxzoom"] + 1
    assert matrices["0"].matrixwidth == 1 and matrices["0"].scaledenominator == pytest.approx(559082264.0287178)
    limits = layer.tilematrixsetlinks["WebMercatorQuad"].tilematrixlimits
    assert sorted(map(int, limits)) == list(range(tilejson["minzoom"], tilejson["maxzoom"] + 1))
    z, x, y = some_tile(client, job_id)
    limit = limits[str(z)]
    assert limit.mintilecol <= x <= limit.maxtilecol and limit.mintilerow <= y <= limit.maxtilerow
    [resource] = [r for r in layer.resourceURLs if r["resourceType"] == "tile"]
    tile_url = resource["template"].replace("{TileMatrix}", str(z)).replace("{TileCol}", str(x))
    tile_url = tile_url.replace("{TileRow}", str(y))
    tile = client.get(local(tile_url), headers=anonymous(client))  # QGIS sends no token: the template is signed
    assert tile.status_code == 200 and tile.content == client.get(f"/tiles/{job_id}/{z}/{x}/{y}.png").content


def test_wmts_is_the_owners_and_its_title_is_escaped(client: TestClient, job_id: int) -> None:
    flight_id = client.get(f"/api/jobs/{job_id}").json()["flight_id"]
    from sqlalchemy import update

    from core.db import Flight

    with client.app.state.db.session() as s:
        s.execute(update(Flight).where(Flight.id == flight_id).values(name='<b>&"park"</b>'))
    xml = client.get(f"/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml").content
    assert b"<b>" not in xml and b"&lt;b&gt;&amp;" in xml
    wmts = WebMapTileService("http://testserver/wmts", xml=xml)
    assert wmts.contents[f"job-{job_id}"].title == f'<b>&"park"</b> (job {job_id})'
    bob = user_headers(client, "bob")
    assert client.get(f"/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml", headers=bob).status_code == 404
    signature = client.get(f"/api/jobs/{job_id}").json()["signature"]
    signed = client.get(f"/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml?{signature}", headers=anonymous(client))
    assert signed.status_code == 200 and signature.replace("&", "&amp;").encode() in signed.content


def test_a_mosaic_without_map_coordinates_has_no_wmts(client: TestClient, api_settings, job_id: int) -> None:
    path = job_workspace(api_settings.data_dir, job_id).mosaic_path()
    scratch = path.with_name("plain.tmp.tif")
    with open_block_writer(scratch, 300, 200, None, None, compress=None) as w:
        w(Window(0, 0, 300, 200), np.zeros((200, 300, 3), np.uint8), np.ones((200, 300), bool))
    translate_to_cog(scratch, path, "lzw")
    scratch.unlink()
    refused = client.get(f"/tiles/{job_id}/WebMercatorQuad/WMTSCapabilities.xml")
    assert refused.status_code == 409 and "no map coordinates" in refused.json()["detail"]
    item = client.get(f"/api/jobs/{job_id}/stac.json").json()
    assert item["geometry"] is None and "bbox" not in item and item["properties"]["proj:code"] is None


# -- all.zip -----------------------------------------------------------------------------------------------


def test_all_zip_holds_every_output_by_name(client: TestClient, api_settings, job_id: int) -> None:
    listing = client.get(f"/api/jobs/{job_id}/outputs").json()
    names = {o["name"] for o in listing["outputs"]}
    assert {"mosaic.tif", "report.json", "footprints.geojson"} <= names
    response = client.get(local(listing["all_zip_url"]), headers=anonymous(client))  # signed link, no token
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    assert "content-length" not in response.headers  # streamed as it is written
    assert f"job{job_id}_all.zip" in response.headers["content-disposition"]
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    assert archive.testzip() is None and set(archive.namelist()) == names
    outputs = job_workspace(api_settings.data_dir, job_id).outputs()
    for name in names:
        assert archive.read(name) == outputs[name].read_bytes()
    assert archive.getinfo("mosaic.tif").compress_type == zipfile.ZIP_STORED  # a COG is compressed already
    assert archive.getinfo("report.json").compress_type == zipfile.ZIP_DEFLATED


def test_all_zip_is_the_owners_and_needs_outputs(client: TestClient, job_id: int, processed: dict) -> None:
    assert client.get(f"/api/jobs/{job_id}/outputs/all.zip", headers=user_headers(client, "bob")).status_code == 404
    assert client.get(f"/api/jobs/{job_id}/outputs/all.zip", headers=anonymous(client)).status_code == 401
    empty = client.post("/api/jobs", json={"flight_id": flight_with(client, processed["frames"])}).json()
    refused = client.get(f"/api/jobs/{empty['id']}/outputs/all.zip")
    assert refused.status_code == 409 and "no outputs" in refused.json()["detail"]
    assert client.get(f"/api/jobs/{empty['id']}/outputs").json()["all_zip_url"] is None


def test_zip_stream_never_holds_more_than_a_chunk(tmp_path: Path) -> None:
    from api.zipstream import CHUNK, zip_chunks

    big = tmp_path / "big.tif"
    big.write_bytes(np.random.default_rng(0).integers(0, 255, 5 * CHUNK, dtype=np.uint8).tobytes())
    chunks = list(zip_chunks([("big.tif", big), ("note.txt", b"hello"), ("gone.json", tmp_path / "missing")]))
    assert len(chunks) >= 5 and max(map(len, chunks)) <= CHUNK + 1024
    archive = zipfile.ZipFile(io.BytesIO(b"".join(chunks)))
    assert archive.namelist() == ["big.tif", "note.txt"] and archive.read("big.tif") == big.read_bytes()
