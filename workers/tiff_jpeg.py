"""The blocks of a JPEG-in-TIFF decoded by libjpeg(-turbo) itself: whole at 1/2, 1/4 or 1/8 of their size by the
DCT, or by window at full size.

GDAL decodes each JPEG block of a TIFF whole, whatever size is asked of it (a 135 MP aerial frame costs the same
1.3-1.4 s at any reduction), and rasterio's wheel carries libjpeg 9, 6-8x slower than the libjpeg-turbo in Pillow
and OpenCV. So the upload check, the previews and the working copies of aerial frames, and the windows compose
and the fine tie points read, take the blocks' coded bytes themselves (where they lie and the tables they share
come from GDAL's TIFF metadata: ``BLOCK_OFFSET_x_y``, ``BLOCK_SIZE_x_y``, ``JPEGTABLES``) and decode them: at 1/8
a block's pixel is its 8 x 8 px mean (the DC term), within a level or two of GDAL's area average (the DC's
quantisation); at full size the same pixels as libtiff with libjpeg-turbo. Every block's entropy-coded data is
decoded in full, so a block missing or cut short is found as a full decode finds it, and left to GDAL. NumPy,
Pillow and (lazily) rasterio: the API's upload check uses it, with Pillow's decoder; the workers pass OpenCV's.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np
from PIL import JpegImagePlugin

if TYPE_CHECKING:
    from rasterio.io import DatasetReader

SCALES = (8, 4, 2)  # libjpeg's DCT scalings used here, the coarsest first


class JpegBlockError(Exception):
    """A block that cannot be decoded here (not stored, cut short, not the JPEG stream expected): the caller reads
    the file through GDAL instead, which says what is wrong with it."""


class BlockCache:
    """Decoded blocks, least recently used dropped past ``max_bytes``; shared by a process's threads (two threads
    that miss the same block both decode it, harmlessly). A window's neighbours read most of its blocks again."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes, self.bytes = max_bytes, 0
        self._blocks: OrderedDict[Hashable, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], np.ndarray]) -> np.ndarray:
        with self._lock:
            if (found := self._blocks.get(key)) is not None:
                self._blocks.move_to_end(key)
                return found
        made = make()
        with self._lock:
            if key not in self._blocks:
                self._blocks[key] = made
                self.bytes += made.nbytes
                while self.bytes > self.max_bytes and len(self._blocks) > 1:
                    self.bytes -= self._blocks.popitem(last=False)[1].nbytes
        return made

    def clear(self) -> None:
        with self._lock:
            self._blocks.clear()
            self.bytes = 0


# the blocks windows are read from, per process: as much as GDAL's block cache had (workers/__init__), which these
# reads no longer fill
BLOCK_CACHE = BlockCache(512 * 2**20)


Decoder = Callable[[bytes, str, int], np.ndarray]  # (JPEG stream, "RGB" or "L", DCT scale) -> pixels


