"""Validate an uploaded photo and read what photogrammetry needs from it (EXIF GPS, focal length,
DJI XMP attitude). Pillow only: the API uses this without loading OpenCV."""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, UnidentifiedImageError

GPS_IFD = 0x8825
EXIF_IFD = 0x8769
_XMP_FIELDS = {
    "yaw": ("FlightYawDegree", "GimbalYawDegree"),
    "pitch": ("GimbalPitchDegree", "FlightPitchDegree"),
    "roll": ("GimbalRollDegree", "FlightRollDegree"),
    "relative_altitude": ("RelativeAltitude",),
}


class InvalidImageError(ValueError):
    """The file is not an image this service can use; the message says why.

    ``too_large`` tells an over-size image (HTTP 413) from an unreadable one (422).
    """

    def __init__(self, message: str, too_large: bool = False) -> None:
        super().__init__(message)
        self.too_large = too_large


@dataclass(frozen=True)
class ImageLimits:
    max_pixels: int = 250_000_000
    max_side: int = 100_000
    min_side: int = 16


def inspect_image(path: Path, limits: ImageLimits = ImageLimits()) -> dict[str, Any]:
    """Check that ``path`` fully decodes within ``limits`` and return its metadata.

    The header is checked before decoding, so a decompression bomb is refused without allocating it.
    Raises ``InvalidImageError`` with a reason a user can act on.
    """
    if path.stat().st_size == 0:
        raise InvalidImageError("empty file")
    # Pillow's bomb guard is process-wide; align it with ours (its default, 89 MP, would refuse
    # a legitimate 135 MP aerial frame).
    Image.MAX_IMAGE_PIXELS = limits.max_pixels
    with warnings.catch_warnings():
        warnings.simplefilter("error", Image.DecompressionBombWarning)
        try:
            with Image.open(path) as img:
                width, height = img.size
                _check_dimensions(width, height, limits)
                exif = img.getexif()
                xmp = img.info.get("xmp", b"")
                fmt = img.format or ""
                img.load()  # full decode: a truncated or corrupt file fails here
        except InvalidImageError:
            raise
        except (Image.DecompressionBombError, Image.DecompressionBombWarning):
            # Pillow's own guard fires on the declared size before we could read it.
            raise InvalidImageError(
                f"image declares more than {Image.MAX_IMAGE_PIXELS} px (a decompression bomb?)", too_large=True
            ) from None
        except UnidentifiedImageError:
            raise InvalidImageError("not a readable image (JPEG, PNG or TIFF expected)") from None
        except (OSError, SyntaxError, ValueError) as exc:
            raise InvalidImageError(f"image data is corrupt or truncated ({exc})") from None
    meta: dict[str, Any] = {"width": width, "height": height, "format": fmt}
    meta.update(_exif_fields(exif))
    meta.update(_xmp_fields(xmp if isinstance(xmp, bytes) else str(xmp).encode()))
    return meta


def _check_dimensions(width: int, height: int, limits: ImageLimits) -> None:
    if width * height > limits.max_pixels or max(width, height) > limits.max_side:
        raise InvalidImageError(
            f"image is {width}x{height} px, over the limit of {limits.max_pixels} px and {limits.max_side} px per side",
            too_large=True,
        )
    if min(width, height) < limits.min_side:
        raise InvalidImageError(f"image is {width}x{height} px, under {limits.min_side} px per side")


def _exif_fields(exif: Image.Exif) -> dict[str, Any]:
    sub = exif.get_ifd(EXIF_IFD)
    focal = _as_float(sub.get(0x920A))  # FocalLength, mm
    focal35 = _as_float(sub.get(0xA405))  # FocalLengthIn35mmFilm, mm
    return {
        "gps": _gps(exif.get_ifd(GPS_IFD)),
        "focal_length_mm": focal,
        "focal_length_35mm": focal35,
        "make": str(exif.get(0x010F, "")).strip("\x00 ") or None,
        "model": str(exif.get(0x0110, "")).strip("\x00 ") or None,
        "datetime": str(sub.get(0x9003, "")).strip("\x00 ") or None,
    }


def _gps(ifd: dict[int, Any]) -> dict[str, float | None] | None:
    lat, lon = _dms(ifd.get(2)), _dms(ifd.get(4))
    if lat is None or lon is None:
        return None
    if str(ifd.get(1, "N")).upper().startswith("S"):
        lat = -lat
    if str(ifd.get(3, "E")).upper().startswith("W"):
        lon = -lon
    if not (-90 <= lat <= 90 and -180 <= lon <= 180) or (lat == 0 and lon == 0):
        return None
    alt = _as_float(ifd.get(6), positive=False)  # sea level is a real altitude
    if alt is not None and ifd.get(5) in (1, b"\x01"):
        alt = -alt
    return {"lat": lat, "lon": lon, "alt": alt}


def _dms(value: Any) -> float | None:
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return d + m / 60.0 + s / 3600.0


def _as_float(value: Any, positive: bool = True) -> float | None:
    try:
        result = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if not math.isfinite(result) or (positive and result <= 0):
        return None  # NaN, and a focal length of 0, mean "unknown" in EXIF
    return result


def _xmp_fields(xmp: bytes) -> dict[str, float | None]:
    """DJI's attitude and height; a value that is not a finite number (``"e"``, ``"1e999"``) counts as absent."""
    text = xmp.decode("utf-8", "replace")
    found: dict[str, float | None] = {}
    for key, names in _XMP_FIELDS.items():
        found[key] = None
        for name in names:
            match = re.search(rf'drone-dji:{name}\s*=\s*"([-+0-9.eE]+)"', text) or re.search(
                rf"<drone-dji:{name}>([-+0-9.eE]+)<", text
            )
            value = _as_float(match.group(1), positive=False) if match else None
            if value is not None:
                found[key] = value
                break
    return found
