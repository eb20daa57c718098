"""A photo at a glance, for the API (Pillow and NumPy only: no OpenCV there).

At upload, ``workers.image_meta`` decodes every photo into a reduced copy anyway (a JPEG at 1/2 to 1/8 of its
size, a TIFF block by block); ``measure`` reads that copy at ``ANALYSIS_PX`` on its longer side: sharpness (the
variance of the Laplacian, as in Pech-Pacheco et al. 2000, "Diatom autofocusing in brightfield microscopy"),
exposure (mean brightness, the share of nearly black and of clipped white pixels) and a 64-bit perceptual hash
(the signs of the 8 x 8 lowest DCT frequencies of a 32 x 32 copy against their median, as pHash does). Those
figures are stored with the photo; ``judge`` reads a flight's photos against each other (a photo much less
sharp than its flight, too dark, too bright, without GPS where the others have it, the same picture as another,
another size) and says why, in words. ``preview_jpeg`` makes the reduced JPEGs the viewer shows.
"""

from __future__ import annotations

import io
import math
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from workers.tiff_jpeg import JpegBlockError, JpegBlocks

ANALYSIS_PX = 512  # longer side of the copy the figures are measured on, px
DARK_LEVEL, BRIGHT_LEVEL = 24, 245  # of 255: a pixel at or below is nearly black, at or above clipped white
DARK_SHARE, BRIGHT_SHARE = 0.5, 0.3  # a photo with more of such pixels is under- or over-exposed
DARK_MEAN, BRIGHT_MEAN = 35.0, 225.0  # ... or with a mean brightness beyond these
BLUR_RATIO = 1 / 3  # a photo with less than this share of its flight's median sharpness is blurred
BLUR_FLOOR = 15.0  # a sharpness below this is flat or blurred whatever the flight (a 0-255 image's Laplacian)
MIN_FLIGHT = 3  # photos measured before the flight's median means anything
DUPLICATE_BITS = 5  # perceptual hashes this close (of 64 bits) are the same picture
FULL_DECODE_PIXELS = 40_000_000  # a PNG (or other format without a reduced decode) is measured up to this size


def analysis_gray(img: Image.Image) -> np.ndarray:
    """``(h, w) uint8`` brightness of ``img`` (any Pillow mode, 8 or 16 bits), box-reduced by a whole factor to at
    most ``ANALYSIS_PX`` on its longer side."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        values = np.asarray(img, dtype=np.float64)
        gray = Image.fromarray(np.clip(values * 255.0 / full_scale(float(values.max())), 0, 255).astype(np.uint8))
    else:
        gray = img.convert("L")
    factor = math.ceil(max(gray.size) / ANALYSIS_PX)
    return np.asarray(gray.reduce(factor) if factor > 1 else gray)


def full_scale(peak: float) -> float:
    """The white level of 16-bit samples whose largest is ``peak``: 10-, 12-, 14- or 16-bit sensors' data is
    stored in 16-bit samples, so the smallest of those ranges that holds the peak."""
    return next((2.0**bits - 1 for bits in (8, 10, 12, 14) if peak <= 2**bits - 1), 65535.0)


def laplacian_variance(gray: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of ``gray`` (``(h, w)``, 0-255): high for sharp detail."""
    g = gray.astype(np.float32)
    if min(g.shape) < 3:
        return 0.0
    lap = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def _dct_matrix(n: int) -> np.ndarray:
    k, x = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    m = np.sqrt(2.0 / n) * np.cos(np.pi * (2 * x + 1) * k / (2 * n))
    m[0] /= np.sqrt(2.0)
    return m


_DCT32 = _dct_matrix(32)


def perceptual_hash(gray: np.ndarray) -> str:
    """64-bit pHash of ``gray`` as 16 hex digits: the 8 x 8 lowest frequencies of the DCT of a 32 x 32 copy,
    each 1 where it is above their median (the constant term left out of the median)."""
    small = np.asarray(Image.fromarray(gray).resize((32, 32), Image.Resampling.BOX), dtype=np.float64)
    low = (_DCT32 @ small @ _DCT32.T)[:8, :8].ravel()
    bits = low > np.median(low[1:])
    return f"{int(''.join('1' if b else '0' for b in bits), 2):016x}"


def hamming(a: str, b: str) -> int:
    """Bits that differ between two hashes of ``perceptual_hash``."""
    return (int(a, 16) ^ int(b, 16)).bit_count()