def decode_pillow(stream: bytes, mode: str, scale: int) -> np.ndarray:
    """One block's JPEG ``stream`` decoded at 1/``scale`` by Pillow's libjpeg(-turbo): ``(h, w, 3)`` RGB (``mode``
    "RGB") or ``(h, w)`` grey ("L")."""
    try:
        with JpegImagePlugin.JpegImageFile(io.BytesIO(stream)) as img:
            full = img.size
            img.draft(mode, (-(-full[0] // scale), -(-full[1] // scale)))
            if img.mode != mode or img.size != (-(-full[0] // scale), -(-full[1] // scale)):
                raise JpegBlockError(f"a {img.mode} block of {full[0]} x {full[1]} px, not {mode} at 1/{scale}")
            return np.asarray(img)
    except (OSError, SyntaxError, ValueError) as exc:
        raise JpegBlockError(f"a block does not decode ({exc})") from None


class JpegBlocks:
    """The blocks (tiles, or strips) of an 8-bit, pixel-interleaved JPEG-in-TIFF of one band or three (RGB, stored
    as YCbCr or RGB); :meth:`open` answers None for any other TIFF. Pixels come as ``decode`` gives them: RGB from
    :func:`decode_pillow` (the API's, no OpenCV), BGR from the workers' OpenCV decoder (``workers.photo_io``)."""

    def __init__(self, path: Path, src: DatasetReader, decode: Decoder) -> None:
        self.path, self._decode = path, decode
        self.width, self.height, self.bands = src.width, src.height, src.count
        self.block_h, self.block_w = src.block_shapes[0]
        item = src.get_tag_item
        tables = item("JPEGTABLES", "TIFF", bidx=1)
        # the tables' stream without its end-of-image marker, put in front of each block's without its start
        self._tables = bytes.fromhex(tables)[:-2] if tables else b""
        self.rows, self.cols = -(-self.height // self.block_h), -(-self.width // self.block_w)
        self._where = np.array(  # (rows, cols, 2): each block's offset and size in the file, 0 where not stored
            [
                [
                    [int(item(f"BLOCK_{what}_{i}_{j}", "TIFF", bidx=1) or 0) for what in ("OFFSET", "SIZE")]
                    for i in range(self.cols)
                ]
                for j in range(self.rows)
            ],
            np.int64,
        ).reshape(self.rows, self.cols, 2)
        stat = path.stat()
        self._key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)  # the cache's: the same file, unchanged
        self._mode = "RGB" if self.bands == 3 else "L"

    @classmethod
    def open(cls, path: str | Path, decode: Decoder = decode_pillow) -> JpegBlocks | None:
        """The blocks of the TIFF at ``path``, decoded by ``decode``; None when it is not a JPEG-in-TIFF this class
        decodes."""
        import rasterio  # GDAL: only for TIFF photos

        try:
            with rasterio.open(path) as src:
                jpeg = src.compression is not None and src.compression.name == "jpeg"
                interleaved = src.count == 1 or (src.interleaving is not None and src.interleaving.name == "pixel")
                if not jpeg or src.dtypes[0] != "uint8" or src.count not in (1, 3) or not interleaved:
                    return None
                return cls(Path(path), src, decode)
        except (rasterio.errors.RasterioError, OSError):
            return None

    def scale_for(self, factor: float) -> int:
        """The coarsest DCT scale (8, 4 or 2) at most ``factor`` that divides the width and the height (every
        reduced pixel is then a whole square of source pixels), else 1: no scaled decode."""
        return next((s for s in SCALES if s <= factor and self.width % s == 0 and self.height % s == 0), 1)

    def _stream(self, f: BinaryIO, j: int, i: int) -> bytes:
        """Block (row ``j``, column ``i``)'s JPEG stream, the shared tables spliced in."""
        offset, size = (int(v) for v in self._where[j, i])
        if offset == 0 or size == 0:  # a sparse block: GDAL reads it as zeros
            raise JpegBlockError(f"block {i},{j} is not stored")
        f.seek(offset)
        data = f.read(size)
        if len(data) != size or data[:2] != b"\xff\xd8":
            raise JpegBlockError(f"block {i},{j} is cut short or not a JPEG stream")
        return self._tables + data[2:] if self._tables else data

    def _decoded(self, f: BinaryIO, j: int, i: int, scale: int) -> np.ndarray:
        """Block (``j``, ``i``) at 1/``scale``, cut to the image."""
        row, col = j * self.block_h // scale, i * self.block_w // scale
        h = min(self.block_h // scale, self.height // scale - row)
        w = min(self.block_w // scale, self.width // scale - col)
        pixels = self._decode(self._stream(f, j, i), self._mode, scale)
        if pixels.shape[0] < h or pixels.shape[1] < w:
            raise JpegBlockError(f"block {i},{j} decodes to {pixels.shape[1]} x {pixels.shape[0]} px, not {w} x {h}")
        return pixels[:h, :w]

    def block_rows(self, scale: int) -> Iterator[tuple[int, np.ndarray]]:
        """Each row of blocks decoded at 1/``scale`` (one of :data:`SCALES`, dividing the width and height), top to
        bottom, as ``(row, pixels)``: its first row in the reduced image and its ``(h, W / scale, 3)`` RGB or
        ``(h, W / scale)`` grey uint8 (a row of 256 px tiles of a 75000 px frame at 1/8: 0.9 MB). Raises
        :class:`JpegBlockError`."""
        if scale not in SCALES or self.width % scale or self.height % scale:
            raise ValueError(f"scale {scale} is not one of {SCALES} dividing {self.width} x {self.height}")
        channels = (3,) if self.bands == 3 else ()
        with open(self.path, "rb") as f:
            for j in range(self.rows):
                row = j * self.block_h // scale
                out = np.empty(
                    (min(self.block_h // scale, self.height // scale - row), self.width // scale, *channels), np.uint8
                )
                for i in range(self.cols):
                    col = i * self.block_w // scale
                    pixels = self._decoded(f, j, i, scale)
                    out[:, col : col + pixels.shape[1]] = pixels
                yield row, out

    def reduced(self, scale: int) -> np.ndarray:
        """The whole image at 1/``scale`` (:meth:`block_rows`): ``(H/scale, W/scale, 3)`` RGB or ``(.., ..)`` grey."""
        return np.concatenate([pixels for _, pixels in self.block_rows(scale)])

    def window(self, r0: int, r1: int, c0: int, c1: int, cache: BlockCache = BLOCK_CACHE) -> np.ndarray:
        """Rows ``r0:r1``, columns ``c0:c1`` (within the image) at full size, ``(h, w, 3)`` RGB or ``(h, w)`` grey,
        from the blocks they touch, each decoded once while ``cache`` keeps it. Raises :class:`JpegBlockError`."""
        out = np.empty((r1 - r0, c1 - c0, *((3,) if self.bands == 3 else ())), np.uint8)
        if out.size == 0:
            return out
        with open(self.path, "rb") as f:
            for j in range(r0 // self.block_h, (r1 - 1) // self.block_h + 1):
                for i in range(c0 // self.block_w, (c1 - 1) // self.block_w + 1):
                    # keyed by the decoder too: Pillow's pixels are RGB, OpenCV's BGR
                    block = cache.get((self._key, self._decode, j, i), partial(self._decoded, f, j, i, 1))
                    top, left = j * self.block_h, i * self.block_w
                    y0, y1 = max(r0, top), min(r1, top + block.shape[0])
                    x0, x1 = max(c0, left), min(c1, left + block.shape[1])
                    out[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0] = block[y0 - top : y1 - top, x0 - left : x1 - left]
        return out
