"""GPS side files: each frame's position from a navigation log instead of its EXIF tags.

Two formats, read into the same records (WGS84 longitude and latitude in degrees, the height as the
file states it, no geoid or ellipsoid conversion, as for GCPs):

- ODM's ``geo.txt``: the first line names the coordinate system (``EPSG:4326``, a PROJ string such as
  ``+proj=utm +zone=32 +datum=WGS84``, ``WGS84``, or ODM's ``WGS84 UTM 32N``); then one line per image,
  ``image_name x y [z] [omega phi kappa] [horizontal_accuracy vertical_accuracy] [extras...]``, x the
  easting or longitude. Coordinates in another system are converted to longitude and latitude with pyproj.
- a CSV ``name,lat,lon,alt[,accuracy]``, the header row optional, the accuracy in metres.

Blank lines and ``#`` comments are skipped in both. Every problem raises ``ValueError`` naming the 1-based
line and what is wrong with it. pyproj only: the API parses an upload with this module before storing it.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pyproj import CRS

GPS_FILE_NAMES = ("geo.txt", "gps.csv")  # the stored names: ODM's geo.txt, the CSV
MAX_NAME_CHARS = 255  # an image name longer than any stored one is a misread line

_CSV_HEADER = (
    ("name", "image", "image_name", "filename", "file"),
    ("lat", "latitude"),
    ("lon", "lng", "long", "longitude"),
    ("alt", "altitude", "height", "z"),
    ("accuracy", "accuracy_m", "horizontal_accuracy", "acc"),
)


@dataclass(frozen=True)
class GpsFix:
    """One image's position from a side file.

    Attributes
    ----------
    name : the image's file name, as the file writes it.
    lat, lon : WGS84 degrees.
    alt : height in metres as the file states it, or None when the file gives none.
    accuracy_m : horizontal accuracy in metres (the CSV's accuracy, geo.txt's horizontal accuracy), or None.
    line : the 1-based line of the file it was read from.
    """

    name: str
    lat: float
    lon: float
    alt: float | None
    accuracy_m: float | None
    line: int


@dataclass(frozen=True)
class GpsFile:
    """A parsed side file: its stored name (one of ``GPS_FILE_NAMES``), its coordinate system and fixes."""

    name: str
    crs: str
    fixes: list[GpsFix]


def gps_file_name(uploaded: str, text: str) -> str:
    """The stored name of an uploaded side file: the CSV's for a ``.csv`` name, or when the first line that is
    not a comment has a comma and names no coordinate system; ODM's ``geo.txt`` otherwise."""
    if uploaded.lower().endswith(".csv"):
        return GPS_FILE_NAMES[1]
    first = next((line for _, line in _content_lines(text)), "")
    looks_like_crs = first.startswith("+") or first.upper().startswith(("EPSG:", "WGS84"))
    return GPS_FILE_NAMES[1] if "," in first and not looks_like_crs else GPS_FILE_NAMES[0]


def parse_gps_file(name: str, text: str) -> GpsFile:
    """A side file by its stored name (``gps_file_name``): ``parse_gps_csv`` or ``parse_geo_txt``."""
    if name == GPS_FILE_NAMES[1]:
        return GpsFile(name, "EPSG:4326", parse_gps_csv(text))
    crs, fixes = parse_geo_txt(text)
    return GpsFile(name, crs, fixes)


