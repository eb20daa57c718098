"""Validate an uploaded photo and read what photogrammetry needs from it (EXIF GPS, focal length,
DJI XMP attitude). Pillow (and GDAL for TIFF): the API uses this without loading OpenCV.

Every byte of the image data is decoded, so a truncated or corrupt file is refused, but never into a
full-size raster: a few-hundred-KiB PNG may declare 240 MP (720 MB decoded). A JPEG is decoded at 1/8 scale
(libjpeg's DCT scaling, Pillow's ``draft``: every coefficient is still read); a PNG's zlib stream is inflated
in bounded pieces and checked (chunk CRCs, filter bytes, exactly the data its header declares); a TIFF
(striped or tiled, JPEG or otherwise compressed, BigTIFF) is decoded one tile or strip at a time by GDAL
(rasterio, imported only then); other formats in full, within a process-wide memory budget shared by
concurrent validations.

That decode also gives the reduced copy the photo's quality figures are measured on (``workers.photo_check``:
sharpness, exposure, a perceptual hash), stored as ``quality``: a JPEG is decoded at 1/8 of its size or at the
scale that keeps ``ANALYSIS_PX`` on its longer side, whichever is larger; a TIFF's blocks are averaged into it as
they are checked; a PNG is decoded a second time, whole, up to ``FULL_DECODE_PIXELS`` (a larger one is not
measured).
"""

from __future__ import annotations

import math
import re
import struct
import threading
import warnings
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from PIL import Image, PngImagePlugin, UnidentifiedImageError

from workers.photo_check import ANALYSIS_PX, FULL_DECODE_PIXELS, analysis_gray, full_scale, measure
from workers.tiff_jpeg import JpegBlockError, JpegBlocks

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
    decode_budget_bytes: int = 1024**3  # full decodes (TIFF) of all threads of the process hold at most this


def inspect_image(path: Path, limits: ImageLimits = ImageLimits()) -> dict[str, Any]:
    """Check that ``path`` fully decodes within ``limits`` and return its metadata.

    The header is checked before decoding, so a decompression bomb is refused without allocating it; the
    decode itself holds a bounded amount of memory (see the module's docstring).
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
                xmp = img.info.get("xmp", b"")
                fmt = img.format or ""
                # a truncated or corrupt file fails here; the reduced copy is measured below
                gray = _decode(img, path, decode_budget(limits.decode_budget_bytes))
                exif = Image.Image.getexif(img)  # not PngImageFile's, which decodes the image to look for EXIF
        except InvalidImageError:
            raise
        except (Image.DecompressionBombError, Image.DecompressionBombWarning):
            # Pillow's own guard fires on the declared size before we could read it.
            raise InvalidImageError(
                f"image declares more than {Image.MAX_IMAGE_PIXELS} px (a decompression bomb?)", too_large=True
            ) from None
        except UnidentifiedImageError:
            if _is_tiff(path):  # a TIFF Pillow has no mode for (16-bit RGB, say): GDAL's header and blocks
                return _inspect_tiff(path, limits)
            raise InvalidImageError("not a readable image (JPEG, PNG or TIFF expected)") from None
        except (OSError, SyntaxError, ValueError) as exc:
            raise InvalidImageError(f"image data is corrupt or truncated ({exc})") from None
    meta: dict[str, Any] = {"width": width, "height": height, "format": fmt}
    if fmt == "TIFF" and _has_rpcs(path):
        meta["rpc"] = True
    meta.update(_exif_fields(exif))
    meta.update(_xmp_fields(xmp if isinstance(xmp, bytes) else str(xmp).encode()))
    meta["quality"] = measure(gray) if gray is not None else None
    return meta


class DecodeBudget:
    """Bytes of decoded pixels the threads of a process may hold at once; a decode larger than the whole
    budget waits until it is alone."""

    def __init__(self, total: int) -> None:
        self.total, self.free = total, total
        self._changed = threading.Condition()

    @contextmanager
    def hold(self, nbytes: int) -> Iterator[None]:
        need = min(nbytes, self.total)
        with self._changed:
            self._changed.wait_for(lambda: self.free >= need)
            self.free -= need
        try:
            yield
        finally:
            with self._changed:
                self.free += need
                self._changed.notify_all()


@lru_cache(maxsize=4)
def decode_budget(total: int) -> DecodeBudget:
    """The process's budget of ``total`` bytes (one per size, shared by every caller)."""
    return DecodeBudget(total)


