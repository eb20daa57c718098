"""OGC WMTS 1.0.0 GetCapabilities of one raster, RESTful, in the WebMercatorQuad tile matrix set: what QGIS,
ArcGIS and OpenLayers read to add a job's mosaic as a layer.

The tile matrices (scale denominators, origins, sizes) come from ``morecantile``'s definition of the OGC
WebMercatorQuad set, as TiTiler's WMTS endpoint does; each layer's ``TileMatrixSetLimits`` bound the tiles to
the raster's extent, so a client never asks for tiles the route would answer 404. Every text (a flight's name
in a title) is escaped by ElementTree.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import morecantile

TMS_ID = "WebMercatorQuad"  # the tile matrix sets the tile routes serve, by their OGC id
SUPPORTED_TMS = (TMS_ID,)

NS = {
    "": "http://www.opengis.net/wmts/1.0",
    "ows": "http://www.opengis.net/ows/1.1",
    "xlink": "http://www.w3.org/1999/xlink",
}
for _prefix, _uri in NS.items():
    ET.register_namespace(_prefix, _uri)


@dataclass(frozen=True)
class WmtsLayer:
    identifier: str  # e.g. "job-12"
    title: str  # shown by the client; may hold user text (escaped)
    bounds: tuple[float, float, float, float]  # west, south, east, north, degrees
    minzoom: int
    maxzoom: int
    template: str  # ResourceURL with {TileMatrix}, {TileCol}, {TileRow}; may carry a query string


def _q(prefix: str, tag: str) -> str:
    return f"{{{NS[prefix]}}}{tag}"


def _sub(parent: ET.Element, prefix: str, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    node = ET.SubElement(parent, _q(prefix, tag), {(_q(*k.split(":")) if ":" in k else k): v for k, v in attrs.items()})
    if text is not None:
        node.text = text
    return node


def capabilities(service_title: str, layers: list[WmtsLayer], service_url: str) -> bytes:
    """The GetCapabilities document (UTF-8 XML) of ``layers``; ``service_url`` is where it was read from."""
    tms = morecantile.tms.get(TMS_ID)
    root = ET.Element(_q("", "Capabilities"), {"version": "1.0.0"})
    ident = _sub(root, "ows", "ServiceIdentification")
    _sub(ident, "ows", "Title", service_title)
    _sub(ident, "ows", "ServiceType", "OGC WMTS")
    _sub(ident, "ows", "ServiceTypeVersion", "1.0.0")
    meta = _sub(root, "ows", "OperationsMetadata")
    operation = _sub(meta, "ows", "Operation", name="GetCapabilities")
    get = _sub(_sub(_sub(operation, "ows", "DCP"), "ows", "HTTP"), "ows", "Get", **{"xlink:href": service_url})
    _sub(_sub(get, "ows", "Constraint", name="GetEncoding"), "ows", "AllowedValues").append(_value("RESTful"))
    contents = _sub(root, "", "Contents")
    for layer in layers:
        _layer(contents, layer, tms)
    _matrix_set(contents, tms, max((layer.maxzoom for layer in layers), default=0))
    ET.SubElement(root, _q("", "ServiceMetadataURL"), {_q("xlink", "href"): service_url})
    return bytes(ET.tostring(root, encoding="utf-8", xml_declaration=True))


def _value(text: str) -> ET.Element:
    node = ET.Element(_q("ows", "Value"))
    node.text = text
    return node


def _layer(contents: ET.Element, layer: WmtsLayer, tms: morecantile.TileMatrixSet) -> None:
    node = _sub(contents, "", "Layer")
    _sub(node, "ows", "Title", layer.title)  # the schema's order: title, box, identifier
    west, south, east, north = layer.bounds
    box = _sub(node, "ows", "WGS84BoundingBox", crs="urn:ogc:def:crs:OGC:2:84")
    _sub(box, "ows", "LowerCorner", f"{west!r} {south!r}")
    _sub(box, "ows", "UpperCorner", f"{east!r} {north!r}")
    _sub(node, "ows", "Identifier", layer.identifier)
    _sub(_sub(node, "", "Style", isDefault="true"), "ows", "Identifier", "default")
    _sub(node, "", "Format", "image/png")
    link = _sub(node, "", "TileMatrixSetLink")
    _sub(link, "", "TileMatrixSet", TMS_ID)
    limits = _sub(link, "", "TileMatrixSetLimits")
    for z in range(layer.minzoom, layer.maxzoom + 1):
        upper_left, lower_right = tms.tile(west, north, z), tms.tile(east, south, z)
        row = _sub(limits, "", "TileMatrixLimits")
        _sub(row, "", "TileMatrix", str(z))
        _sub(row, "", "MinTileRow", str(upper_left.y))
        _sub(row, "", "MaxTileRow", str(lower_right.y))
        _sub(row, "", "MinTileCol", str(upper_left.x))
        _sub(row, "", "MaxTileCol", str(lower_right.x))
    _sub(node, "", "ResourceURL", format="image/png", resourceType="tile", template=layer.template)


def _matrix_set(contents: ET.Element, tms: morecantile.TileMatrixSet, maxzoom: int) -> None:
    node = _sub(contents, "", "TileMatrixSet")
    _sub(node, "ows", "Identifier", TMS_ID)
    _sub(node, "ows", "SupportedCRS", "urn:ogc:def:crs:EPSG::3857")
    _sub(node, "", "WellKnownScaleSet", "urn:ogc:def:wkss:OGC:1.0:GoogleMapsCompatible")
    for z in range(0, maxzoom + 1):
        matrix = tms.matrix(z)
        row = _sub(node, "", "TileMatrix")
        _sub(row, "ows", "Identifier", str(z))
        _sub(row, "", "ScaleDenominator", repr(matrix.scaleDenominator))
        x0, y0 = matrix.pointOfOrigin
        _sub(row, "", "TopLeftCorner", f"{x0!r} {y0!r}")
        _sub(row, "", "TileWidth", str(matrix.tileWidth))
        _sub(row, "", "TileHeight", str(matrix.tileHeight))
        _sub(row, "", "MatrixWidth", str(matrix.matrixWidth))
        _sub(row, "", "MatrixHeight", str(matrix.matrixHeight))