def parse_geo_txt(text: str) -> tuple[str, list[GpsFix]]:
    """Read ODM's ``geo.txt``: its coordinate system as written on its first line, and one fix per image.

    Raises ValueError naming the line (1-based) of bad input: a coordinate system pyproj does not know, a
    line of 5, 6 or 8 fields (which columns they are is ambiguous), a value that is not a finite number, a
    longitude or latitude off the globe, an accuracy that is not positive, an image listed twice.
    """
    lines = _content_lines(text)
    if not lines:
        raise ValueError("geo.txt is empty: expected a coordinate system on line 1")
    number, first = lines[0]
    try:
        crs = _parse_crs(first)
    except ValueError as exc:
        raise ValueError(f"line {number}: {exc}") from None
    rows = [_geo_line(n, line) for n, line in lines[1:]]
    _refuse_duplicates([(n, name) for n, name, *_ in rows])
    if not rows:
        return first, []
    xy = np.array([[x, y] for _, _, x, y, _, _ in rows], dtype=np.float64)
    if crs.is_geographic:  # x is the longitude (pyproj's always_xy): checked before it is converted
        for (n, *_), (x, y) in zip(rows, xy, strict=True):
            _check_lonlat(n, x, y)
    lonlat = _to_lonlat(xy, crs)
    fixes = []
    for (n, name, _, _, alt, accuracy), (lon, lat) in zip(rows, lonlat, strict=True):
        if not (math.isfinite(lon) and math.isfinite(lat)):
            raise ValueError(f"line {n}: {name} lies outside the area its coordinate system covers")
        _check_lonlat(n, lon, lat)
        fixes.append(GpsFix(name, float(lat), float(lon), alt, accuracy, n))
    return first, fixes


def parse_gps_csv(text: str) -> list[GpsFix]:
    """Read a CSV ``name,lat,lon,alt[,accuracy]`` (WGS84 degrees, metres); the first row may be a header
    naming those columns in that order. An empty altitude or accuracy is unknown (None).

    Raises ValueError naming the line (1-based) of bad input, as ``parse_geo_txt`` does.
    """
    rows = []
    for k, (number, line) in enumerate(_content_lines(text)):
        fields = [f.strip() for f in next(csv.reader([line]))]
        if k == 0 and _is_header(number, fields):
            continue
        rows.append(_csv_line(number, fields))
    _refuse_duplicates([(fix.line, fix.name) for fix in rows])
    return rows


def _content_lines(text: str) -> list[tuple[int, str]]:
    """(1-based line number, text without its comment) of every line that is not blank or only a comment."""
    text = text.removeprefix("\ufeff")  # the byte-order mark spreadsheets write at the start of a CSV
    lines = [(n, raw.split("#", 1)[0].strip()) for n, raw in enumerate(text.splitlines(), start=1)]
    return [(n, line) for n, line in lines if line]


def _parse_crs(text: str) -> CRS:
    """A CRS from geo.txt's first line: a PROJ string, ``EPSG:nnnn``, ``WGS84`` or ``WGS84 UTM <zone><N|S>``
    (ODM's first line, read as the GCP file's is: :func:`workers.algorithms.sfm.gcp.parse_crs`).

    pyproj (~20 MiB) is imported here, by the side files that name a system, not by every worker that imports
    the workspace (a drone flight without a side file composes without it)."""
    from workers.algorithms.sfm.gcp import parse_crs

    try:
        crs = parse_crs(text)
    except ValueError as exc:
        if "UTM zone" in str(exc):
            raise
        raise ValueError(
            f"unknown coordinate system {text[:80]!r}; expected EPSG:4326, a +proj=... string or WGS84"
        ) from None
    if not (crs.is_geographic or crs.is_projected):
        raise ValueError(f"{text[:80]!r} is not a horizontal coordinate system (geographic or projected)")
    return crs


def _to_lonlat(xy: np.ndarray, crs: CRS) -> np.ndarray:
    """(N, 2) float64 x, y in ``crs`` (x = easting or longitude) -> (N, 2) WGS84 longitude, latitude degrees;
    inf or NaN where a point lies outside what ``crs`` can convert."""
    from pyproj import CRS, Transformer  # see _parse_crs

    wgs84 = CRS.from_epsg(4326)
    if crs == wgs84:
        return xy
    lon, lat = Transformer.from_crs(crs, wgs84, always_xy=True).transform(xy[:, 0], xy[:, 1], errcheck=False)
    return np.column_stack([np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)])