def _decode(img: Image.Image, path: Path, budget: DecodeBudget) -> np.ndarray | None:
    """Decode all of ``img``'s data without holding its full-size raster (a PNG, a JPEG) or within ``budget``;
    answer the photo's reduced brightness (``analysis_gray``), or None for a PNG too large to decode whole."""
    width, height = img.size
    if img.format in ("JPEG", "MPO"):
        img.draft(img.mode, _draft_size(width, height))  # DCT scaling to 1/8 (1/64 of the pixels), or less
        img.load()
        return analysis_gray(img)
    if img.format == "PNG":
        with path.open("rb") as f:
            check_png_data(f, width, height)
            _read_png_trailer(f, img.info)
        return _whole_png_gray(path, width * height * len(img.getbands()) * 2, budget)
    if img.format == "TIFF":
        return _decode_tiff_blocks(path)
    bands = len(img.getbands())
    with budget.hold(width * height * bands * _BYTES_PER_BAND.get(img.mode, 4)):
        img.load()
        return analysis_gray(img)


def _draft_size(width: int, height: int) -> tuple[int, int]:
    """The size to ask libjpeg's DCT scaling for: 1/8, or the largest of 1/4, 1/2, 1/1 that keeps ``ANALYSIS_PX``
    on the longer side (a 4000 px photo is decoded at 500 px, a 1600 px one at 800 px)."""
    factor = min(8.0, max(1.0, max(width, height) / ANALYSIS_PX))
    return math.ceil(width / factor), math.ceil(height / factor)


def _whole_png_gray(path: Path, nbytes: int, budget: DecodeBudget) -> np.ndarray | None:
    """A PNG's reduced brightness from a second, whole decode within ``budget``; None above ``FULL_DECODE_PIXELS``."""
    with Image.open(path) as png:
        if png.width * png.height > FULL_DECODE_PIXELS:
            return None
        with budget.hold(nbytes):
            png.load()
            return analysis_gray(png)


TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # classic and BigTIFF, both byte orders


def _is_tiff(path: Path) -> bool:
    with path.open("rb") as f:
        return f.read(4) in TIFF_MAGIC


def _inspect_tiff(path: Path, limits: ImageLimits) -> dict[str, Any]:
    """Size and a block-by-block decode of a TIFF through GDAL alone (no EXIF: Pillow could not open it)."""
    import rasterio
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(path) as src:
            width, height = src.width, src.height
    except RasterioError as exc:
        raise InvalidImageError(f"not a readable TIFF ({exc})") from None
    _check_dimensions(width, height, limits)
    gray = _decode_tiff_blocks(path)
    meta = {"width": width, "height": height, "format": "TIFF", **({"rpc": True} if _has_rpcs(path) else {})}
    return {**meta, "quality": measure(gray)}


def _has_rpcs(path: Path) -> bool:
    """Whether a TIFF carries a usable rational polynomial camera model (a satellite product's RPC metadata);
    a broken one (missing terms, a zero scale) counts as none."""
    import rasterio  # GDAL: only for TIFF uploads

    from workers.algorithms.stereo.rpc import Rpc  # NumPy only

    try:
        with rasterio.open(path) as src:
            rpcs = src.rpcs
        if rpcs is None:
            return False
        Rpc.from_dict(rpcs.to_dict())
        return True
    except (rasterio.errors.RasterioError, ValueError, TypeError):
        return False


def _decode_tiff_blocks(path: Path) -> np.ndarray:
    """Decode every tile or strip of a TIFF once, one block at a time: a 135 MP JPEG-in-TIFF aerial frame is
    checked in a few MiB instead of its 405 MB raster. Each block's brightness is averaged, as it goes, into cells
    of ``f`` x ``f`` pixels (``f`` keeps ``ANALYSIS_PX`` on the longer side): the reduced copy.

    An 8-bit JPEG-in-TIFF's blocks are decoded at a DCT scale (``workers.tiff_jpeg``; ``f`` then a multiple of it,
    so the cells are the same whole pixels' means): 0.4 s for such a frame instead of GDAL's 1.4. Any other TIFF, or
    one whose blocks do not decode that way, is read by GDAL, which names what is wrong."""
    import rasterio  # GDAL: only for TIFF uploads
    from rasterio.errors import RasterioError

    if (cells := _scaled_block_means(path)) is not None:
        return cells.gray()
    try:
        with rasterio.open(path) as src:
            if src.dtypes[0] not in ("uint8", "uint16"):
                raise InvalidImageError(f"{src.dtypes[0]} samples: 8- or 16-bit unsigned integers expected")
            f = max(1, math.ceil(max(src.width, src.height) / ANALYSIS_PX))
            cells = BlockMeans((math.ceil(src.height / f), math.ceil(src.width / f)), f)
            for _, window in src.block_windows(1):
                cells.add(src.read(window=window), int(window.row_off), int(window.col_off))
    except RasterioError as exc:
        raise InvalidImageError(f"image data is corrupt or truncated ({exc})") from None
    return cells.gray()


