"""Stage ``compose_mosaic``: warp, gain-compensate and feather-blend the frames into a COG.

The output is produced one window at a time; a window reads only the part of each working frame
it needs (the frames are memory-mapped), so memory depends on the window and frame size, never on
the size of the mosaic.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from rasterio.windows import Window

from workers.algorithms.alignment import apply_homography, frame_corners
from workers.algorithms.blending import feather_weights, gain_compensation, overlap_statistics, warp_maps
from workers.config import MosaicConfig
from workers.raster_io import open_block_writer, translate_to_cog
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json, write_json

OVERVIEW_PX = 768  # longest side of the low-resolution render used for gains and the footprint


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``mosaic.tif`` (COG, RGB + mask) and ``footprints.geojson``-ready ``coverage.json``."""
    geo = read_json(ws.georef_file())
    frames = ws.load_composed_frames()
    homs = {int(k): np.array(H) for k, H in read_json(ws.alignment_file())["homographies"].items()}
    out_to_plane = np.array(geo["output_to_plane"])
    # output pixel -> frame pixel, for every frame
    to_frame = {k: np.linalg.inv(H) @ out_to_plane for k, H in homs.items()}
    boxes = {k: _output_box(M, frames[k], geo["width"], geo["height"]) for k, M in to_frame.items()}
    progress(0.0, "gain compensation")
    gains, coverage = _gains_and_coverage(ws, frames, to_frame, geo, cfg.gain_compensation)
    write_json(ws.root / "coverage.json", coverage)
    blocks = [(x, y) for y in range(0, geo["height"], cfg.block_px) for x in range(0, geo["width"], cfg.block_px)]
    tmp = ws.root / "mosaic.tmp.tif"
    transform = geo["transform"] if geo["georeferenced"] else None
    with open_block_writer(tmp, geo["width"], geo["height"], geo["epsg"], transform) as write:
        for n, (x, y) in enumerate(blocks):
            progress(0.1 + 0.75 * n / len(blocks), f"block {n + 1}/{len(blocks)}")
            w, h = min(cfg.block_px, geo["width"] - x), min(cfg.block_px, geo["height"] - y)
            rgb, mask = _compose_block(ws, frames, to_frame, boxes, gains, (x, y, w, h), cfg.feather_px)
            write(Window(x, y, w, h), rgb, mask)
    progress(0.85, "writing COG with overviews")
    translate_to_cog(tmp, ws.mosaic_file(), cfg.cog_compression)
    tmp.unlink(missing_ok=True)
    progress(1.0, f"block {len(blocks)}/{len(blocks)}")
    return {"width": geo["width"], "height": geo["height"], "blocks": len(blocks),
            "gains": {frames[k]["name"]: g for k, g in gains.items()}}


def _output_box(to_frame: np.ndarray, frame: dict[str, Any], width: int, height: int) -> tuple[int, int, int, int]:
    """Output pixel bbox (x0, y0, x1, y1) of a frame, clipped to the grid."""
    c = apply_homography(np.linalg.inv(to_frame), frame_corners(frame["width"], frame["height"]))
    x0, y0 = np.floor(c.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(c.max(axis=0)).astype(int) + 1
    return max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)


def _compose_block(ws: JobWorkspace, frames: dict[int, dict[str, Any]], to_frame: dict[int, np.ndarray],
                   boxes: dict[int, tuple[int, int, int, int]], gains: dict[int, np.ndarray],
                   window: tuple[int, int, int, int], feather_px: float) -> tuple[np.ndarray, np.ndarray]:
    x, y, w, h = window
    acc = np.zeros((h, w, 3), np.float32)
    wsum = np.zeros((h, w), np.float32)
    for k, (bx0, by0, bx1, by1) in boxes.items():
        if bx1 <= x or by1 <= y or bx0 >= x + w or by0 >= y + h:
            continue
        f = frames[k]
        map_x, map_y = warp_maps(to_frame[k], x, y, w, h)
        weight = feather_weights(map_x, map_y, f["width"], f["height"], feather_px)
        if not weight.any():
            continue
        pixels = _sample(ws.load_compose_image(k, mmap=True), map_x, map_y, weight > 0)
        acc += weight[..., None] * pixels * gains[k][None, None, :].astype(np.float32)
        wsum += weight
    mask = wsum > 0
    bgr = np.clip(acc / np.maximum(wsum, 1e-6)[..., None] + 0.5, 0, 255).astype(np.uint8)
    bgr[~mask] = 0
    return bgr[..., ::-1], mask


def _sample(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` (H, W, 3) at the maps, reading only the rows/columns needed."""
    xs, ys = map_x[valid], map_y[valid]
    c0, r0 = max(int(math.floor(xs.min())) - 1, 0), max(int(math.floor(ys.min())) - 1, 0)
    c1, r1 = min(int(math.ceil(xs.max())) + 2, image.shape[1]), min(int(math.ceil(ys.max())) + 2, image.shape[0])
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    out = cv2.remap(crop, map_x - c0, map_y - r0, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.astype(np.float32)


def _gains_and_coverage(ws: JobWorkspace, frames: dict[int, dict[str, Any]], to_frame: dict[int, np.ndarray],
                        geo: dict[str, Any], enabled: bool) -> tuple[dict[int, np.ndarray], dict[str, Any]]:
    """Gains from a low-resolution render of every frame, and the mosaic's coverage outline."""
    r = min(1.0, OVERVIEW_PX / max(geo["width"], geo["height"]))
    lw, lh = max(1, round(geo["width"] * r)), max(1, round(geo["height"] * r))
    low_to_out = np.diag([1 / r, 1 / r, 1.0])
    keys = sorted(to_frame)
    images, masks = [], []
    for k in keys:
        f = frames[k]
        map_x, map_y = warp_maps(to_frame[k] @ low_to_out, 0, 0, lw, lh)
        inside = feather_weights(map_x, map_y, f["width"], f["height"], 2.0 / r) >= 1.0
        image = ws.load_compose_image(k, mmap=True)
        images.append(_sample(image, map_x, map_y, inside) if inside.any() else np.zeros((lh, lw, 3), np.float32))
        masks.append(inside)
    gains = np.ones((len(keys), 3))
    if enabled:
        means, counts = overlap_statistics(images, masks)
        gains = gain_compensation(means, counts)
    union = np.any(masks, axis=0).astype(np.uint8) if masks else np.zeros((lh, lw), np.uint8)
    contours, _ = cv2.findContours(union, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outline = [(c.reshape(-1, 2).astype(np.float64) + 0.5) / r for c in contours if len(c) >= 3]
    return ({k: gains[n] for n, k in enumerate(keys)},
            {"outline_px": [o.tolist() for o in outline], "area_fraction": float(union.mean())})