def measure(gray: np.ndarray) -> dict[str, Any]:
    """The figures stored with a photo, of its ``analysis_gray`` copy."""
    return {
        "analysed_px": [int(gray.shape[1]), int(gray.shape[0])],
        "sharpness": round(laplacian_variance(gray), 2),
        "mean_brightness": round(float(gray.mean()), 2),
        "dark_share": round(float((gray <= DARK_LEVEL).mean()), 4),
        "bright_share": round(float((gray >= BRIGHT_LEVEL).mean()), 4),
        "phash": perceptual_hash(gray),
    }


# -- A flight's photos against each other ------------------------------------------------------------------


@dataclass(frozen=True)
class PhotoFacts:
    """What ``judge`` reads of one photo: its key (the image id), name, size, whether a job will have a
    position for it, and its stored ``measure`` figures (None: measured before the check existed)."""

    key: int
    name: str
    width: int
    height: int
    has_gps: bool
    quality: dict[str, Any] | None


def judge(photos: list[PhotoFacts]) -> dict[int, list[dict[str, str]]]:
    """Per photo key, its issues as ``{"code", "message"}``: codes ``blurred``, ``under_exposed``,
    ``over_exposed``, ``no_gps``, ``duplicate`` (of an earlier photo in ``photos``' order), ``size_mismatch``,
    ``not_checked``. A photo with none maps to an empty list."""
    issues: dict[int, list[dict[str, str]]] = {p.key: [] for p in photos}
    measured = [p for p in photos if p.quality]
    sharp = [float(p.quality["sharpness"]) for p in measured if p.quality]
    median = float(np.median(sharp)) if len(sharp) >= MIN_FLIGHT else None
    with_gps = sum(p.has_gps for p in photos)
    sizes = Counter((p.width, p.height) for p in photos)
    ((usual, usual_count),) = sizes.most_common(1) or [((0, 0), 0)]
    earlier = HashIndex()
    for p in photos:
        found = issues[p.key]
        if p.quality is None:
            found.append(_issue("not_checked", "not checked: uploaded before photos were checked, or too large"))
        else:
            # a dark or washed-out photo has little contrast, so little Laplacian too: the exposure says why
            found.extend(_exposure(p.quality) or _blur(p.quality, median))
            twin = earlier.near(str(p.quality["phash"]))
            if twin is not None:
                found.append(_issue("duplicate", f"the same picture as {twin} (perceptual hashes all but alike)"))
            earlier.add(str(p.quality["phash"]), p.name)
        if not p.has_gps and with_gps:
            found.append(_issue("no_gps", f"no GPS position, unlike {with_gps} other photo(s) of the flight"))
        if (p.width, p.height) != usual and usual_count > len(photos) / 2:
            found.append(
                _issue(
                    "size_mismatch",
                    f"{p.width} x {p.height} px, while {usual_count} of {len(photos)} photos are "
                    f"{usual[0]} x {usual[1]} px: another camera, or a cropped or rotated copy",
                )
            )
    return issues