def _scaled_block_means(path: Path) -> BlockMeans | None:
    """:func:`_decode_tiff_blocks`'s cells from a JPEG-in-TIFF's blocks decoded at a DCT scale, or None where that
    does not apply (not such a TIFF, too small to reduce) or a block does not decode so."""
    jpeg = JpegBlocks.open(path)
    if jpeg is None:
        return None
    f = max(1, math.ceil(max(jpeg.width, jpeg.height) / ANALYSIS_PX))
    scale = jpeg.scale_for(f)
    if scale == 1:
        return None
    f = scale * math.ceil(f / scale)
    cells = BlockMeans((math.ceil(jpeg.height / f), math.ceil(jpeg.width / f)), f // scale)
    try:
        for row, pixels in jpeg.block_rows(scale):  # a row of blocks at a time: a few MB, one sum each
            cells.add(np.moveaxis(pixels, 2, 0) if pixels.ndim == 3 else pixels[None], row, 0)
    except JpegBlockError:
        return None
    return cells


class BlockMeans:
    """The mean brightness of ``f`` x ``f`` cells of an image read block by block (a block's rows and columns
    summed per cell with ``np.add.reduceat``, whatever the blocks' sizes and offsets)."""

    def __init__(self, shape: tuple[int, int], f: int) -> None:
        self.f, self.total, self.count, self.peak = f, np.zeros(shape), np.zeros(shape), 0.0

    def add(self, block: np.ndarray, row: int, col: int) -> None:
        """``block``: ``(bands, h, w)`` samples whose first pixel is at (``row``, ``col``) of the image.

        Each band's samples are summed per cell in integers first and weighted into brightness on the cells
        (the weights are linear): a 135 MP frame's 2344 blocks took 1.26 s in float64 per pixel, the blocks'
        decode 1.36 s, and the upload check ran no faster on 16 threads than on 2 (held the GIL)."""
        if block.size == 0:
            return
        if block.dtype != np.uint8:  # 8-bit samples' white level is 255 whatever their peak (full_scale)
            self.peak = max(self.peak, float(block.max()))
        rows = (row + np.arange(block.shape[1])) // self.f
        cols = (col + np.arange(block.shape[2])) // self.f
        r0 = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        c0 = np.flatnonzero(np.r_[True, cols[1:] != cols[:-1]])
        sums = np.add.reduceat(np.add.reduceat(block, r0, axis=1, dtype=np.int64), c0, axis=2)
        luma = sums[0] if len(block) < 3 else 0.299 * sums[0] + 0.587 * sums[1] + 0.114 * sums[2]
        counts = np.outer(np.diff(np.r_[r0, len(rows)]), np.diff(np.r_[c0, len(cols)]))
        self.total[np.ix_(rows[r0], cols[c0])] += luma
        self.count[np.ix_(rows[r0], cols[c0])] += counts

    def gray(self) -> np.ndarray:
        """``(h, w) uint8`` mean brightness per cell, scaled by the samples' ``full_scale``."""
        mean = self.total / np.maximum(self.count, 1)
        return np.clip(mean * 255.0 / full_scale(self.peak), 0, 255).astype(np.uint8)


_BYTES_PER_BAND = {"1": 1, "L": 1, "P": 1, "RGB": 1, "RGBA": 1, "CMYK": 1, "YCbCr": 1, "LA": 1, "PA": 1}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # by colour type
_ADAM7 = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]
PIECE = 1024 * 1024  # bytes read or inflated at a time


