"""Disk and time of writing a gigapixel mosaic's COGs: bands assembled into the COG (workers/cog_writer.py)
against the reference, the path every mosaic took before (bands as ZSTD GeoTIFFs, copied into a scratch
GeoTIFF, overviews built into it, GDAL's COG driver copying it), on the same synthetic mosaic in one run.

Run by hand from the repository root::

    .venv/bin/python bench/cog_disk.py [--size 30000 20000] [--compression deflate] [--dir DIR]

The mosaic is ``tests/strip_scenes.GroundTexture`` (fields, hedges, roads, noise) over a slanted strip's
footprint (the rest uncovered, as a strip's mosaic is), with a frame index of 40 frames along it; each path
writes its bands as compose_mosaic's parts do (the pixels rendered before the clock runs), then finishes.
Printed per path: seconds writing the bands, seconds finishing, the folder's peak size (sampled every 0.2 s:
bands, scratch, overviews and COGs while they exist), the COGs' size and peak / COGs; then ours / reference.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

from tests.strip_scenes import GroundTexture  # noqa: E402
from workers.cog_writer import (  # noqa: E402
    open_cog_band_writer,
    open_cog_index_band_writer,
    write_cog_from_bands,
)
from workers.raster_io import (  # noqa: E402
    open_band_reader,
    open_block_writer,
    open_index_reader,
    open_index_writer,
    translate_index_to_cog,
    translate_to_cog,
)

BAND_ROWS = 512  # compose_mosaic's default block_px: a band of rows per part
TRANSFORM = [0.1, 0.0, 500000.0, 0.0, -0.1, 6000000.0]
EPSG = 32633


def band(texture: GroundTexture, width: int, height: int, y: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``y`` .. of the mosaic: (h, w, 3) uint8 RGB, (h, w) coverage and (h, w) uint16 frame index (+1)."""
    h = min(BAND_ROWS, height - y)
    rgb = np.empty((h, width, 3), np.uint8)
    for x in range(0, width, 16384):
        w = min(16384, width - x)
        rgb[:, x : x + w] = np.clip(texture.raster(x, y, w, h), 0, 255).astype(np.uint8)
    xs = np.arange(width, dtype=np.float64)[None, :]
    ys = np.arange(y, y + h, dtype=np.float64)[:, None]
    # a strip's footprint: a band 70 % of the height wide, slanted corner to corner
    centre = height * (0.15 + 0.7 * xs / width)
    covered = np.abs(ys - centre) < 0.35 * height
    index = ((xs * 40 // width).astype(np.uint16) + 1) * covered
    rgb[~covered] = 0
    return rgb, covered, index.astype(np.uint16)


def windows(width: int, h: int) -> Iterator[Window]:
    for x in range(0, width, BAND_ROWS):
        yield Window(x, 0, min(BAND_ROWS, width - x), h)


class DiskPeak:
    """The peak total size (allocated blocks) of the files under a folder, sampled every 0.2 s by a thread."""

    def __init__(self, folder: Path) -> None:
        self.folder, self.peak, self._stop = folder, 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def size(self) -> int:
        total = 0
        for root, _, files in os.walk(self.folder):
            for name in files:
                with contextlib.suppress(FileNotFoundError):  # deleted while we looked
                    total += os.stat(os.path.join(root, name)).st_blocks * 512
        return total

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self.size())
            time.sleep(0.2)

    def __enter__(self) -> DiskPeak:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.size())


def write_bands(
    folder: Path, texture: GroundTexture, width: int, height: int, writers: tuple[Callable[..., Any], ...]
) -> float:
    """Every band through ``writers`` (band writer, index writer); seconds spent writing (not rendering)."""
    seconds = 0.0
    for y in range(0, height, BAND_ROWS):
        rgb, covered, index = band(texture, width, height, y)
        started = time.perf_counter()
        open_band, open_index = writers
        h = rgb.shape[0]
        with (
            open_band(folder / f"band_{y:07d}.tif", width, h) as write,
            open_index(folder / f"index_{y:07d}.tif", width, h) as write_index,
        ):
            for w in windows(width, h):
                cols = slice(w.col_off, w.col_off + w.width)
                write(w, rgb[:, cols], covered[:, cols])
                write_index(w, index[:, cols])
        seconds += time.perf_counter() - started
    return seconds


def reference(folder: Path, texture: GroundTexture, width: int, height: int, codec: str) -> dict[str, Any]:
    """Bands as ZSTD GeoTIFFs, a scratch GeoTIFF, overviews into it and GDAL's COG driver (the path before)."""

    def zstd_band(path: Path, w: int, h: int) -> Any:
        return open_block_writer(path, w, h, None, None, compress="zstd")

    def zstd_index(path: Path, w: int, h: int) -> Any:
        return open_index_writer(path, w, h, None, None, compress="zstd")

    with DiskPeak(folder) as disk:
        bands = write_bands(folder, texture, width, height, (zstd_band, zstd_index))
        started = time.perf_counter()
        scratch, scratch_index = folder / "mosaic.tmp.tif", folder / "frame_index.tmp.tif"
        with (
            open_block_writer(scratch, width, height, EPSG, TRANSFORM, compress="zstd") as write,
            open_index_writer(scratch_index, width, height, EPSG, TRANSFORM, compress="zstd") as write_index,
        ):
            for y in range(0, height, BAND_ROWS):
                path, index_path = folder / f"band_{y:07d}.tif", folder / f"index_{y:07d}.tif"
                with open_band_reader(path) as read, open_index_reader(index_path) as index:
                    h = min(BAND_ROWS, height - y)
                    for w in windows(width, h):
                        target = Window(w.col_off, y, w.width, w.height)
                        write(target, *read(w))
                        write_index(target, index(w))
                path.unlink()
                index_path.unlink()
        tags = {"TIFFTAG_IMAGEDESCRIPTION": "bench"}
        translate_to_cog(scratch, folder / "mosaic.tif", codec, tags=tags)
        translate_index_to_cog(scratch_index, folder / "frame_index.tif", codec, tags=tags)
        scratch.unlink()
        scratch_index.unlink()
        finish = time.perf_counter() - started
    return summary(folder, bands, finish, disk.peak)


