"""Stage ``compute_disparity``: the rectified pair matched by ``sgbm`` or the source work's ``local`` method,
checked left-right, speckle-filtered and (with ``fill``) filled from the background side.

Writes ``disparity.tif`` (float32 px in the rectified left view, NaN where there is none),
``confidence.tif`` (0 where a value was filled) and the colour-ramped picture the viewer tiles.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from gpu_kernels.backend import resolve_device
from workers.algorithms.disparity import match_pair
from workers.algorithms.stereo import DISPARITY, Rectification, colour_ramp, legend, value_range
from workers.config import StereoDemConfig
from workers.raster_io import write_array_cog, write_rgb_cog
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: StereoDemConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Match the rectified pair over the disparity range ``rectify_pair`` chose."""
    left, right, valid_left, valid_right = ws.load_rectified_pair()
    info = ws.load_rectification()
    rect = Rectification.from_json(info["rectification"])
    low, count = int(info["min_disparity"]), int(info["num_disparities"])
    device = resolve_device(cfg.device) if cfg.method == "local" else "cpu"
    progress(0.05, f"{cfg.method} over {count} disparities from {low} px")
    started = time.perf_counter()
    result = match_pair(
        left,
        right,
        cfg.method,
        low,
        count,
        valid_left=valid_left,
        valid_right=valid_right,
        fundamental=rect.fundamental,
        fill=cfg.fill,
        device=device,
    )
    seconds = time.perf_counter() - started
    progress(0.8, "writing")
    ws.save_disparity_arrays(result.disparity, result.dense, result.filled, result.confidence)
    write_array_cog(ws.disparity_path(), result.dense, nodata=float("nan"), compression=cfg.cog_compression)
    write_array_cog(ws.confidence_path(), result.confidence, compression=cfg.cog_compression)
    shown = np.isfinite(result.dense)
    lo, hi = value_range(result.dense, shown)
    write_rgb_cog(
        ws.disparity_view_path(),
        ws.view_scratch_path("disparity"),
        colour_ramp(result.dense, lo, hi, DISPARITY),
        shown,
        compression=cfg.cog_compression,
    )
    inside = int(valid_left.sum())
    checked = int(np.isfinite(result.disparity).sum())
    return {
        "method": cfg.method,
        "device": device,
        "min_disparity": low,
        "num_disparities": count,
        "pixels": inside,
        "checked_share": round(checked / max(inside, 1), 4),
        "filled_share": round(int(result.filled.sum()) / max(inside, 1), 4),
        "match_seconds": round(seconds, 3),
        "seconds_per_megapixel": round(seconds / max(left.shape[0] * left.shape[1] / 1e6, 1e-9), 3),
        "legend": {"units": "px", "stops": legend(lo, hi, DISPARITY)},
    }