def check_png_data(f: BinaryIO, width: int, height: int) -> None:
    """Check a PNG's image data as a full decode would, holding ``PIECE`` bytes at a time: the zlib stream of
    its IDAT chunks (each one's CRC right) inflates to at least the rows its header declares, with a filter
    byte of 0 to 4 before each row of each Adam7 pass (PNG spec, sections 7 and 8); what follows is not
    inflated. ``f`` is left at the chunk after the image data. Raises ``ValueError`` saying what is wrong."""
    if f.read(8) != _PNG_SIGNATURE:
        raise ValueError("not a PNG signature")
    rows = _png_rows(f, width, height)
    filters = _filter_bytes(rows)
    inflate, expected, seen = zlib.decompressobj(), sum(n * size for n, size in rows), 0
    for data in _png_idat(f):
        while data and seen < expected and not inflate.eof:
            try:
                out = inflate.decompress(data, min(PIECE, expected - seen))
            except zlib.error as exc:
                raise ValueError(f"the PNG image data does not inflate ({exc})") from None
            data = inflate.unconsumed_tail
            if (bad := filters(seen, out)) is not None:
                raise ValueError(f"unknown PNG row filter {bad}")
            seen += len(out)
    if seen < expected:
        raise ValueError(f"image file is truncated ({seen} of {expected} bytes of image data)")


def _read_png_trailer(f: BinaryIO, info: dict[Any, Any]) -> None:
    """Read the chunks after a PNG's image data into ``info`` (EXIF, text, XMP) as Pillow's ``load`` does
    (``PngImageFile.load_end``), with Pillow's own chunk readers and their limits on text."""
    stream = PngImagePlugin.PngStream(f)
    stream.im_info = info
    while True:
        try:
            kind, pos, length = stream.read()
        except (struct.error, SyntaxError):
            return
        if kind in (b"IEND", b"fcTL"):
            return
        try:
            stream.call(kind, pos, length)
        except (UnicodeDecodeError, EOFError):
            return
        except AttributeError:  # a chunk Pillow has no reader for
            f.seek(length, 1)
        f.read(4)  # its CRC, which Pillow does not check here either


def _png_rows(f: BinaryIO, width: int, height: int) -> list[tuple[int, int]]:
    """(rows, bytes per row with its filter byte) of each pass of the image (one, or Adam7's seven), from the
    IHDR chunk (its CRC checked)."""
    head = f.read(8)
    length, kind = struct.unpack(">I4s", head) if len(head) == 8 else (0, b"")
    data = f.read(13) if (kind, length) == (b"IHDR", 13) else b""
    if len(data) != 13:
        raise ValueError("the first PNG chunk is not a whole header (IHDR)")
    if f.read(4) != struct.pack(">I", zlib.crc32(data, zlib.crc32(kind))):
        raise ValueError("broken PNG file (the header's CRC is wrong)")
    declared_w, declared_h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data)
    if (declared_w, declared_h) != (width, height) or colour not in _PNG_CHANNELS:
        raise ValueError("the PNG header does not describe the image")
    bits = depth * _PNG_CHANNELS[colour]
    passes = _ADAM7 if interlace else [(0, 0, 1, 1)]
    sizes = [(-(-(height - y0) // dy), -(-(width - x0) // dx)) for x0, y0, dx, dy in passes]
    return [(h, 1 + (w * bits + 7) // 8) for h, w in sizes if h > 0 and w > 0]


def _filter_bytes(rows: list[tuple[int, int]]) -> Callable[[int, bytes], int | None]:
    """A check of inflated data ``out`` found at ``offset`` in the stream: its first row filter byte that is
    not 0 to 4, or None."""
    passes, start = [], 0
    for n, size in rows:
        passes.append((start, start + n * size, size))
        start += n * size

    def first_bad(offset: int, out: bytes) -> int | None:
        data = np.frombuffer(out, dtype=np.uint8)
        for begin, end, size in passes:
            first = begin + -(-max(offset - begin, 0) // size) * size
            picked = data[np.arange(first, min(end, offset + len(out)), size) - offset]
            if (bad := picked[picked > 4]).size:
                return int(bad[0])
        return None

    return first_bad


def _png_idat(f: BinaryIO) -> Iterator[bytes]:
    """The image data, in pieces: the content of the consecutive IDAT chunks, each one's CRC checked once read
    whole. It ends where the file or the IDAT chunks do."""
    started = False
    while len(head := f.read(8)) == 8:
        length, kind = struct.unpack(">I4s", head)
        if kind != b"IDAT":
            if started or kind == b"IEND":
                f.seek(-8, 1)
                return
            f.seek(length + 4, 1)  # a chunk before the image data, read by Pillow when it opened the file
            continue
        started, crc, left = True, zlib.crc32(kind), length
        while left and (piece := f.read(min(PIECE, left))):
            left -= len(piece)
            crc = zlib.crc32(piece, crc)
            yield piece
        if left:
            return
        if f.read(4) != struct.pack(">I", crc):
            raise ValueError("broken PNG file (the CRC of an image data chunk is wrong)")


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