def ours(folder: Path, texture: GroundTexture, width: int, height: int, codec: str) -> dict[str, Any]:
    """Bands as the COG's own tiles, assembled into the COGs (workers/cog_writer.py)."""

    def cog_band(path: Path, w: int, h: int) -> Any:
        return open_cog_band_writer(path, w, h, codec)

    def cog_index(path: Path, w: int, h: int) -> Any:
        return open_cog_index_band_writer(path, w, h, codec)

    with DiskPeak(folder) as disk:
        bands = write_bands(folder, texture, width, height, (cog_band, cog_index))
        started = time.perf_counter()
        ys = range(0, height, BAND_ROWS)
        placed = {"width": width, "height": height, "crs": EPSG, "transform": TRANSFORM, "compression": codec}
        tags = {"TIFFTAG_IMAGEDESCRIPTION": "bench"}
        write_cog_from_bands(
            folder / "mosaic.tif",
            [folder / f"band_{y:07d}.tif" for y in ys],
            kind="rgb",
            tags=tags,
            scratch=folder / "mosaic.tmp.tif",
            **placed,  # type: ignore[arg-type]
        )
        write_cog_from_bands(
            folder / "frame_index.tif",
            [folder / f"index_{y:07d}.tif" for y in ys],
            kind="index",
            tags=tags,
            scratch=folder / "frame_index.tmp.tif",
            **placed,  # type: ignore[arg-type]
        )
        finish = time.perf_counter() - started
    return summary(folder, bands, finish, disk.peak)


def summary(folder: Path, bands: float, finish: float, peak: int) -> dict[str, Any]:
    outputs = sum((folder / name).stat().st_blocks * 512 for name in ("mosaic.tif", "frame_index.tif"))
    return {
        "bands_s": bands,
        "finish_s": finish,
        "peak_gb": peak / 1e9,
        "cogs_gb": outputs / 1e9,
        "peak_over_cogs": peak / outputs,
    }


def same_pixels(a: Path, b: Path, width: int, height: int) -> bool:
    """The two mosaics' full resolution and mask agree on a few windows across the strip."""
    with rasterio.open(a) as one, rasterio.open(b) as two:
        for k in range(5):
            x, y = (width - 1024) * k // 4, (height - 1024) * k // 4
            w = Window(x, y, 1024, 1024)
            if not (
                np.array_equal(one.read(window=w), two.read(window=w))
                and np.array_equal(one.read_masks(1, window=w), two.read_masks(1, window=w))
            ):
                return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, nargs=2, default=(30000, 20000), metavar=("W", "H"))
    parser.add_argument("--compression", default="deflate", choices=("deflate", "zstd", "lzw", "jpeg"))
    parser.add_argument("--dir", type=Path, default=None, help="where to write (default: a temporary folder)")
    args = parser.parse_args()
    width, height = args.size
    texture = GroundTexture(seed=7, field_angle=0.3, road_angle=1.1)
    base = Path(tempfile.mkdtemp(prefix="cog_disk_", dir=args.dir))
    try:
        print(
            f"mosaic {width} x {height} px ({width * height / 1e9:.2f} Gpx), {args.compression}, {os.cpu_count()} cores"
        )
        results = {}
        for name, run in (("reference", reference), ("ours", ours)):
            folder = base / name
            folder.mkdir()
            results[name] = run(folder, texture, width, height, args.compression)
            r = results[name]
            print(
                f"{name:>9}: bands {r['bands_s']:6.1f} s  finish {r['finish_s']:6.1f} s  "
                f"peak {r['peak_gb']:5.2f} GB  COGs {r['cogs_gb']:5.2f} GB  peak/COGs {r['peak_over_cogs']:.2f}"
            )
        same = same_pixels(base / "ours" / "mosaic.tif", base / "reference" / "mosaic.tif", width, height)
        ref, new = results["reference"], results["ours"]
        ratio = {key: new[key] / ref[key] for key in ("bands_s", "finish_s", "peak_gb", "cogs_gb")}
        print(
            f"ours / reference: bands {ratio['bands_s']:.2f}  finish {ratio['finish_s']:.2f}  "
            f"bands + finish {(new['bands_s'] + new['finish_s']) / (ref['bands_s'] + ref['finish_s']):.2f}  "
            f"peak disk {ratio['peak_gb']:.2f}  COGs {ratio['cogs_gb']:.2f}; "
            f"same full-resolution pixels and mask: {same}"
        )
    finally:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