class HashIndex:
    """Hashes seen so far, found again within ``DUPLICATE_BITS`` without comparing every pair: the 64 bits are cut
    into ``DUPLICATE_BITS + 1`` bands, and two hashes that differ in at most that many bits agree on a whole band
    (pigeonhole), so only the hashes sharing a band with the new one are compared (a flight of 20 000 photos is
    judged in well under a second instead of 2e8 comparisons)."""

    BANDS = DUPLICATE_BITS + 1

    def __init__(self) -> None:
        self.buckets: dict[tuple[int, int], list[tuple[int, str, str]]] = {}  # band -> (order added, hash, name)
        self.count = 0

    def _keys(self, phash: str) -> list[tuple[int, int]]:
        value, width = int(phash, 16), -(-64 // self.BANDS)
        return [(b, (value >> (b * width)) & ((1 << width) - 1)) for b in range(self.BANDS)]

    def near(self, phash: str) -> str | None:
        """The name of the first hash added within ``DUPLICATE_BITS`` of ``phash``, or None."""
        found = [
            (order, name)
            for key in self._keys(phash)
            for order, other, name in self.buckets.get(key, [])
            if hamming(other, phash) <= DUPLICATE_BITS
        ]
        return min(found)[1] if found else None

    def add(self, phash: str, name: str) -> None:
        for key in self._keys(phash):
            self.buckets.setdefault(key, []).append((self.count, phash, name))
        self.count += 1


def _issue(code: str, message: str) -> dict[str, str]:
    return {"code": code, "message": message}


def _exposure(q: dict[str, Any]) -> list[dict[str, str]]:
    mean, dark, bright = float(q["mean_brightness"]), float(q["dark_share"]), float(q["bright_share"])
    if dark > DARK_SHARE or mean < DARK_MEAN:
        return [
            _issue("under_exposed", f"too dark: {dark:.0%} of its pixels are nearly black (mean brightness {mean:.0f})")
        ]
    if bright > BRIGHT_SHARE or mean > BRIGHT_MEAN:
        return [_issue("over_exposed", f"too bright: {bright:.0%} of its pixels are clipped white (mean {mean:.0f})")]
    return []


def _blur(q: dict[str, Any], median: float | None) -> list[dict[str, str]]:
    value = float(q["sharpness"])
    if median is not None and value < BLUR_RATIO * median:
        return [
            _issue(
                "blurred",
                f"blurred: sharpness {value:.0f}, under a third of the flight's median {median:.0f} "
                "(variance of the Laplacian)",
            )
        ]
    if value < BLUR_FLOOR:
        return [_issue("blurred", f"blurred or without detail: sharpness {value:.1f} (variance of the Laplacian)")]
    return []


# -- Previews ----------------------------------------------------------------------------------------------


@contextmanager
def _unbounded(nbytes: int) -> Iterator[None]:
    yield


class PreviewError(ValueError):
    """The photo has no preview: unreadable, or a format too large to decode whole."""


def preview_jpeg(path: Path, size: int, hold: Callable[[int], AbstractContextManager[None]] = _unbounded) -> bytes:
    """A JPEG of the photo at ``path``, at most ``size`` px on its longer side: a JPEG decoded at a reduced scale,
    a TIFF read decimated through GDAL (its overviews where it has them), other formats whole up to
    ``FULL_DECODE_PIXELS``, holding ``hold(bytes)`` (a process's decode budget) meanwhile. Raises
    ``PreviewError``."""
    try:
        with Image.open(path) as img:
            if img.format in ("JPEG", "MPO"):
                img.draft("RGB", (size, size))
                img.load()
                return _encode(img, size)
            if img.format != "TIFF":
                if img.width * img.height > FULL_DECODE_PIXELS:
                    raise PreviewError(f"no preview of a {img.format} photo over {FULL_DECODE_PIXELS} px")
                with hold(img.width * img.height * len(img.getbands()) * 2):
                    img.load()
                    return _encode(img, size)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        if isinstance(exc, PreviewError):
            raise
        # a TIFF that Pillow cannot open (16-bit RGB, BigTIFF) is GDAL's
    return _encode(_tiff_preview(path, size), size)


def _tiff_preview(path: Path, size: int) -> Image.Image:
    """A TIFF photo area-averaged to at most ``size`` px: an 8-bit JPEG-in-TIFF decoded at a DCT scale (a 135 MP
    aerial frame in a third of the time, ``workers.tiff_jpeg``), any other (or one whose blocks do not decode so)
    through GDAL, which says what is wrong."""
    jpeg = JpegBlocks.open(path)
    if jpeg is not None and (dct_scale := jpeg.scale_for(max(jpeg.width, jpeg.height) / size)) > 1:
        try:
            h, w = _preview_shape(jpeg.width, jpeg.height, size)
            return Image.fromarray(jpeg.reduced(dct_scale)).resize((w, h), Image.Resampling.BOX)
        except JpegBlockError:
            pass
    import rasterio  # GDAL: only for TIFF photos
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(path) as src:
            shape = _preview_shape(src.width, src.height, size)
            bands = [1, 2, 3] if src.count >= 3 else [1]
            data = src.read(bands, out_shape=(len(bands), *shape), resampling=Resampling.average).astype(np.float64)
    except RasterioError as exc:
        raise PreviewError(f"not a readable TIFF ({exc})") from None
    scale = 255.0 / full_scale(float(data.max())) if data.size else 1.0
    pixels = np.clip(np.moveaxis(data, 0, -1) * scale, 0, 255).astype(np.uint8)
    return Image.fromarray(pixels[..., 0] if pixels.shape[-1] == 1 else pixels)


def _preview_shape(width: int, height: int, size: int) -> tuple[int, int]:
    """(rows, columns) of a ``width`` x ``height`` photo's preview of at most ``size`` px."""
    factor = max(1.0, max(width, height) / size)
    return max(1, round(height / factor)), max(1, round(width / factor))


def _encode(img: Image.Image, size: int) -> bytes:
    if img.mode not in ("RGB", "L"):
        img = img.convert("RGB") if img.mode not in ("I;16", "I;16B", "I;16L", "I", "F") else _eight_bit(img)
    img.thumbnail((size, size), Image.Resampling.BOX)
    out = io.BytesIO()
    img.save(out, "JPEG", quality=85)
    return out.getvalue()


def _eight_bit(img: Image.Image) -> Image.Image:
    values = np.asarray(img, dtype=np.float64)
    return Image.fromarray(np.clip(values * 255.0 / full_scale(float(values.max())), 0, 255).astype(np.uint8))
