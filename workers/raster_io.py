"""Writing the mosaic: a tiled GeoTIFF filled window by window, then a Cloud-Optimized GeoTIFF; and small
single-band rasters (a DSM, a disparity map) as COGs in one go."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import cv2
import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.io import MemoryFile
from rasterio.shutil import copy as rio_copy
from rasterio.transform import Affine
from rasterio.windows import Window

from workers.workspace import atomic_path

BlockWriter = Callable[[Window, np.ndarray, np.ndarray], None]


@contextmanager
def open_block_writer(
    path: Path,
    width: int,
    height: int,
    crs: int | str | None,
    transform: list[float] | None,
    compress: str | None = "deflate",
) -> Iterator[BlockWriter]:
    """A 3-band uint8 tiled GeoTIFF with an internal mask; yields ``write(window, rgb, mask)``.

    ``compress`` None writes the tiles uncompressed: right for a scratch file that is read once into a
    COG (deflating it first cost 0.75 s of a 3 s COG on a 14 MP mosaic, for a file that is then deleted).

    ``transform`` (rasterio's affine a, b, c, d, e, f) places the pixels; ``crs`` names their CRS: an EPSG
    code, a WKT string (a local engineering frame such as a specimen's mm), or None for none.

    ``rgb`` is (h, w, 3) uint8 in R, G, B order and ``mask`` (h, w) bool, True where there is data.
    """
    profile = _tiled_profile(width, height, crs, transform, compress, count=3, dtype="uint8", photometric="RGB")
    profile.update(interleave="band", num_threads="ALL_CPUS")  # a scratch file: the COG is pixel-interleaved
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as dst:

        def write(window: Window, rgb: np.ndarray, mask: np.ndarray) -> None:
            # band by band from contiguous planes: rasterio copies a strided view slowly, and GDAL
            # interleaves pixels when the COG is made, on every core (half the time of this thread's writes)
            dst.write(np.ascontiguousarray(np.moveaxis(rgb, 2, 0)), window=window)
            dst.write_mask(mask.astype(np.uint8) * np.uint8(255), window=window)

        yield write


def _tiled_profile(
    width: int,
    height: int,
    crs: int | str | None,
    transform: list[float] | None,
    compress: str | None,
    **bands: Any,
) -> dict[str, Any]:
    """A tiled (COG_BLOCK_PX) GeoTIFF's rasterio profile, placed by ``transform`` in ``crs`` (an EPSG code or WKT;
    none without a transform), compressed unless ``compress`` is None; ``bands``: count, dtype and the like."""
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "tiled": True,
        "blockxsize": COG_BLOCK_PX,
        "blockysize": COG_BLOCK_PX,
        "BIGTIFF": "IF_SAFER",
        **bands,
    }
    if compress is not None:
        profile["compress"] = compress
    if compress == "zstd":
        profile["zstd_level"] = 1  # scratch rasters: the fastest level
    return {**profile, **placement(crs, transform)}


def placement(crs: int | str | None, transform: list[float] | None) -> dict[str, Any]:
    """The rasterio profile items that place a raster: ``transform`` (rasterio's a, b, c, d, e, f) in ``crs`` (an
    EPSG code or WKT; none without a transform); empty for a raster placed nowhere."""
    if transform is None:
        return {}
    if crs is None:
        return {"transform": Affine(*transform)}
    return {"transform": Affine(*transform), "crs": CRS.from_epsg(crs) if isinstance(crs, int) else CRS.from_wkt(crs)}


@dataclass(frozen=True)
class CogCodec:
    """How a COG's tiles are compressed: what :func:`copy_to_cog` asks GDAL's COG driver for, and what
    ``workers.cog_writer`` writes a gigapixel mosaic's bands with (their tiles are copied into its COG as they
    are, so both must agree)."""

    name: str  # deflate, zstd, lzw or jpeg
    predictor: int | None  # 2: horizontal differencing
    level: int | None  # deflate's or ZSTD's
    quality: int | None  # JPEG's


def cog_codec(compression: str, *, index: bool = False) -> CogCodec:
    """The codec of a mosaic's COG (``index``: of its frame index) asked to be ``compression``.

    An index is never JPEG (lossy: deflate instead) and has no horizontal differencing: it is runs of one value,
    which deflate packs as well without it (157 against 148 KiB on the Brighton strip, in 0.12 s instead of
    0.17 s). A mosaic's deflate/LZW/ZSTD tiles are differenced (its COG 21.0 -> 15.7 MiB, in the same time; the
    pixels read back are identical); JPEG is quality 90 (GDAL stores 3-band JPEG as YCbCr). Deflate and ZSTD at
    their fastest level: measured on the Brighton strip's 14 MP mosaic (overviews + COG, one run): deflate level
    6 (GDAL's default) 2.48 s 15.6 MiB, level 1 1.43 s 16.0 MiB; zstd 1 1.03 s 16.5 MiB, zstd 3 1.14 s 15.9 MiB;
    lzw 1.65 s 17.1 MiB; jpeg 90 1.98 s 2.8 MiB (lossy); none 0.57 s 63.8 MiB. Deflate stays the default: every
    TIFF reader knows it, not every one ZSTD."""
    name = "deflate" if index and compression == "jpeg" else compression
    return CogCodec(
        name,
        predictor=None if index or name == "jpeg" else 2,
        level=1 if name in ("deflate", "zstd") else None,
        quality=90 if name == "jpeg" else None,
    )


def translate_to_cog(src: Path, dst: Path, compression: str, tags: Mapping[str, str] | None = None) -> None:
    """Copy the scratch GeoTIFF ``src`` (as :func:`open_block_writer` writes it) into a COG at ``dst`` with
    overviews and its mask, atomically.

    ``tags`` (GDAL metadata items such as ``TIFFTAG_IMAGEDESCRIPTION``) become TIFF tags; given any,
    ``TIFFTAG_SOFTWARE`` ("Fotoskhema <version>") and ``TIFFTAG_DATETIME`` (now, UTC) are added unless named.
    The overviews are averaged under the mask by :class:`OverviewPyramid` (beside ``src``, removed after), then
    GDAL's COG driver copies every level and compresses it on all cores in one pass. Memory: a band of rows.
    """
    _translate(src, dst, compression, None if tags is None else {**provenance_tags(), **tags}, index=False)


def translate_index_to_cog(src: Path, dst: Path, compression: str, tags: Mapping[str, str] | None = None) -> None:
    """:func:`translate_to_cog` for a frame index (``src`` as :func:`open_index_writer` writes it; 0: none): nodata
    0, overviews by nearest neighbour (a frame number is not averaged), never JPEG (deflate instead)."""
    _translate(src, dst, compression, {**provenance_tags(), **(tags or {})}, index=True)


def _translate(src: Path, dst: Path, compression: str, tags: Mapping[str, str] | None, *, index: bool) -> None:
    """The overviews of ``src`` by :class:`OverviewPyramid`, band by band, then ``src`` and them (through a VRT)
    copied to a COG at ``dst`` with ``tags`` added to ``src``'s own."""
    levels_dir = src.with_name(src.name + ".levels")
    try:
        with rasterio.open(src) as scratch:
            width, height, crs, transform = scratch.width, scratch.height, scratch.crs, scratch.transform
            metadata = {**scratch.tags(), **(tags or {})}
        levels = _pyramid_paths(levels_dir, width, height)
        with (
            # each block is read once and written once: GDAL's cache (5 % of RAM unless set) would keep the whole
            # scratch (Brighton: +100 MiB, the job's peak)
            rasterio.Env(GDAL_CACHEMAX=STREAM_CACHE_MIB),
            OverviewPyramid(levels, width, height, index=index) as pyramid,
            (open_index_reader if index else open_band_reader)(src) as read,
        ):
            for y in range(0, height, COG_BLOCK_PX):
                rows = read(Window(0, y, width, min(COG_BLOCK_PX, height - y)))
                pyramid.add(*((rows,) if index else rows))
        placed = transform if crs is not None or not transform.is_identity else None
        vrt = _vrt_with_overviews(levels_dir / "cog.vrt", src, width, height, crs, placed, levels, metadata, index)
        copy_to_cog(vrt, dst, compression, index=index)
    finally:
        shutil.rmtree(levels_dir, ignore_errors=True)


def copy_to_cog(src: Path, dst: Path, compression: str, *, index: bool = False) -> None:
    """GDAL's COG driver copies ``src`` (its overviews, if any, as they are) to ``dst``, atomically, compressing
    on all cores with :func:`cog_codec`'s codec (``index``: a frame index's, and overviews by nearest neighbour
    when ``src`` has none)."""
    codec = cog_codec(compression, index=index)
    options: dict[str, Any] = {
        "compress": codec.name.upper(),
        "blocksize": COG_BLOCK_PX,
        "num_threads": "ALL_CPUS",
        "bigtiff": "IF_SAFER",  # past 4 GB (a gigapixel strip): BigTIFF
        "overviews": "AUTO",  # the source's, else built (nearest for an index)
        # tiles with no data at all are not stored (readers see zeros, masked): a rotated strip's bounding box is
        # half empty (Brighton: 23 of 64 tiles; 13 % of the COG's time)
        "sparse_ok": True,
    }
    if index:
        options["overview_resampling"] = "NEAREST"
    if codec.predictor is not None:
        options["predictor"] = codec.predictor
    if codec.level is not None:
        options["level"] = codec.level
    if codec.quality is not None:
        options["quality"] = codec.quality
    with (
        rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, GDAL_CACHEMAX=256, GDAL_NUM_THREADS="ALL_CPUS"),
        atomic_path(dst) as tmp,
    ):
        rio_copy(str(src), str(tmp), driver="COG", **options)


