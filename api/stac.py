"""A finished job as a STAC 1.1 item: its mosaic (and DSM when there is one), report and footprints as assets,
its map grid in the projection extension (``proj:code``, ``proj:bbox``, ``proj:shape``, ``proj:transform``).

Geometry is the mosaic's outline in lon/lat from ``report.json`` (the pixels that hold photos, not the COG's
box); ``datetime`` is the first photo's capture time as its camera wrote it (EXIF has no time zone: read as
UTC), else the job's creation time. Asset hrefs are the job's signed download URLs, so a STAC client that
cannot send a token still opens them until they expire.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import rasterio
from rasterio.warp import transform_bounds

from api.models import JobOut

STAC_VERSION = "1.1.0"
PROJECTION = "https://stac-extensions.github.io/projection/v2.0.0/schema.json"
COG = "image/tiff; application=geotiff; profile=cloud-optimized"
# output name -> asset key, title, media type, roles
ASSETS = {
    "mosaic.tif": ("visual", "Mosaic (orthophoto)", COG, ["visual", "data"]),
    "dsm.tif": ("dsm", "Digital surface model", COG, ["data"]),
    "report.html": ("report", "Quality report", "text/html", ["metadata"]),
    "report.json": ("report-json", "Quality report (JSON)", "application/json", ["metadata"]),
    "footprints.geojson": ("footprints", "Photo footprints", "application/geo+json", ["metadata"]),
    "cutlines.geojson": ("cutlines", "Seam lines", "application/geo+json", ["metadata"]),
    "frame_index.tif": ("frame-index", "Frame of each pixel (index + 1, 0: none)", COG, ["data"]),
}


def stac_item(
    job: JobOut,
    outputs: dict[str, Path],
    report: dict[str, Any],
    capture_times: list[str],
    links: dict[str, str],
    flight_name: str | None,
) -> dict[str, Any]:
    """The item of ``job``: ``outputs`` its files by name, ``links`` its URLs (``self``, ``viewer``, ``xyz``,
    ``wmts`` and every output name, signed)."""
    grid = _grid(outputs["mosaic.tif"])
    used = len(report.get("frames_used", []))
    geometry = _footprint(report, grid)
    properties: dict[str, Any] = {
        "title": f"{flight_name} (job {job.id})" if flight_name else f"Mosaic of job {job.id}",
        "description": f"Fotoskhema {report.get('mode', 'planar')} mosaic of {used} photos",
        "datetime": _capture_time(capture_times) or _iso(job.created_at),
        "created": _iso(job.created_at),
        "updated": _iso(job.updated_at),
        **grid["proj"],
    }
    if isinstance(report.get("gsd_m"), int | float):
        properties["gsd"] = float(report["gsd_m"])
    for key in ("tie_point_rms_px", "gps_residual_rms_m"):
        if isinstance(report.get(key), int | float):
            properties[f"fotoskhema:{key}"] = report[key]
    item: dict[str, Any] = {
        "type": "Feature",
        "stac_version": STAC_VERSION,
        "stac_extensions": [PROJECTION],
        "id": f"fotoskhema-job-{job.id}",
        "geometry": geometry,
        "properties": properties,
        "links": _links(links),
        "assets": _assets(outputs, links),
    }
    if geometry is not None:
        item["bbox"] = _bbox(geometry)
    return item


def _grid(cog: Path) -> dict[str, Any]:
    """The COG's projection fields and, for a georeferenced one, its box in lon/lat."""
    with rasterio.open(cog) as src:
        epsg = src.crs.to_epsg() if src.crs is not None else None
        proj: dict[str, Any] = {"proj:code": f"EPSG:{epsg}" if epsg else None, "proj:shape": [src.height, src.width]}
        lonlat = None
        if epsg:
            proj["proj:bbox"] = list(src.bounds)
            proj["proj:transform"] = list(src.transform)[:6]
            lonlat = transform_bounds(src.crs, "EPSG:4326", *src.bounds)
    return {"proj": proj, "lonlat": lonlat}


def _footprint(report: dict[str, Any], grid: dict[str, Any]) -> dict[str, Any] | None:
    """The outline the report gives in lon/lat; else the COG's box; None for a mosaic without map coordinates."""
    if grid["lonlat"] is None:
        return None
    outline = (report.get("mosaic") or {}).get("footprint") or {}
    if outline.get("type") == "MultiPolygon" and outline.get("units") == "lon/lat degrees":
        return {"type": "MultiPolygon", "coordinates": outline["coordinates"]}
    west, south, east, north = grid["lonlat"]
    ring = [[west, south], [east, south], [east, north], [west, north], [west, south]]
    return {"type": "Polygon", "coordinates": [ring]}


def _bbox(geometry: dict[str, Any]) -> list[float]:
    rings = (
        geometry["coordinates"] if geometry["type"] == "Polygon" else [r for p in geometry["coordinates"] for r in p]
    )
    xs = [pt[0] for ring in rings for pt in ring]
    ys = [pt[1] for ring in rings for pt in ring]
    return [min(xs), min(ys), max(xs), max(ys)]


def _capture_time(times: list[str]) -> str | None:
    """The earliest EXIF ``DateTimeOriginal`` (``2024:05:01 10:22:13``) as RFC 3339, read as UTC."""
    parsed = []
    for text in times:
        try:
            parsed.append(datetime.strptime(text, "%Y:%m:%d %H:%M:%S").replace(tzinfo=UTC))
        except (TypeError, ValueError):
            continue
    return _iso(min(parsed)) if parsed else None


def _iso(when: datetime) -> str:
    return when.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _links(links: dict[str, str]) -> list[dict[str, Any]]:
    out = [
        {"rel": "self", "href": links["self"], "type": "application/geo+json"},
        {"rel": "alternate", "href": links["viewer"], "type": "text/html", "title": "The job in Fotoskhema's viewer"},
    ]
    if "xyz" in links:
        out.append({"rel": "xyz", "href": links["xyz"], "type": "image/png", "title": "XYZ tiles (WebMercatorQuad)"})
    if "wmts" in links:
        out.append({"rel": "wmts", "href": links["wmts"], "type": "application/xml", "title": "WMTS capabilities"})
    return out


def _assets(outputs: dict[str, Path], links: dict[str, str]) -> dict[str, Any]:
    assets = {}
    for name, (key, title, media, roles) in ASSETS.items():
        if name not in outputs:
            continue
        asset: dict[str, Any] = {"href": links[name], "type": media, "title": title, "roles": roles}
        if name == "dsm.tif":  # its grid may differ from the mosaic's (the item's): the asset says its own
            asset.update(_grid(outputs[name])["proj"])
        assets[key] = asset
    return assets
