"""Ground control points: ODM's ``gcp_list.txt`` and OpenSfM's ``ground_control_points.json`` read
into one structure, positions in the job's local frame, observations in OpenCV pixel coordinates.

Local frame: ``(UTM easting - easting0, UTM northing - northing0, height)`` in metres, one UTM zone
for the whole job (``georef.utm_epsg``). Heights are passed through as the file states them (no
geoid or ellipsoid conversion): EXIF GPS altitudes and GCP heights must share a vertical datum.

Pixel convention (OpenCV's): ``(0, 0)`` is the centre of the first pixel. ODM's ``gcp_list.txt``
pixels are read as they are (OpenSfM's ``read_gcp_list`` reads them the same way); OpenSfM's
normalised projections are ``((x + 0.5 - w / 2) / max(w, h), (y + 0.5 - h / 2) / max(w, h))``
(``opensfm.features.normalized_image_coordinates``) and are mapped back with the image's size.

NumPy and pyproj only: the API parses an uploaded GCP file with these functions before storing it.
How GCPs and GPS fixes then place a reconstruction is in ``datum.py``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from workers.algorithms.geometry import lonlat_to_utm

if TYPE_CHECKING:  # pyproj (~20 MiB) is imported by the functions that convert: the workspace imports this module
    from pyproj import CRS

_ODM_UTM = re.compile(r"^WGS84\s+UTM\s+(\d{1,2})\s*([NS])$", re.IGNORECASE)


@dataclass(frozen=True)
class LocalFrame:
    """The job's local Cartesian frame: UTM zone ``epsg`` shifted by ``(easting0, northing0)``."""

    epsg: int
    easting0: float
    northing0: float

    def from_lonlat(self, lonlatalt: np.ndarray) -> np.ndarray:
        """(N, 3) longitude, latitude (WGS84 degrees), height m -> (N, 3) local metres."""
        lla = np.asarray(lonlatalt, dtype=np.float64).reshape(-1, 3)
        en = lonlat_to_utm(lla[:, :2], self.epsg)
        return np.column_stack([en[:, 0] - self.easting0, en[:, 1] - self.northing0, lla[:, 2]])

    def from_crs(self, xyz: np.ndarray, crs: CRS) -> np.ndarray:
        """(N, 3) coordinates in ``crs`` (x = easting or longitude) -> (N, 3) local metres."""
        from pyproj import CRS, Transformer

        pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        tr = Transformer.from_crs(crs, CRS.from_epsg(self.epsg), always_xy=True)
        e, n = tr.transform(pts[:, 0], pts[:, 1])
        return np.column_stack([np.asarray(e) - self.easting0, np.asarray(n) - self.northing0, pts[:, 2]])


@dataclass(frozen=True)
class GroundControlPoint:
    """One ground control point.

    Attributes
    ----------
    id : the file's name for it (ODM: the 7th column, else its coordinates as written).
    position : (3,) float64 local metres, or None when the file gives no position (a tie point).
    observations : image name -> (2,) float64 pixel (x, y), OpenCV convention.
    """

    id: str
    position: np.ndarray | None
    observations: dict[str, np.ndarray] = field(default_factory=dict)


