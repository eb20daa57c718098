"""Writing the mosaic: a tiled GeoTIFF filled window by window, then a Cloud-Optimized GeoTIFF; and small
single-band rasters (a DSM, a disparity map) as COGs in one go."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
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
    if transform is not None:
        profile["transform"] = Affine(*transform)
        if crs is not None:
            profile["crs"] = CRS.from_epsg(crs) if isinstance(crs, int) else CRS.from_wkt(crs)
    return profile


def translate_to_cog(src: Path, dst: Path, compression: str, tags: Mapping[str, str] | None = None) -> None:
    """Copy the scratch GeoTIFF ``src`` into a COG at ``dst`` with overviews and its mask, atomically.

    ``tags`` (GDAL metadata items such as ``TIFFTAG_IMAGEDESCRIPTION``) are set on ``src`` before the copy, so
    the COG driver writes them as TIFF tags; given any, ``TIFFTAG_SOFTWARE`` ("Fotoskhema <version>") and
    ``TIFFTAG_DATETIME`` (now, UTC, TIFF's "YYYY:MM:DD HH:MM:SS") are added unless named.

    The overviews are built into ``src`` first (GDAL's average over the data the mask admits), then GDAL's
    COG driver copies them and compresses every level on all cores in one pass. Measured on the Brighton
    strip's 14 MP mosaic: 0.27 s + 0.56 s, against 1.33 s for the COG driver building its own overviews
    and 1.96 s for rio-cogeo's ``cog_translate`` (which writes a second temporary GeoTIFF); same pixels,
    same size. Memory stays that of GDAL's block cache: nothing is read whole.
    """
    options: dict[str, Any] = {
        "compress": compression.upper(),
        "blocksize": COG_BLOCK_PX,
        "num_threads": "ALL_CPUS",
        "bigtiff": "IF_SAFER",  # past 4 GB (a gigapixel strip): BigTIFF
    }
    if compression == "jpeg":
        options["quality"] = 90  # the COG driver stores 3-band JPEG as YCbCr
    else:
        # horizontal differencing before deflate/LZW/ZSTD: the Brighton mosaic's COG 21.0 -> 15.7 MiB, in the
        # same time; the pixels read back are identical
        options["predictor"] = 2
    if compression in ("deflate", "zstd"):
        # the fastest level: measured on the Brighton strip's 14 MP mosaic (overviews + COG, one run):
        # deflate level 6 (GDAL's default) 2.48 s 15.6 MiB, level 1 1.43 s 16.0 MiB; zstd 1 1.03 s 16.5 MiB,
        # zstd 3 1.14 s 15.9 MiB; lzw 1.65 s 17.1 MiB; jpeg 90 1.98 s 2.8 MiB (lossy); none 0.57 s 63.8 MiB.
        # Deflate stays the default: every TIFF reader knows it, not every one ZSTD.
        options["level"] = 1
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, GDAL_CACHEMAX=256, GDAL_NUM_THREADS="ALL_CPUS"):
        with rasterio.open(src, "r+") as scratch:
            if tags is not None:
                scratch.update_tags(**{**provenance_tags(), **tags})
            levels = overview_levels(scratch.width, scratch.height)
            if levels:
                scratch.build_overviews(levels, Resampling.average)
        with atomic_path(dst) as tmp:
            rio_copy(str(src), str(tmp), driver="COG", overviews="FORCE_USE_EXISTING", **options)


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


def translate_index_to_cog(src: Path, dst: Path, compression: str, tags: Mapping[str, str] | None = None) -> None:
    """:func:`translate_to_cog` for a frame index: overviews by nearest neighbour (a frame number is not averaged),
    nodata 0; JPEG (lossy) is never used for it: deflate instead. No horizontal differencing: an index is runs of
    one value, which deflate packs as well without it (Brighton strip: 157 KiB against 148 KiB) in 0.12 s
    instead of 0.17 s."""
    codec = "deflate" if compression == "jpeg" else compression
    options: dict[str, Any] = {
        "compress": codec.upper(),
        "blocksize": COG_BLOCK_PX,
        "num_threads": "ALL_CPUS",
        "bigtiff": "IF_SAFER",
    }
    if codec in ("deflate", "zstd"):
        options["level"] = 1
    with rasterio.Env(GDAL_CACHEMAX=256, GDAL_NUM_THREADS="ALL_CPUS"):
        with rasterio.open(src, "r+") as scratch:
            scratch.update_tags(**{**provenance_tags(), **(tags or {})})
            levels = overview_levels(scratch.width, scratch.height)
            if levels:
                scratch.build_overviews(levels, Resampling.nearest)
        with atomic_path(dst) as tmp:
            rio_copy(str(src), str(tmp), driver="COG", overviews="FORCE_USE_EXISTING", **options)


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
