"""Stage ``compose_mosaic``: warp, gain-compensate and blend the frames into a COG, window by window
(:mod:`workers.algorithms.mosaic.compose`), a part per band of windows.

The plan measures what every part shares: the gains and the coverage from a low-resolution render, and the
seams (a multiband mosaic is cut along them; a feathered one's seam visibility is measured on them). Each part
composes one band of rows (``block_px`` high, rounded up to the COG's 512 px tiles) into a GeoTIFF of the COG's
own tiles, compressed as the COG is, and the band's frame index (which frame each pixel came from) into another;
the finish assembles both COGs from the bands with their overviews (:mod:`workers.cog_writer`), each band
deleted once copied: no scratch mosaic, so the disk holds the bands or the COGs, not both. Memory depends on the
band's width and the frames' size, never on the size of the mosaic.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import Any

import cv2
import numpy as np
from rasterio.windows import Window

from workers.algorithms.mosaic import (
    ccd_gains,
    column_brightness,
    compose_block,
    compose_block_multiband,
    gains_and_coverage,
    output_box,
    owned_regions,
    seam_labels,
    seam_points,
    seam_visibility,
)
from workers.cog_writer import (
    band_fits,
    first_level_path,
    open_cog_band_writer,
    open_cog_index_band_writer,
    write_cog_from_bands,
)
from workers.config import MosaicConfig
from workers.parallel import RecentCache, keep_freed_memory, ordered_imap, thread_count
from workers.photo_io import WindowReader, dct_block, reads_by_window
from workers.pipeline import PipelineError
from workers.raster_io import COG_BLOCK_PX, open_window_reader
from workers.records import Coverage, Frame
from workers.workspace import JobWorkspace, NpyWindows, ProgressFn, atomic_path, noop_progress

STAGE = "compose_mosaic"
_PHOTOS: RecentCache[Any] = RecentCache(16)  # full photos this process composes from (native resolution)


PART_UNIT = "band"  # what a part is, in the progress
# mosaics whose bands keep their first overview level for the finish (cog_writer.open_cog_band_writer): 2.5 bytes
# of disk a mosaic pixel until the finish, and a band's width x 1.25 KiB of memory while a part writes it; a wider
# or larger mosaic's finish decodes its bands' tiles again instead
FIRST_LEVEL_MAX_WIDTH = 16384
FIRST_LEVEL_MAX_PX = 1 << 27
# (plan, bands) shares of the stage's progress, finish has the rest: on the Brighton strip and 12- and 24-frame
# synthetic flights (bench/eta.py) the plan (gains, coverage, seams) took 10-70 % of the stage, the bands 5-40 %,
# and finish (the COGs with overviews) 20-45 %; progress at the default shares (5/85/10 %) stood at 95 % for the
# last 45 % of the time, and a time left extrapolated from it ran out too early
PROGRESS_SHARES = (0.25, 0.35)


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """Gains, coverage and (multiband) seams, saved for the parts; a part per band of ``block_px`` rows."""
    geo = ws.load_georef()
    sizes, to_frame = _working_geometry(ws)
    # gains and the outline from a 768 px render: the working copies are plenty for it, at any output scale
    working_of = partial(ws.load_compose_image, mmap=True)
    gains, outline, area, vignette = gains_and_coverage(
        working_of, sizes, to_frame, geo.width, geo.height, cfg.gain_compensation, cfg.vignetting_correction
    )
    ws.save_coverage(Coverage(outline, area))
    shared: dict[str, Any] = {"gains": {str(k): g.tolist() for k, g in gains.items()}, "vignette": list(vignette)}
    # the seams a multiband mosaic is cut along; a feathered one is measured on the same lines (not cut there),
    # when asked to (measure_seams)
    if _has_seams(cfg):
        labels, label_scale = seam_labels(working_of, sizes, to_frame, gains, geo.width, geo.height)
        ws.save_part_arrays(STAGE, labels=labels)
        shared["label_scale"] = label_scale
    if cfg.blend == "multiband":
        ws.save_seams(owned_regions(labels, label_scale))
    else:
        ws.remove_seams()  # a feathered mosaic (again): no cut lines
    if cfg.ccd_segments > 1:
        shared["ccd_gains"] = _ccd_gains(ws, cfg.ccd_segments, thread_count(cfg.threads)).tolist()
    ws.save_part_inputs(STAGE, shared)
    return [f"{y:07d}" for y in range(0, geo.height, _band_rows(cfg))]


def _ccd_gains(ws: JobWorkspace, segments: int, threads: int) -> np.ndarray:
    """The gain of each CCD sub-image, from the native columns either side of every join of every frame."""
    frames = ws.load_composed_frames()
    widths = {f.orig_width for f in frames.values()}
    if len(widths) != 1:
        raise PipelineError("ccd_segments is for frames of one camera: these frames differ in width")
    (width,) = widths
    if width < 2 * segments:
        raise PipelineError(f"frames {width} px wide cannot be joined from {segments} CCD sub-images")

    def columns_of(k: int, c0: int, c1: int) -> np.ndarray:
        return np.asarray(_photo(ws, frames, k)[:, c0:c1])

    blocks = {k: dct_block(frame.path) for k, frame in frames.items()}  # a join inside a JPEG block is smeared
    # each thread on one photo at a time: at most 16, the photos _PHOTOS keeps open
    return ccd_gains(columns_of, sorted(frames), width, segments, blocks, threads=min(16, threads))


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Compose the band of rows from ``key`` into its files (``compose_band_path``, ``index_band_path``)."""
    y = int(key)
    geo = ws.load_georef()
    # glibc keeps a window's freed arrays for the next (workers.parallel): on the Brighton strip's 14 MP mosaic
    # the stage took 0.73 s instead of 0.82 s (medians of four), for up to 40 MiB more at the job's peak
    keep_freed_memory()
    shared = ws.load_part_inputs(STAGE)
    gains = {int(k): np.array(g, np.float64) for k, g in shared["gains"].items()}
    vignette = (float(shared["vignette"][0]), float(shared["vignette"][1]))
    sizes, to_frame = _working_geometry(ws)
    # each frame's working copy read by window, not memory-mapped: a map keeps the rows it has touched resident
    opened: dict[int, NpyWindows] = {}

    def working(k: int) -> NpyWindows:
        if k not in opened:
            opened[k] = ws.compose_image_windows(k)
        return opened[k]

    image_of: Callable[[int], Any] = working
    if cfg.output_resolution == "native":
        frames = ws.load_composed_frames()
        to_frame = {k: _working_to_photo(frames[k]) @ M for k, M in to_frame.items()}
        sizes = {k: (frames[k].orig_width, frames[k].orig_height) for k in to_frame}
        image_of = partial(_photo, ws, frames, by_rows=True)
    boxes = {k: output_box(M, sizes[k], geo.width, geo.height) for k, M in to_frame.items()}
    steps = np.array(shared["ccd_gains"]) if "ccd_gains" in shared else None
    columns = None if steps is None else {k: column_brightness(sizes[k][0], steps) for k in to_frame}
    if cfg.blend == "multiband":
        labels, label_scale = ws.load_part_arrays(STAGE)["labels"], float(shared["label_scale"])

    def one(window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if cfg.blend == "multiband":
            return compose_block_multiband(
                image_of, sizes, to_frame, boxes, gains, window, labels, label_scale, cfg.blend_bands, vignette, columns
            )
        return compose_block(image_of, sizes, to_frame, boxes, gains, window, cfg.feather_px, vignette, columns)

    rows = _band_rows(cfg)
    height = min(rows, geo.height - y)
    windows = [  # block_px square, row after row (one row of them but in a gigapixel mosaic's band)
        (x, y + dy, min(cfg.block_px, geo.width - x), min(cfg.block_px, height - dy))
        for dy in range(0, height, cfg.block_px)
        for x in range(0, geo.width, cfg.block_px)
    ]
    # the bands a process composes at once share its cores; a mosaic of fewer bands than cores (a wide strip)
    # composes the windows of each band on the cores left
    bands = math.ceil(geo.height / rows)
    inner = max(1, thread_count(cfg.threads) // max(1, min(bands, thread_count(cfg.threads))))
    # each window is written as it comes: a band in progress holds a few windows, not all of them (a 75000 px
    # wide strip's band is 38 Mpx: 0.3 GB a thread, 5 GB on 16 cores, when they were kept until the band ended)
    results = ordered_imap(one, windows, inner)
    # a small mosaic's band keeps its first overview level beside it, for the finish (cog_writer.first_level_path);
    # a band written without one leaves none from an earlier run
    levels = [first_level_path(ws.compose_band_path(y)), first_level_path(ws.index_band_path(y))]
    small = geo.width <= FIRST_LEVEL_MAX_WIDTH and geo.width * geo.height <= FIRST_LEVEL_MAX_PX
    # windows at even offsets (the 2x2 blocks never cut) and lossless tiles (the sums are the stored pixels')
    keep = small and cfg.block_px % 2 == 0 and cfg.cog_compression != "jpeg"
    if not keep:
        for level in levels:
            level.unlink(missing_ok=True)
    level_rgb, level_index = levels if keep else (None, None)
    with (  # the COGs' own tiles, which the finish copies into them (cog_writer)
        atomic_path(ws.compose_band_path(y)) as tmp,
        atomic_path(ws.index_band_path(y)) as tmp_index,
        open_cog_band_writer(tmp, geo.width, height, cfg.cog_compression, level_rgb) as write,
        open_cog_index_band_writer(tmp_index, geo.width, height, cfg.cog_compression, level_index) as write_index,
    ):
        for (x, wy, w, h), (rgb, mask, index) in zip(windows, results, strict=True):
            write(Window(x, wy - y, w, h), rgb, mask)
            write_index(Window(x, wy - y, w, h), _index_values(index))
    return {"rows": height}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """``mosaic.tif`` (COG, RGB + mask) and ``frame_index.tif`` assembled from the bands (:func:`_assemble_cogs`),
    then the seams measured and the report's figures."""
    _assemble_cogs(ws, cfg, records, progress)
    return _finished(ws, cfg, records, progress)


def _finished(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], progress: ProgressFn
) -> dict[str, Any]:
    """With both COGs written: the seams measured on the mosaic, the native copies removed, the report."""
    geo = ws.load_georef()
    frames = ws.load_composed_frames()
    shared = ws.load_part_inputs(STAGE)
    visibility = None
    if _has_seams(cfg):
        progress(0.95, "measuring the seams")
        labels, label_scale = ws.load_part_arrays(STAGE)["labels"], float(shared["label_scale"])
        with open_window_reader(ws.mosaic_path()) as read_window:
            visibility = seam_visibility(read_window, *seam_points(labels, label_scale))
    ws.remove_native_images()
    vignette = shared["vignette"]
    progress(1.0, f"band {len(records)}/{len(records)}")
    return {
        "width": geo.width,
        "height": geo.height,
        "blocks": math.ceil(geo.width / cfg.block_px) * len(records),
        "output_resolution": cfg.output_resolution,
        "blend": cfg.blend,
        "vignetting": {"c1": vignette[0], "c2": vignette[1]} if cfg.vignetting_correction else None,
        "ccd_gains": shared.get("ccd_gains"),  # of each CCD sub-image, left to right (ccd_segments)
        # colour step across the cut lines / the same 16 px beside them (1.0: invisible); a feathered mosaic is
        # measured on the lines a multiband one would be cut along
        "seam_visibility": visibility,
        "gains": {frames[int(k)].name: g for k, g in shared["gains"].items()},
    }


def _band_rows(cfg: MosaicConfig) -> int:
    """Rows of a part's band: ``block_px``, rounded up to a multiple of the COG's 512 px tiles (the band's tiles
    are copied into the COG as they are)."""
    return -(-cfg.block_px // COG_BLOCK_PX) * COG_BLOCK_PX


def _assemble_cogs(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], progress: ProgressFn
) -> None:
    """``mosaic.tif`` and ``frame_index.tif`` put together from the bands' tiles (:mod:`workers.cog_writer`),
    each band deleted once copied: the disk's peak is the COGs and a band, where copying the bands into a
    scratch mosaic and that into a COG held about three mosaics (13.3 GB for 5.9 GB of frames and COGs on
    bench/strips.py's 40 frames). A finish stopped midway composes the bands it had deleted again (and those an
    older version wrote otherwise) and writes both COGs anew."""
    geo = ws.load_georef()
    for key, record in records.items():
        y, height = int(key), int(record["rows"])
        fits = band_fits(ws.compose_band_path(y), geo.width, height, cfg.cog_compression, "rgb")
        if not (fits and band_fits(ws.index_band_path(y), geo.width, height, cfg.cog_compression, "index")):
            run_part(ws, cfg, key)
    rows = [int(key) for key in records]
    write = partial(
        write_cog_from_bands,
        width=geo.width,
        height=geo.height,
        crs=geo.epsg,
        transform=geo.transform if geo.georeferenced else None,
        compression=cfg.cog_compression,
    )
    progress(0.0, "writing the mosaic's COG")
    write(
        ws.mosaic_path(),
        [ws.compose_band_path(y) for y in rows],
        kind="rgb",
        tags={"TIFFTAG_IMAGEDESCRIPTION": _description(cfg)},
        scratch=ws.mosaic_scratch_path(),
        progress=lambda f, m: progress(0.8 * f, m),
    )
    progress(0.8, "writing the frame index")
    write(
        ws.frame_index_path(),
        [ws.index_band_path(y) for y in rows],
        kind="index",
        tags=_index_tags(ws.load_composed_frames()),
        scratch=ws.frame_index_scratch_path(),
        progress=lambda f, m: progress(0.8 + 0.15 * f, m),
    )


def _description(cfg: MosaicConfig) -> str:
    """``mosaic.tif``'s TIFF description."""
    return f"Fotoskhema mosaic job, mode {cfg.mode}, blend {cfg.blend}"


def _index_values(index: np.ndarray) -> np.ndarray:
    """(h, w) uint16 of the frame index file: frame index + 1, 0 where no frame is."""
    return np.clip(index.astype(np.int64) + 1, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _index_tags(frames: dict[int, Frame]) -> dict[str, str]:
    """The frame index COG's description and, per value, the frame's name (``FRAME_<value>``)."""
    tags = {"TIFFTAG_IMAGEDESCRIPTION": "Fotoskhema frame index: the frame each mosaic pixel was taken from, "
            "its index + 1 (footprints.geojson's index); 0: none"}  # fmt: skip
    tags.update({f"FRAME_{k + 1}": "".join(c if c.isprintable() else " " for c in f.name) for k, f in frames.items()})
    return tags


def _has_seams(cfg: MosaicConfig) -> bool:
    return cfg.blend == "multiband" or cfg.measure_seams


def _working_geometry(ws: JobWorkspace) -> tuple[dict[int, tuple[int, int]], dict[int, np.ndarray]]:
    """Each composed frame's working (width, height) and output pixel -> working pixel map."""
    geo = ws.load_georef()
    frames = ws.load_composed_frames()
    homs = ws.load_alignment().homographies
    to_frame = {k: np.linalg.inv(H) @ geo.output_to_plane for k, H in homs.items()}
    return {k: (frames[k].width, frames[k].height) for k in to_frame}, to_frame


def _working_to_photo(frame: Frame) -> np.ndarray:
    """(3, 3) working-copy px -> photo px; pixel centres at integers on both, ``(x + 0.5) / s - 0.5``."""
    sx, sy = frame.width / frame.orig_width, frame.height / frame.orig_height
    return np.array([[1 / sx, 0.0, 0.5 / sx - 0.5], [0.0, 1 / sy, 0.5 / sy - 0.5], [0.0, 0.0, 1.0]])


def _photo(ws: JobWorkspace, frames: dict[int, Frame], k: int, *, by_rows: bool = False) -> Any:
    """Photo ``k`` at full size, as something windows can be sliced from: a TIFF read by window where it lies
    (never decoded whole), any other photo decoded once into the job's scratch (``native/``, shared by every
    worker; written atomically, so two workers decoding it at once both leave a whole file) and read from there
    by rows (``by_rows``: :class:`NpyWindows`, for windows; nothing of it stays resident) or memory-mapped (for
    columns, which rows would read whole: the CCD joins)."""

    def open_photo() -> Any:
        frame = frames[k]
        if reads_by_window(frame.path):
            reader = WindowReader(frame.path)
            if reader.shape[:2] != (frame.orig_height, frame.orig_width):
                raise PipelineError(f"{frame.name} changed size since it was loaded")
            return reader
        if not ws.native_image_exists(k):
            image = cv2.imread(frame.path, cv2.IMREAD_COLOR)  # as load_images read it (EXIF orientation applied)
            if image is None or image.shape[:2] != (frame.orig_height, frame.orig_width):
                raise PipelineError(f"{frame.name} could not be decoded again at its full size")
            ws.save_native_image(k, image)
        return ws.native_image_windows(k) if by_rows else ws.load_native_image(k, mmap=True)

    # a TIFF's reader serves both: one per frame, its block table parsed once
    return _PHOTOS.get((str(ws.root.resolve()), k, by_rows and not reads_by_window(frames[k].path)), open_photo)