def parse_crs(text: str) -> CRS:
    """A CRS from ODM's first line: a PROJ string, ``EPSG:nnnn`` or ``WGS84 UTM <zone><N|S>``."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    text = text.strip()
    found = _ODM_UTM.match(text)
    if found:
        zone = int(found.group(1))
        if not 1 <= zone <= 60:
            raise ValueError(f"UTM zone {zone} is outside 1..60")
        return CRS.from_epsg((32600 if found.group(2).upper() == "N" else 32700) + zone)
    try:
        return CRS.from_user_input(text)
    except CRSError:
        # PROJ's own message ("Internal Proj Error: proj_create: ...") says nothing a user can act on.
        raise ValueError(
            f"unknown coordinate system {text!r}: expected EPSG:nnnn, a +proj=... string, WGS84 or WGS84 UTM 32N"
        ) from None


def parse_gcp_list(text: str, frame: LocalFrame) -> list[GroundControlPoint]:
    """Read ODM's ``gcp_list.txt``.

    Format: the first non-empty line names the CRS (see ``parse_crs``); every further line is
    ``geo_x geo_y geo_z im_x im_y image_name [gcp_name [extras...]]``, blank lines and ``#`` comments
    skipped. Lines with the same ``gcp_name`` (or, without names, the same coordinates) are one GCP.

    Returns
    -------
    GCPs in order of first appearance. Raises ValueError naming the line (1-based) of bad input.
    """
    lines = [(n, raw.split("#", 1)[0].strip()) for n, raw in enumerate(text.splitlines(), start=1)]
    lines = [(n, line) for n, line in lines if line]
    if not lines:
        raise ValueError("gcp_list.txt is empty: expected a coordinate system on line 1")
    try:
        crs = parse_crs(lines[0][1])
    except ValueError as exc:
        raise ValueError(f"line {lines[0][0]}: {exc}") from None
    names: dict[str, tuple[int, tuple[float, float, float]]] = {}
    points: dict[str, dict[str, np.ndarray]] = {}
    for number, line in lines[1:]:
        gcp_id, xyz, image, pixel = _gcp_line(number, line)
        if crs.is_geographic:
            _check_lonlat(f"line {number}", xyz[0], xyz[1])
        first = names.setdefault(gcp_id, (number, xyz))
        if not np.allclose(first[1], xyz, rtol=0.0, atol=1e-6):
            raise ValueError(f"line {number}: GCP {gcp_id!r} has other coordinates on line {first[0]}")
        seen = points.setdefault(gcp_id, {})
        if image in seen:
            raise ValueError(f"line {number}: GCP {gcp_id!r} is observed twice in {image}")
        seen[image] = pixel
    ids = list(names)
    local = frame.from_crs(np.array([names[i][1] for i in ids]), crs) if ids else np.zeros((0, 3))
    for k, i in enumerate(ids):
        if not np.all(np.isfinite(local[k])):
            raise ValueError(f"line {names[i][0]}: GCP {i!r} lies outside the area its coordinate system covers")
    return [GroundControlPoint(i, local[k], points[i]) for k, i in enumerate(ids)]


def _check_lonlat(where: str, lon: float, lat: float) -> None:
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"{where}: latitude {lat} is outside -90..90 degrees")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"{where}: longitude {lon} is outside -180..180 degrees")


def _gcp_line(number: int, line: str) -> tuple[str, tuple[float, float, float], str, np.ndarray]:
    fields = line.split()
    if len(fields) < 6:
        raise ValueError(
            f"line {number}: expected 'geo_x geo_y geo_z im_x im_y image_name [gcp_name]', got {len(fields)} fields"
        )
    try:
        values = [float(v) for v in fields[:5]]
    except ValueError:
        raise ValueError(f"line {number}: the first five fields must be numbers") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"line {number}: coordinates must be finite")
    if min(values[3], values[4]) < -0.5:
        raise ValueError(f"line {number}: pixel ({values[3]}, {values[4]}) is outside the image")
    xyz = (values[0], values[1], values[2])
    gcp_id = fields[6] if len(fields) > 6 else " ".join(fields[:3])
    return gcp_id, xyz, fields[5], np.array(values[3:5])


def parse_opensfm_gcps(
    text: str, image_sizes: Mapping[str, tuple[int, int]], frame: LocalFrame
) -> list[GroundControlPoint]:
    """Read OpenSfM's ``ground_control_points.json``.

    Parameters
    ----------
    text : ``{"points": [{"id", "position": {"latitude", "longitude", "altitude"}?,
        "observations": [{"shot_id", "projection": [x, y]}]}]}``, projections normalised.
    image_sizes : image name -> (width, height) px of the image the projections refer to.
        Observations of images not listed are skipped (images not in this job).

    Returns
    -------
    GCPs in file order. Raises ValueError with the JSON line or the entry path of bad input.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"line {exc.lineno}: not valid JSON ({exc.msg})") from None
    entries = data.get("points") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        raise ValueError('ground_control_points.json needs a top-level {"points": [...]} list')
    found = [_opensfm_point(k, entry, image_sizes, frame) for k, entry in enumerate(entries)]
    ids = [g.id for g in found]
    if len(set(ids)) != len(ids):
        raise ValueError("ground_control_points.json repeats a point id")
    return found