def _pyramid_paths(work_dir: Path, width: int, height: int) -> list[Path]:
    """The overview level files of a ``width`` x ``height`` mosaic in ``work_dir`` (made), coarsest last."""
    work_dir.mkdir(parents=True, exist_ok=True)
    return [work_dir / f"overview_{factor}.tif" for factor in overview_levels(width, height)]


IndexWriter = Callable[[Window, np.ndarray], None]


@contextmanager
def open_index_writer(
    path: Path,
    width: int,
    height: int,
    crs: int | str | None,
    transform: list[float] | None,
    compress: str | None = "deflate",
) -> Iterator[IndexWriter]:
    """A 1-band uint16 tiled GeoTIFF with nodata 0 (a mosaic's frame index); yields ``write(window, index)``,
    ``index`` (h, w) uint16. Placed as :func:`open_block_writer` places the mosaic."""
    profile = _tiled_profile(width, height, crs, transform, compress, count=1, dtype="uint16", nodata=0)
    with rasterio.open(path, "w", **profile) as dst:

        def write(window: Window, index: np.ndarray) -> None:
            dst.write(np.ascontiguousarray(index, np.uint16), 1, window=window)

        yield write


@contextmanager
def open_index_reader(path: Path) -> Iterator[Callable[[Window], np.ndarray]]:
    """``read(window)`` -> (h, w) uint16 of a raster :func:`open_index_writer` wrote."""
    with rasterio.open(path) as src:
        yield lambda window: src.read(1, window=window)


