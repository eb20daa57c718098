"""Stage ``compose_mosaic``: warp, gain-compensate and feather-blend the frames into a COG, one window at a
time (:mod:`workers.algorithms.mosaic.compose`)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from typing import Any

import cv2
import numpy as np
from rasterio.windows import Window

from workers.algorithms.mosaic import (
    SCRATCH_RAW_MAX_PX,
    compose_block,
    compose_block_multiband,
    gains_and_coverage,
    output_box,
    owned_regions,
    seam_labels,
    seam_points,
    seam_visibility,
)
from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.photo_io import WindowReader, reads_by_window
from workers.pipeline import PipelineError
from workers.raster_io import open_block_writer, open_window_reader, translate_to_cog
from workers.records import Coverage, Frame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``mosaic.tif`` (COG, RGB + mask) and ``footprints.geojson``-ready ``coverage.json``."""
    geo = ws.load_georef()
    frames = ws.load_composed_frames()
    homs = ws.load_alignment().homographies
    # output pixel -> frame pixel, for every frame
    to_frame = {k: np.linalg.inv(H) @ geo.output_to_plane for k, H in homs.items()}
    sizes = {k: (frames[k].width, frames[k].height) for k in to_frame}
    boxes = {k: output_box(M, sizes[k], geo.width, geo.height) for k, M in to_frame.items()}
    progress(0.0, "gain compensation")
    # gains and the outline from a 768 px render: the working copies are plenty for it, at any output scale
    working_of = partial(ws.load_compose_image, mmap=True)
    gains, outline, area, vignette = gains_and_coverage(
        working_of, sizes, to_frame, geo.width, geo.height, cfg.gain_compensation, cfg.vignetting_correction
    )
    ws.save_coverage(Coverage(outline, area))
    image_of: Callable[[int], Any] = working_of
    working_sizes, working_to_frame = sizes, to_frame
    if cfg.output_resolution == "native":
        progress(0.05, "decoding the photos at full size")
        photos = _open_photos(ws, [frames[k] for k in sorted(to_frame)], cfg.threads)
        to_frame = {k: _working_to_photo(frames[k]) @ M for k, M in to_frame.items()}
        sizes = {k: (frames[k].orig_width, frames[k].orig_height) for k in to_frame}
        boxes = {k: output_box(M, sizes[k], geo.width, geo.height) for k, M in to_frame.items()}
        image_of = photos.__getitem__
    blocks = [(x, y) for y in range(0, geo.height, cfg.block_px) for x in range(0, geo.width, cfg.block_px)]
    tmp = ws.mosaic_scratch_path()
    transform = geo.transform if geo.georeferenced else None
    windows = [(x, y, min(cfg.block_px, geo.width - x), min(cfg.block_px, geo.height - y)) for x, y in blocks]

    if cfg.blend == "multiband":
        progress(0.08, "cutting seams")
        labels, label_scale = seam_labels(working_of, working_sizes, working_to_frame, gains, geo.width, geo.height)
        ws.save_seams(owned_regions(labels, label_scale))
    else:
        ws.remove_seams()  # a feathered mosaic (again): no cut lines

    def one(window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        if cfg.blend == "multiband":
            return compose_block_multiband(
                image_of, sizes, to_frame, boxes, gains, window, labels, label_scale, cfg.blend_bands, vignette
            )
        return compose_block(image_of, sizes, to_frame, boxes, gains, window, cfg.feather_px, vignette)

    threads = thread_count(cfg.threads)
    # uncompressed is fastest, but past SCRATCH_RAW_MAX_PX the scratch would take 4 B/px of disk
    scratch_codec = None if geo.width * geo.height <= SCRATCH_RAW_MAX_PX else "deflate"
    with (
        open_block_writer(tmp, geo.width, geo.height, geo.epsg, transform, compress=scratch_codec) as write,
        ThreadPoolExecutor(max_workers=threads) as pool,
    ):
        # Windows are composed on every core (OpenCV and NumPy release the GIL) and written in order by
        # this thread while the next ones are composed; at most 2 per thread wait, so memory holds a few
        # windows, never the whole mosaic.
        pending: deque[tuple[tuple[int, int, int, int], Future[tuple[np.ndarray, np.ndarray]]]] = deque()
        written = 0

        def write_oldest(keep: int) -> None:
            nonlocal written
            while len(pending) > keep:
                (x, y, w, h), future = pending.popleft()
                write(Window(x, y, w, h), *future.result())
                written += 1
                progress(0.1 + 0.75 * written / len(windows), f"block {written}/{len(windows)}")

        for window in windows:
            pending.append((window, pool.submit(one, window)))
            write_oldest(2 * threads)
        write_oldest(0)
    progress(0.85, "writing COG with overviews")
    translate_to_cog(
        tmp,
        ws.mosaic_path(),
        cfg.cog_compression,
        tags={"TIFFTAG_IMAGEDESCRIPTION": f"Fotoskhema mosaic job, mode {cfg.mode}, blend {cfg.blend}"},
    )
    tmp.unlink(missing_ok=True)
    visibility = None
    if cfg.blend == "multiband":
        progress(0.95, "measuring the seams")
        with open_window_reader(ws.mosaic_path()) as read:
            visibility = seam_visibility(read, *seam_points(labels, label_scale))
    ws.remove_native_images()
    progress(1.0, f"block {len(blocks)}/{len(blocks)}")
    return {
        "width": geo.width,
        "height": geo.height,
        "blocks": len(blocks),
        "output_resolution": cfg.output_resolution,
        "blend": cfg.blend,
        "vignetting": {"c1": vignette[0], "c2": vignette[1]} if cfg.vignetting_correction else None,
        # multiband: colour step across the cut lines / the same 16 px beside them (1.0: invisible)
        "seam_visibility": visibility,
        "gains": {frames[k].name: g for k, g in gains.items()},
    }


def _working_to_photo(frame: Frame) -> np.ndarray:
    """(3, 3) working-copy px -> photo px; pixel centres at integers on both, ``(x + 0.5) / s - 0.5``."""
    sx, sy = frame.width / frame.orig_width, frame.height / frame.orig_height
    return np.array([[1 / sx, 0.0, 0.5 / sx - 0.5], [0.0, 1 / sy, 0.5 / sy - 0.5], [0.0, 0.0, 1.0]])


def _open_photos(ws: JobWorkspace, used: list[Frame], threads: int) -> dict[int, Any]:
    """Each used photo at full size, as something windows can be sliced from: a TIFF read by window where
    it lies (never decoded whole), any other photo decoded once into the workspace's scratch (``native/``)
    and memory-mapped."""

    def one(frame: Frame) -> Any:
        if reads_by_window(frame.path):
            reader = WindowReader(frame.path)
            if reader.shape[:2] != (frame.orig_height, frame.orig_width):
                raise PipelineError(f"{frame.name} changed size since it was loaded")
            return reader
        image = cv2.imread(frame.path, cv2.IMREAD_COLOR)  # as load_images read it (EXIF orientation applied)
        if image is None or image.shape[:2] != (frame.orig_height, frame.orig_width):
            raise PipelineError(f"{frame.name} could not be decoded again at its full size")
        ws.save_native_image(frame.index, image)
        return ws.load_native_image(frame.index, mmap=True)

    opened = ordered_map(one, used, thread_count(threads), noop_progress, "photo")
    return {frame.index: photo for frame, photo in zip(used, opened, strict=True)}
