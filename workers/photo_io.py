"""Reading a photo whole, reduced or by window, without decoding more of it than asked.

JPEG and PNG go through OpenCV (a whole decode; EXIF orientation applied). TIFF is read tile by tile or strip by
strip: a reduced copy is averaged block by block and a window reads only the blocks it touches, so a 75000 x 1800
JPEG-in-TIFF aerial frame (135 MP, 405 MB decoded) is never held whole. An 8-bit JPEG-in-TIFF's blocks are decoded
by OpenCV's libjpeg-turbo (``workers.tiff_jpeg``: at a DCT scale for a reduced copy), any other TIFF through rasterio
(GDAL). Pixels come back as OpenCV does them: (H, W, 3) uint8 BGR.
"""

from __future__ import annotations

import threading
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.errors import NotGeoreferencedWarning
from rasterio.windows import Window

from workers.tiff_jpeg import JpegBlockError, JpegBlocks

TIFF_SUFFIXES = (".tif", ".tiff")
# a photo has no map placement; rasterio would say so on every open
warnings.filterwarnings("ignore", category=NotGeoreferencedWarning, module="rasterio")


def reads_by_window(path: str | Path) -> bool:
    """True for formats whose windows cost only their blocks (TIFF); JPEG and PNG decode whole."""
    return Path(path).suffix.lower() in TIFF_SUFFIXES


def dct_block(path: str | Path) -> int:
    """Width in px of the blocks the photo's codec transforms: 8 for JPEG (a JPEG file, or a TIFF whose tiles
    or strips are JPEG), 1 for the others (lossless: no blocks to smear an edge across)."""
    if not reads_by_window(path):
        return 8 if Path(path).suffix.lower() in (".jpg", ".jpeg") else 1
    with rasterio.open(path) as src:
        return 8 if src.compression is not None and src.compression.name == "jpeg" else 1


def read_reduced(path: str | Path, max_px: int) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The photo shrunk so its longest side is at most ``max_px`` (area average, no aliasing), and its
    full (width, height); None when it cannot be decoded.

    The reduced size is ``round(side * max_px / longest)``, the same for either reader.
    """
    if reads_by_window(path):
        return _tiff_reduced(Path(path), max_px)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        return None
    height, width = image.shape[:2]
    size = reduced_size(width, height, max_px)
    if size == (width, height):
        return np.ascontiguousarray(image), (width, height)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), (width, height)


def reduced_size(width: int, height: int, max_px: int) -> tuple[int, int]:
    """(width, height) scaled so the longest side is at most ``max_px``; unchanged when already that small."""
    longest = max(width, height)
    if longest <= max_px:
        return width, height
    scale = max_px / longest
    return max(1, round(width * scale)), max(1, round(height * scale))


def _tiff_reduced(path: Path, max_px: int) -> tuple[np.ndarray, tuple[int, int]] | None:
    if (fast := read_jpeg_reduced(path, max_px)) is not None:
        return fast
    try:
        with rasterio.open(path) as src:
            width, height = src.width, src.height
            out_w, out_h = reduced_size(width, height, max_px)
            bands = src.read(
                indexes=_rgb_bands(src.count),
                out_shape=(min(src.count, 3), out_h, out_w),
                resampling=Resampling.average,
            )
            return _to_bgr8(bands, src.dtypes[0]), (width, height)
    except (rasterio.errors.RasterioError, ValueError):  # unreadable, or samples that are not 8/16-bit
        return None


def read_jpeg_reduced(path: str | Path, max_px: int) -> tuple[np.ndarray, tuple[int, int]] | None:
    """:func:`read_reduced` of a JPEG-in-TIFF through :class:`JpegBlocks` when its DCT scaling gets at least half
    way (area-averaged the rest of the way); None when it does not apply or a block would not decode here."""
    jpeg = JpegBlocks.open(path, decode_bgr)
    if jpeg is None:
        return None
    out_w, out_h = reduced_size(jpeg.width, jpeg.height, max_px)
    scale = jpeg.scale_for(min(jpeg.width / out_w, jpeg.height / out_h))
    if scale == 1:
        return None
    try:
        pixels = jpeg.reduced(scale)
    except JpegBlockError:
        return None
    reduced = pixels if pixels.ndim == 3 else cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR)
    if reduced.shape[:2] != (out_h, out_w):
        reduced = cv2.resize(reduced, (out_w, out_h), interpolation=cv2.INTER_AREA)
    return reduced, (jpeg.width, jpeg.height)


_CV_FLAGS = {
    ("RGB", 1): cv2.IMREAD_COLOR,  # BGR
    ("RGB", 2): cv2.IMREAD_REDUCED_COLOR_2,
    ("RGB", 4): cv2.IMREAD_REDUCED_COLOR_4,
    ("RGB", 8): cv2.IMREAD_REDUCED_COLOR_8,
    ("L", 1): cv2.IMREAD_GRAYSCALE,
    ("L", 2): cv2.IMREAD_REDUCED_GRAYSCALE_2,
    ("L", 4): cv2.IMREAD_REDUCED_GRAYSCALE_4,
    ("L", 8): cv2.IMREAD_REDUCED_GRAYSCALE_8,
}


def decode_bgr(stream: bytes, mode: str, scale: int) -> np.ndarray:
    """A JPEG-in-TIFF block (``workers.tiff_jpeg.Decoder``) through OpenCV's libjpeg-turbo: ``(h, w, 3)`` BGR for
    ``mode`` "RGB", ``(h, w)`` grey for "L", straight into NumPy (Pillow's copy out of its image was half the cost)."""
    pixels = cv2.imdecode(np.frombuffer(stream, np.uint8), _CV_FLAGS[(mode, scale)])
    if pixels is None:
        raise JpegBlockError("a block does not decode")
    return pixels


class WindowReader:
    """Windows of one TIFF photo, ``reader[r0:r1, c0:c1]`` -> (h, w, 3) uint8 BGR, safe across threads (each
    thread opens its own handle: a GDAL dataset must not be shared while it reads).

    An 8-bit JPEG-in-TIFF's windows are decoded from its blocks by libjpeg-turbo (``workers.tiff_jpeg``, blocks
    kept in a process-wide cache): the libjpeg 9 that rasterio's GDAL carries decoded them 6-8x slower (a 20000 x
    1800 frame: 0.8-1.2 s against 0.14 s), most of composing a strip and of its fine tie points. The same JPEG
    data; colour may differ by a few levels where the two libraries upsample the half-resolution chroma."""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self._local = threading.local()
        with rasterio.open(self.path) as src:
            self.shape = (src.height, src.width, 3)
            self._count, self._dtype = src.count, src.dtypes[0]
        self._jpeg = JpegBlocks.open(self.path, decode_bgr)

    def _dataset(self) -> rasterio.io.DatasetReader:
        src = getattr(self._local, "src", None)
        if src is None:
            src = self._local.src = rasterio.open(self.path)
        return src

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        if self._jpeg is not None and r1 > r0 and c1 > c0:
            try:
                pixels = self._jpeg.window(r0, r1, c0, c1)
                return pixels if pixels.ndim == 3 else cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR)
            except JpegBlockError:
                pass  # GDAL reads it, or says what is wrong
        window = Window(c0, r0, max(c1 - c0, 0), max(r1 - r0, 0))
        return _to_bgr8(self._dataset().read(indexes=_rgb_bands(self._count), window=window), self._dtype)