def write_array_cog(
    path: Path,
    band: np.ndarray,
    *,
    transform: tuple[float, ...] | None = None,
    epsg: int | None = None,
    nodata: float | None = None,
    resampling: str = "average",
    compression: str = "deflate",
    description: str = "",
) -> None:
    """One (H, W) band (float32 or uint8) as a COG at ``path``, atomically, built from an in-memory GeoTIFF.

    ``transform`` (rasterio's a, b, c, d, e, f) and ``epsg`` place it, or neither (a raster in a photo's
    pixels); ``nodata`` marks empty cells (NaN values become it); ``resampling`` builds the overviews
    ("average" for heights, "nearest" for class codes). Floating-point data is compressed with predictor 3.
    Meant for rasters that fit in memory: a DSM or disparity map of a stereo pair.
    """
    data = np.asarray(band)
    if nodata is not None and np.issubdtype(data.dtype, np.floating):
        data = np.where(np.isfinite(data), data, nodata).astype(data.dtype)
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": data.shape[1],
        "height": data.shape[0],
        "count": 1,
        "dtype": str(data.dtype),
        "tiled": True,
        "blockxsize": COG_BLOCK_PX,
        "blockysize": COG_BLOCK_PX,
    }
    if transform is not None:
        profile["transform"] = Affine(*transform)
        if epsg is not None:
            profile["crs"] = CRS.from_epsg(epsg)
    if nodata is not None:
        profile["nodata"] = nodata
    options = {
        "compress": compression.upper(),
        "blocksize": COG_BLOCK_PX,
        "predictor": 3 if np.issubdtype(data.dtype, np.floating) else 2,
        "overview_resampling": resampling.upper(),
        "num_threads": "ALL_CPUS",
    }
    tags = {**provenance_tags(), **({"TIFFTAG_IMAGEDESCRIPTION": description} if description else {})}
    with rasterio.Env(GDAL_NUM_THREADS="ALL_CPUS"), MemoryFile() as memory:
        with memory.open(**profile) as scratch:
            scratch.write(data, 1)
            scratch.update_tags(**tags)
        with memory.open() as scratch, atomic_path(path) as tmp:
            rio_copy(scratch, str(tmp), driver="COG", **options)