def _geo_line(number: int, line: str) -> tuple[int, str, float, float, float | None, float | None]:
    """(line, image name, x, y, z or None, horizontal accuracy or None) of one geo.txt image line."""
    fields = line.split()
    if len(fields) < 3 or len(fields) in (5, 6, 8):
        raise ValueError(
            f"line {number}: expected 'image_name x y [z] [omega phi kappa] [horizontal_accuracy "
            f"vertical_accuracy]' (3, 4, 7 or 9 fields), got {len(fields)} fields"
        )
    name = _image_name(number, fields[0])
    x, y = _finite(number, "x", fields[1]), _finite(number, "y", fields[2])
    z = _finite(number, "z", fields[3]) if len(fields) >= 4 else None
    for what, value in zip(("omega", "phi", "kappa"), fields[4:7], strict=False):
        _finite(number, what, value)
    accuracy = None
    if len(fields) >= 9:
        accuracy = _accuracy(number, "horizontal accuracy", fields[7])
        _accuracy(number, "vertical accuracy", fields[8])
    return number, name, x, y, z, accuracy


def _is_header(number: int, fields: list[str]) -> bool:
    """Whether the CSV's first row is a header: its latitude is not a number and it names a column. It must then
    name the columns in the order they are read, so that ``name,lon,lat,alt`` is not read with lat and lon swapped."""
    names = [f.lower() for f in fields]
    known = {alias for aliases in _CSV_HEADER for alias in aliases}
    if len(fields) < 2 or _is_number(fields[1]) or not known.intersection(names):
        return False  # a data row: its own checks say what is wrong with it
    if not 4 <= len(names) <= 5 or any(n not in aliases for n, aliases in zip(names, _CSV_HEADER, strict=False)):
        raise ValueError(f"line {number}: header {','.join(fields)[:80]!r} is not name,lat,lon,alt[,accuracy]")
    return True


def _csv_line(number: int, fields: list[str]) -> GpsFix:
    if len(fields) not in (4, 5):
        raise ValueError(f"line {number}: expected 'name,lat,lon,alt[,accuracy]', got {len(fields)} fields")
    name = _image_name(number, fields[0])
    lat, lon = _finite(number, "latitude", fields[1]), _finite(number, "longitude", fields[2])
    _check_lonlat(number, lon, lat)
    alt = _finite(number, "altitude", fields[3]) if fields[3] else None
    accuracy = _accuracy(number, "accuracy", fields[4]) if len(fields) == 5 and fields[4] else None
    return GpsFix(name, lat, lon, alt, accuracy, number)


def _image_name(number: int, name: str) -> str:
    if not name:
        raise ValueError(f"line {number}: the image name is empty")
    if len(name) > MAX_NAME_CHARS:
        raise ValueError(f"line {number}: an image name of {len(name)} characters; at most {MAX_NAME_CHARS}")
    return name


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _finite(number: int, what: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"line {number}: {what} {text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"line {number}: {what} {text[:40]!r} is not a finite number")
    return value


def _accuracy(number: int, what: str, text: str) -> float:
    value = _finite(number, what, text)
    if value <= 0:
        raise ValueError(f"line {number}: {what} {value} m is not positive")
    return value


def _check_lonlat(number: int, lon: float, lat: float) -> None:
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"line {number}: latitude {lat} is outside -90..90 degrees")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"line {number}: longitude {lon} is outside -180..180 degrees")


def _refuse_duplicates(names: list[tuple[int, str]]) -> None:
    first: dict[str, int] = {}
    for number, name in names:
        if (earlier := first.setdefault(name, number)) != number:
            raise ValueError(f"line {number}: {name} is listed twice, on lines {earlier} and {number}")


def with_side_file_gps(frame: dict[str, Any], source: str, fixes: dict[str, GpsFix]) -> dict[str, Any]:
    """A job input entry with the side file's position in place of its EXIF one, when the file names it.
    ``gps`` keeps its ``{"lat", "lon", "alt"}`` shape; the accuracy (m, or None) is a key of its own."""
    fix = fixes.get(frame["name"])
    if fix is None:
        return frame
    gps = {"lat": fix.lat, "lon": fix.lon, "alt": fix.alt}
    return {**frame, "gps": gps, "gps_accuracy_m": fix.accuracy_m, "gps_source": source}