def read_photo_array(path: str | Path) -> np.ndarray | None:
    """The whole photo at its own bit depth: (H, W) for one band (a satellite panchromatic GeoTIFF), else
    (H, W, 3) BGR; uint8 or uint16. None when it cannot be decoded."""
    if not reads_by_window(path):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
        return None if image is None else np.ascontiguousarray(image)
    try:
        with rasterio.open(path) as src:
            bands = src.read(indexes=_rgb_bands(src.count))
    except rasterio.errors.RasterioError:
        return None
    if bands.dtype not in (np.uint8, np.uint16):
        return None
    return bands[0] if len(bands) == 1 else np.ascontiguousarray(np.moveaxis(bands[::-1], 0, 2))


def read_rpcs(path: str | Path) -> dict[str, Any] | None:
    """The RPC camera model a GeoTIFF carries (rasterio's ``RPC.to_dict()``), or None (none, or not a TIFF)."""
    if not reads_by_window(path):
        return None
    try:
        with rasterio.open(path) as src:
            rpcs = src.rpcs
    except rasterio.errors.RasterioError:
        return None
    return None if rpcs is None else dict(rpcs.to_dict())


def _rgb_bands(count: int) -> list[int]:
    """The bands read: R, G, B of a colour photo (an alpha or NIR band after them is left), or its one band."""
    return [1, 2, 3] if count >= 3 else [1]


def _to_bgr8(bands: np.ndarray, dtype: str) -> np.ndarray:
    """(bands, h, w) as read -> (h, w, 3) uint8 BGR; 16-bit data keeps its top 8 bits (full range)."""
    if dtype == "uint16":
        bands = (bands >> 8).astype(np.uint8)
    elif dtype != "uint8":
        raise ValueError(f"{dtype} photos are not supported (8- or 16-bit unsigned integers expected)")
    if len(bands) == 1:
        return np.ascontiguousarray(np.repeat(bands[0][..., None], 3, axis=2))
    return np.ascontiguousarray(np.moveaxis(bands[::-1], 0, 2))