def write_rgb_cog(
    path: Path,
    scratch: Path,
    rgb: np.ndarray,
    mask: np.ndarray,
    *,
    crs: int | None = None,
    transform: tuple[float, ...] | None = None,
    compression: str = "deflate",
) -> None:
    """An (H, W, 3) uint8 RGB picture with its (H, W) bool mask as a COG at ``path`` (through the scratch
    GeoTIFF ``scratch``, removed after), placed by ``transform`` and ``crs`` or in its own pixels."""
    height, width = mask.shape
    scratch.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open_block_writer(scratch, width, height, crs, list(transform) if transform else None, None) as write:
            write(Window(0, 0, width, height), rgb, mask)
        translate_to_cog(scratch, path, compression, tags={})
    finally:
        scratch.unlink(missing_ok=True)


DSM_NODATA = -9999.0  # dsm.tif's nodata value


def write_dsm(
    paths: tuple[Path, Path, Path, Path],
    height: np.ndarray,
    state: np.ndarray,
    relief: np.ndarray,
    *,
    transform: tuple[float, ...],
    epsg: int,
    compression: str,
    description: str,
) -> None:
    """A DSM's three COGs: ``paths`` = (dsm.tif, dsm_mask.tif, the shaded relief's view COG, its scratch file).
    ``height`` (H, W) float32 m, NaN where none (written as ``DSM_NODATA``); ``state`` (H, W) uint8 per cell,
    0 no data, 1 measured, 2 filled; ``relief`` (H, W, 3) uint8, the picture the viewer tiles."""
    dsm, mask, view, scratch = paths
    write_array_cog(
        dsm,
        height.astype(np.float32),
        transform=transform,
        epsg=epsg,
        nodata=DSM_NODATA,
        compression=compression,
        description=description,
    )
    write_array_cog(
        mask,
        state.astype(np.uint8),
        transform=transform,
        epsg=epsg,
        nodata=0,
        resampling="nearest",
        compression=compression,
        description="per DSM cell: 0 no data, 1 measured, 2 filled",
    )
    write_rgb_cog(view, scratch, relief, state > 0, crs=epsg, transform=transform, compression=compression)


def provenance_tags() -> dict[str, str]:
    """``TIFFTAG_SOFTWARE`` and ``TIFFTAG_DATETIME`` of a raster written now."""
    try:
        release = version("fotoskhema")
    except PackageNotFoundError:  # run from a source tree that is not installed
        release = "unknown"
    now = datetime.now(UTC).strftime("%Y:%m:%d %H:%M:%S")
    return {"TIFFTAG_SOFTWARE": f"Fotoskhema {release}", "TIFFTAG_DATETIME": now}


COG_BLOCK_PX = 512  # COG tile edge, px; also where the overview pyramid stops


def overview_levels(width: int, height: int, block_px: int = COG_BLOCK_PX) -> list[int]:
    """Decimation factors 2, 4, 8, ... until the coarsest level fits in one ``block_px`` tile."""
    levels: list[int] = []
    factor = 1
    while max(width, height) / factor > block_px:
        factor *= 2
        levels.append(factor)
    return levels


BandRead = Callable[[Window], tuple[np.ndarray, np.ndarray]]


@contextmanager
def open_band_reader(path: Path) -> Iterator[BandRead]:
    """``read(window)`` -> (h, w, 3) uint8 RGB and (h, w) bool mask of a raster :func:`open_block_writer` wrote,
    as ``write`` took them."""
    with rasterio.open(path) as src:

        def read(window: Window) -> tuple[np.ndarray, np.ndarray]:
            return np.moveaxis(src.read(window=window), 0, 2), src.read_masks(1, window=window) > 0

        yield read


WindowRead = Callable[[int, int, int, int], tuple[np.ndarray, np.ndarray]]