def _opensfm_point(
    k: int, entry: object, sizes: Mapping[str, tuple[int, int]], frame: LocalFrame
) -> GroundControlPoint:
    where = f"points[{k}]"
    if not isinstance(entry, dict) or "id" not in entry:
        raise ValueError(f"{where}: expected an object with an 'id'")
    position = None
    if entry.get("position") is not None:
        pos = entry["position"]
        lla = [_number(pos, key, f"{where}.position") for key in ("longitude", "latitude", "altitude")]
        _check_lonlat(f"{where}.position", lla[0], lla[1])
        position = frame.from_lonlat(np.array([lla]))[0]
        if not np.all(np.isfinite(position)):
            raise ValueError(f"{where}.position: cannot be placed in UTM zone {frame.epsg}")
    observations: dict[str, np.ndarray] = {}
    listed = entry.get("observations", [])
    if not isinstance(listed, list):
        raise ValueError(f"{where}.observations: expected a list of {{'shot_id': str, 'projection': [x, y]}}")
    for m, obs in enumerate(listed):
        here = f"{where}.observations[{m}]"
        proj = obs.get("projection") if isinstance(obs, dict) else None
        if not isinstance(proj, list) or len(proj) != 2 or not isinstance(obs.get("shot_id"), str):
            raise ValueError(f"{here}: expected {{'shot_id': str, 'projection': [x, y]}}")
        xy = np.array([_number({"v": v}, "v", here) for v in proj])
        if obs["shot_id"] in sizes:
            w, h = sizes[obs["shot_id"]]
            observations[obs["shot_id"]] = xy * max(w, h) - 0.5 + np.array([w, h]) / 2.0
    return GroundControlPoint(str(entry["id"]), position, observations)


def _number(obj: object, key: str, where: str) -> float:
    value = obj.get(key) if isinstance(obj, dict) else None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{where}.{key}: expected a finite number, got {value!r}")
    return float(value)


GCP_FILE_NAMES = ("gcp_list.txt", "ground_control_points.json")  # ODM's, OpenSfM's


def gcp_file_name(uploaded: str) -> str:
    """The stored name of an uploaded GCP file: OpenSfM's for ``.json``, else ODM's."""
    return GCP_FILE_NAMES[1] if uploaded.lower().endswith(".json") else GCP_FILE_NAMES[0]


def parse_gcp_file(
    name: str, text: str, image_sizes: Mapping[str, tuple[int, int]], frame: LocalFrame
) -> list[GroundControlPoint]:
    """A GCP file by its stored name (``gcp_file_name``): ``parse_opensfm_gcps`` for the JSON, else
    ``parse_gcp_list``; ``image_sizes`` (name -> (width, height) px) is what OpenSfM's projections refer to."""
    if name == GCP_FILE_NAMES[1]:
        return parse_opensfm_gcps(text, image_sizes, frame)
    return parse_gcp_list(text, frame)


def scale_observations(gcps: list[GroundControlPoint], factor: float) -> list[GroundControlPoint]:
    """The same GCPs with pixel observations for images resized by ``factor`` (OpenCV convention:
    pixel centres scale about the image corner, ``x' = (x + 0.5) * factor - 0.5``)."""
    if not factor > 0:
        raise ValueError("factor must be positive")
    return [
        GroundControlPoint(g.id, g.position, {name: (xy + 0.5) * factor - 0.5 for name, xy in g.observations.items()})
        for g in gcps
    ]
