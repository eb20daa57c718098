"""Stage ``compose_mosaic``: warp, gain-compensate and feather-blend the frames into a COG, one window at a
time (:mod:`workers.algorithms.mosaic.compose`)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import numpy as np
from rasterio.windows import Window

from workers.algorithms.mosaic import compose_block, gains_and_coverage, output_box
from workers.config import MosaicConfig
from workers.parallel import thread_count
from workers.raster_io import open_block_writer, translate_to_cog
from workers.records import Coverage
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
    image_of = partial(ws.load_compose_image, mmap=True)
    gains, outline, area = gains_and_coverage(image_of, sizes, to_frame, geo.width, geo.height, cfg.gain_compensation)
    ws.save_coverage(Coverage(outline, area))
    blocks = [(x, y) for y in range(0, geo.height, cfg.block_px) for x in range(0, geo.width, cfg.block_px)]
    tmp = ws.mosaic_scratch_path()
    transform = geo.transform if geo.georeferenced else None
    windows = [(x, y, min(cfg.block_px, geo.width - x), min(cfg.block_px, geo.height - y)) for x, y in blocks]

    def one(window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        return compose_block(image_of, sizes, to_frame, boxes, gains, window, cfg.feather_px)

    threads = thread_count(cfg.threads)
    with (
        open_block_writer(tmp, geo.width, geo.height, geo.epsg, transform, compress=None) as write,
        ThreadPoolExecutor(max_workers=threads) as pool,
    ):
        # Windows are composed on every core (OpenCV and NumPy release the GIL) and written in order by
        # this thread, a batch at a time, so memory holds a batch of windows, never the whole mosaic.
        for start in range(0, len(windows), threads):
            progress(0.1 + 0.75 * start / len(windows), f"block {start + 1}/{len(windows)}")
            batch = windows[start : start + threads]
            for (x, y, w, h), (rgb, mask) in zip(batch, pool.map(one, batch), strict=True):
                write(Window(x, y, w, h), rgb, mask)
    progress(0.85, "writing COG with overviews")
    translate_to_cog(tmp, ws.mosaic_path(), cfg.cog_compression)
    tmp.unlink(missing_ok=True)
    progress(1.0, f"block {len(blocks)}/{len(blocks)}")
    return {
        "width": geo.width,
        "height": geo.height,
        "blocks": len(blocks),
        "gains": {frames[k].name: g for k, g in gains.items()},
    }
