"""The blocks of a JPEG-in-TIFF decoded at 1/2, 1/4 or 1/8 of their size by libjpeg's DCT scaling.

GDAL decodes each JPEG block of a TIFF whole, whatever size is asked of it: a 135 MP aerial frame costs the same
1.3-1.4 s at any reduction. libjpeg, asked for a scaled decode, inverse-transforms only the coarse coefficients;
at 1/8 a block's pixel is its 8 x 8 px mean (the DC term). So the upload check, the previews and the working copies
of aerial frames read the blocks' coded bytes themselves (where they lie and the tables they share come from GDAL's
TIFF metadata: ``BLOCK_OFFSET_x_y``, ``BLOCK_SIZE_x_y``, ``JPEGTABLES``) and let Pillow's libjpeg decode them scaled:
an 8x reduced copy of a 75000 x 1800 frame in a fifth of GDAL's time, within a level or two of GDAL's area average
(the DC's quantisation). Every block's entropy-coded data is still decoded in full, so a block missing or cut
short is found as a full decode finds it. NumPy, Pillow and (lazily) rasterio: the API's upload check uses it.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import JpegImagePlugin

if TYPE_CHECKING:
    from rasterio.io import DatasetReader

SCALES = (8, 4, 2)  # libjpeg's DCT scalings used here, the coarsest first


class JpegBlockError(Exception):
    """A block that cannot be decoded here (not stored, cut short, not the JPEG stream expected): the caller reads
    the file through GDAL instead, which says what is wrong with it."""


class JpegBlocks:
    """The blocks (tiles, or strips) of an 8-bit, pixel-interleaved JPEG-in-TIFF of one band or three (RGB, stored
    as YCbCr or RGB); :meth:`open` answers None for any other TIFF."""

    def __init__(self, path: Path, src: DatasetReader) -> None:
        self.path = path
        self.width, self.height, self.bands = src.width, src.height, src.count
        self.block_h, self.block_w = src.block_shapes[0]
        item = src.get_tag_item
        tables = item("JPEGTABLES", "TIFF", bidx=1)
        # the tables' stream without its end-of-image marker, put in front of each block's without its start
        self._tables = bytes.fromhex(tables)[:-2] if tables else b""
        rows, cols = -(-self.height // self.block_h), -(-self.width // self.block_w)
        self._blocks = [
            (j, i, item(f"BLOCK_OFFSET_{i}_{j}", "TIFF", bidx=1), item(f"BLOCK_SIZE_{i}_{j}", "TIFF", bidx=1))
            for j in range(rows)
            for i in range(cols)
        ]

    @classmethod
    def open(cls, path: str | Path) -> JpegBlocks | None:
        """The blocks of the TIFF at ``path``, or None when it is not a JPEG-in-TIFF this class decodes."""
        import rasterio  # GDAL: only for TIFF photos

        try:
            with rasterio.open(path) as src:
                jpeg = src.compression is not None and src.compression.name == "jpeg"
                interleaved = src.count == 1 or (src.interleaving is not None and src.interleaving.name == "pixel")
                if not jpeg or src.dtypes[0] != "uint8" or src.count not in (1, 3) or not interleaved:
                    return None
                return cls(Path(path), src)
        except rasterio.errors.RasterioError:
            return None

    def scale_for(self, factor: float) -> int:
        """The coarsest DCT scale (8, 4 or 2) at most ``factor`` that divides the width and the height (every
        reduced pixel is then a whole square of source pixels), else 1: no scaled decode."""
        return next((s for s in SCALES if s <= factor and self.width % s == 0 and self.height % s == 0), 1)

    def blocks(self, scale: int) -> Iterator[tuple[int, int, np.ndarray]]:
        """Each block decoded at 1/``scale`` (one of :data:`SCALES`, dividing the width and height), in file order,
        as ``(row, col, pixels)``: its top-left in the reduced image and its ``(h, w, 3)`` RGB or ``(h, w)`` grey
        uint8 cut to the image. Raises :class:`JpegBlockError`."""
        if scale not in SCALES or self.width % scale or self.height % scale:
            raise ValueError(f"scale {scale} is not one of {SCALES} dividing {self.width} x {self.height}")
        mode = "RGB" if self.bands == 3 else "L"
        size_h, size_w = self.height // scale, self.width // scale
        with open(self.path, "rb") as f:
            for j, i, offset, size in self._blocks:
                if not offset or not size or int(offset) == 0:  # a sparse block: GDAL reads it as zeros
                    raise JpegBlockError(f"block {i},{j} is not stored")
                f.seek(int(offset))
                data = f.read(int(size))
                if len(data) != int(size) or data[:2] != b"\xff\xd8":
                    raise JpegBlockError(f"block {i},{j} is cut short or not a JPEG stream")
                row, col = j * self.block_h // scale, i * self.block_w // scale
                h, w = min(self.block_h // scale, size_h - row), min(self.block_w // scale, size_w - col)
                yield row, col, _decode(self._tables + data[2:] if self._tables else data, mode, scale)[:h, :w]

    def reduced(self, scale: int) -> np.ndarray:
        """The whole image at 1/``scale`` from :meth:`blocks`: ``(H/scale, W/scale, 3)`` RGB or ``(.., ..)`` grey."""
        out = np.empty((self.height // scale, self.width // scale, *((3,) if self.bands == 3 else ())), np.uint8)
        for row, col, pixels in self.blocks(scale):
            out[row : row + pixels.shape[0], col : col + pixels.shape[1]] = pixels
        return out


def _decode(stream: bytes, mode: str, scale: int) -> np.ndarray:
    """One block's JPEG ``stream`` decoded at 1/``scale`` into ``mode``'s pixels."""
    try:
        with JpegImagePlugin.JpegImageFile(io.BytesIO(stream)) as img:
            full = img.size
            img.draft(mode, (-(-full[0] // scale), -(-full[1] // scale)))
            if img.mode != mode or img.size != (-(-full[0] // scale), -(-full[1] // scale)):
                raise JpegBlockError(f"a {img.mode} block of {full[0]} x {full[1]} px, not {mode} at 1/{scale}")
            return np.asarray(img)
    except (OSError, SyntaxError, ValueError) as exc:
        raise JpegBlockError(f"a block does not decode ({exc})") from None