@contextmanager
def open_window_reader(path: Path) -> Iterator[WindowRead]:
    """``read(x, y, w, h)`` -> (h', w', 3) uint8 RGB and (h', w') bool coverage of a mosaic's window, clipped
    to the raster (so smaller than asked at its edges)."""
    with rasterio.open(path) as src:

        def read(x: int, y: int, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
            x0, y0 = max(x, 0), max(y, 0)
            x1, y1 = min(x + w, src.width), min(y + h, src.height)
            if x1 <= x0 or y1 <= y0:
                return np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), bool)
            window = Window(x0, y0, x1 - x0, y1 - y0)
            return np.moveaxis(src.read(window=window), 0, 2), src.read_masks(1, window=window) > 0

        yield read


# -- overviews averaged under the mask, level by level, and the VRT that hands them to GDAL's COG driver -------

STREAM_CACHE_MIB = 32  # GDAL's block cache where each block is read or written once: the pyramid, the scratch copy
OVERVIEW_CHUNK_PX = 8192  # columns averaged at once (even): temporaries of 8192 x a band's rows, never its width


def masked_half(rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next overview level of (h, w, 3) uint8 ``rgb`` under its (h, w) bool ``mask``: each pixel is the mean of
    the (up to four) pixels of its 2 x 2 cell that have data, rounded; covered where any has. An odd edge is
    padded with no-data. GDAL's masked "average" gives these pixels at the first level (and averages the mosaic
    itself for every coarser one), but took 0.25 s of a 14 MP mosaic's 0.55 s COG; this takes 0.02 s: whole cells
    (nearly all) are averaged by OpenCV, only cells the mask cuts one by one. Works on colour planes: ``rgb`` as a
    view of (3, h, w) planes (what GDAL reads) costs no copy, and the result is such a view too."""
    planes = np.moveaxis(rgb, 2, 0)
    height, width = mask.shape
    if height % 2 or width % 2:
        pad = ((0, height % 2), (0, width % 2))
        planes, mask = np.pad(planes, ((0, 0), *pad)), np.pad(mask, pad)
    cells = [mask[i::2, j::2] for i in (0, 1) for j in (0, 1)]
    count = cells[0].astype(np.uint8) + cells[1] + cells[2] + cells[3]
    covered = count > 0
    keep = covered.view(np.uint8)
    size = (mask.shape[1] // 2, mask.shape[0] // 2)
    half = np.zeros((3, size[1], size[0]), np.uint8)  # bitwise_and leaves uncovered pixels as they are
    for c in range(3):  # (numpy's half[~covered] = 0 took 50 ms on a 14 MP mosaic's first level)
        plane = cv2.resize(np.ascontiguousarray(planes[c]), size, interpolation=cv2.INTER_AREA)
        cv2.bitwise_and(plane, plane, dst=half[c], mask=keep)
    cut = cv2.findNonZero(cv2.inRange(count, 1, 3))
    if cut is not None:  # cells the mask cuts: the mean of the pixels with data
        cols, rows = cut.reshape(-1, 2).T
        total = np.zeros((3, rows.size), np.int32)
        for (i, j), inside in zip(((0, 0), (0, 1), (1, 0), (1, 1)), cells, strict=True):
            total += planes[:, 2 * rows + i, 2 * cols + j].astype(np.int32) * inside[rows, cols]
        n = count[rows, cols].astype(np.int32)
        half[:, rows, cols] = ((2 * total + n) // (2 * n)).astype(np.uint8)
    return np.moveaxis(half, 0, 2), covered


class OverviewPyramid:
    """The overview levels of a mosaic fed to it band by band, top to bottom (:meth:`add`), each level written
    as its rows are known into an uncompressed tiled GeoTIFF of ``paths`` (level 2, 4, 8, ...): RGB + mask
    averaged under the mask (:func:`masked_half`), or with ``index`` a frame index (uint16, nodata 0) by nearest
    neighbour (a frame number is not averaged). Memory: one band and a row carried per level, whatever the
    mosaic's size. Each level is averaged from the one above: where the mask cuts a cell, from level 4 on, a mean
    of means (``workers.cog_writer``, a gigapixel mosaic's, carries sums and counts down instead: the mean of the
    covered pixels; the two differ only along the coverage's edge, by a grey level or two)."""

    def __init__(self, paths: list[Path], width: int, height: int, *, index: bool = False) -> None:
        self.sizes = [(-(-width // 2 ** (n + 1)), -(-height // 2 ** (n + 1))) for n in range(len(paths))]
        self.heights = [height] + [h for _, h in self.sizes]
        self.rows_in = [0] * (len(paths) + 1)  # rows of each level received so far
        self.carry: list[tuple[np.ndarray, ...] | None] = [None] * (len(paths) + 1)
        self.index = index
        self._paths = paths
        self._stack = ExitStack()
        self.writers: list[Callable[..., None]] = []

    def __enter__(self) -> OverviewPyramid:
        open_writer: Callable[..., Any] = open_index_writer if self.index else open_block_writer
        for path, (w, h) in zip(self._paths, self.sizes, strict=True):
            self.writers.append(self._stack.enter_context(open_writer(path, w, h, None, None, compress=None)))
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def add(self, *arrays: np.ndarray, level: int = 0) -> None:
        """The next rows of ``level`` (0: the mosaic): (h, w, 3) uint8 RGB and (h, w) bool mask, or with
        ``index`` one (h, w) uint16."""
        self.rows_in[level] += arrays[0].shape[0]
        if level == len(self.writers):
            return
        held = self.carry[level]
        if held is not None:  # the odd row left from the rows before
            arrays = tuple(np.concatenate([a, b]) for a, b in zip(held, arrays, strict=True))
            self.carry[level] = None
        rows = arrays[0].shape[0]
        if rows % 2 and self.rows_in[level] < self.heights[level]:  # not the last rows: keep the odd one
            self.carry[level] = tuple(a[-1:].copy() for a in arrays)
            arrays, rows = tuple(a[:-1] for a in arrays), rows - 1
        if rows == 0:
            return
        if self.index:
            half: tuple[np.ndarray, ...] = (np.ascontiguousarray(arrays[0][::2, ::2]),)
        else:
            parts = [masked_half(arrays[0][:, x : x + OVERVIEW_CHUNK_PX], arrays[1][:, x : x + OVERVIEW_CHUNK_PX])
                     for x in range(0, arrays[0].shape[1], OVERVIEW_CHUNK_PX)]  # fmt: skip
            half = parts[0] if len(parts) == 1 else tuple(np.concatenate([p[n] for p in parts], axis=1) for n in (0, 1))
        y = self.rows_in[level + 1]
        self.writers[level](Window(0, y, half[0].shape[1], half[0].shape[0]), *half)
        self.add(*half, level=level + 1)


def _vrt_with_overviews(
    path: Path,
    src: Path,
    width: int,
    height: int,
    crs: CRS | None,
    transform: Affine | None,
    overviews: list[Path],
    tags: Mapping[str, str],
    index: bool,
) -> Path:
    """A VRT at ``path`` of the GeoTIFF ``src`` (RGB with an internal mask, or with ``index`` one uint16 band,
    nodata 0) whose overviews are the files ``overviews`` (level 2, 4, ...: the same layout) and whose metadata
    is ``tags``, which the COG driver writes as TIFF tags."""
    root = ET.Element("VRTDataset", rasterXSize=str(width), rasterYSize=str(height))
    if transform is not None:
        if crs is not None:
            ET.SubElement(root, "SRS").text = crs.to_wkt()
        ET.SubElement(root, "GeoTransform").text = ", ".join(repr(v) for v in transform.to_gdal())
    if tags:
        metadata = ET.SubElement(root, "Metadata")
        for key, value in tags.items():
            ET.SubElement(metadata, "MDI", key=key).text = value

    def band(parent: ET.Element, source_band: str, number: int | None) -> None:
        node = ET.SubElement(parent, "VRTRasterBand", dataType="UInt16" if index else "Byte")
        if number is not None:
            node.set("band", str(number))
            if not index:
                ET.SubElement(node, "ColorInterp").text = ("Red", "Green", "Blue")[number - 1]
        if index:
            ET.SubElement(node, "NoDataValue").text = "0"
        for file in [src, *overviews]:
            source = ET.SubElement(node, "SimpleSource" if file == src else "Overview")
            ET.SubElement(source, "SourceFilename", relativeToVRT="0").text = str(file.resolve())
            ET.SubElement(source, "SourceBand").text = source_band

    for n in range(1, 2 if index else 4):
        band(root, str(n), n)
    if not index:
        band(ET.SubElement(root, "MaskBand"), "mask,1", None)
    ET.ElementTree(root).write(path)
    return path
