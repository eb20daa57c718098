"""Stage ``build_dsm``: the disparity map back to the ground.

An RPC pair's pixels are triangulated through both RPC models (heights above the ellipsoid), gridded on the
UTM zone of their footprint at the left photo's ground sample distance (or ``dsm_resolution_m``) and written
as ``dsm.tif`` (float32 m, nodata -9999), ``dsm_mask.tif`` (0 no data, 1 measured, 2 filled) and the shaded
relief the viewer tiles. A rig pair's disparities become ``depth.tif`` through the rectification's Q matrix.
Other pairs have no scale: the stage has nothing to add.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from workers.algorithms.geometry import lonlat_to_utm, utm_epsg
from workers.algorithms.stereo import (
    FILLED,
    MEASURED,
    NO_DATA,
    TERRAIN,
    Rectification,
    Rpc,
    grid_dsm,
    legend,
    rpc_correspondences,
    shaded_relief,
    triangulate_rpc,
    value_range,
)
from workers.config import StereoDemConfig
from workers.pipeline import PipelineError
from workers.raster_io import write_array_cog, write_dsm
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

DEFAULT_FILL_CELLS = 64  # DSM holes are filled at most this many cells from a height (max_fill_m unset)


def run(ws: JobWorkspace, cfg: StereoDemConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    info = ws.load_rectification()
    if info["geometry"] == "rpc":
        return _dsm(ws, cfg, info, progress)
    if info["geometry"] == "rig":
        return _depth(ws, cfg, info)
    article = "an" if info["geometry"][:1] in "aeiou" else "a"
    return {
        "surface": None,
        "why": f"{article} {info['geometry']} pair has no camera model: its disparity is all it gives",
    }


def _dsm(ws: JobWorkspace, cfg: StereoDemConfig, info: dict[str, Any], progress: ProgressFn) -> dict[str, Any]:
    rect = Rectification.from_json(info["rectification"])
    rpc_l, rpc_r = (Rpc.from_dict(r) for r in info["rpcs"])
    arrays = ws.load_disparity_arrays()
    rows, cols = np.nonzero(np.isfinite(arrays["dense"]))
    if len(rows) == 0:
        raise PipelineError("no pixel of the pair was matched: there is nothing to triangulate")
    size_l = _left_size(ws)
    corr = rpc_correspondences(rpc_l, rpc_r, size_l, (info["heights_m"][0], info["heights_m"][1]))
    progress(0.1, f"triangulating {len(rows)} pixels")
    lon, lat, height, residual = triangulate_rpc(
        rpc_l, rpc_r, corr, rect, cols.astype(np.float64), rows.astype(np.float64), arrays["dense"][rows, cols]
    )
    epsg = utm_epsg(float(np.median(lat)), float(np.median(lon)))
    east_north = lonlat_to_utm(np.column_stack([lon, lat]), epsg)
    resolution = cfg.dsm_resolution_m or round(float(info["gsd_m"]), 3)
    fill_cells = int(np.ceil(cfg.max_fill_m / resolution)) if cfg.max_fill_m else DEFAULT_FILL_CELLS
    progress(0.6, "gridding")
    try:
        dsm = grid_dsm(
            east_north[:, 0],
            east_north[:, 1],
            height,
            ~arrays["filled"][rows, cols],
            resolution,
            epsg,
            fill=cfg.fill,
            max_fill_cells=fill_cells,
        )
    except ValueError as exc:
        raise PipelineError(f"cannot grid the DSM: {exc}") from None
    progress(0.8, "writing")
    has = dsm.state != NO_DATA
    lo, hi = value_range(dsm.height, has)
    write_dsm(
        (ws.dsm_path(), ws.dsm_mask_path(), ws.dsm_view_path(), ws.view_scratch_path("dsm")),
        dsm.height,
        dsm.state,
        shaded_relief(dsm.height, resolution, lo, hi, TERRAIN),
        transform=dsm.transform,
        epsg=epsg,
        compression=cfg.cog_compression,
        description="DSM, heights above the WGS 84 ellipsoid (m), from a stereo pair",
    )
    cells = int(has.sum())
    return {
        "surface": "dsm",
        "epsg": epsg,
        "resolution_m": resolution,
        "size": [int(dsm.height.shape[1]), int(dsm.height.shape[0])],
        "cells": cells,
        "measured_share": round(int((dsm.state == MEASURED).sum()) / max(cells, 1), 4),
        "filled_share": round(int((dsm.state == FILLED).sum()) / max(cells, 1), 4),
        "height_range_m": [float(np.nanmin(dsm.height)), float(np.nanmax(dsm.height))],
        "triangulation_residual_px": round(float(np.median(residual)), 4),
        "legend": {"units": "m", "stops": legend(lo, hi, TERRAIN)},
    }


def _left_size(ws: JobWorkspace) -> tuple[int, int]:
    left = next(f for f in ws.load_inputs() if f["side"] == "left")
    return int(left["width"]), int(left["height"])


def _depth(ws: JobWorkspace, cfg: StereoDemConfig, info: dict[str, Any]) -> dict[str, Any]:
    rect = Rectification.from_json(info["rectification"])
    if rect.q is None:
        raise PipelineError("the rig's rectification has no disparity-to-depth matrix")
    dense = ws.load_disparity_arrays()["dense"]
    points = cv2.reprojectImageTo3D(np.nan_to_num(dense, nan=0.0).astype(np.float32), rect.q.astype(np.float32))
    depth = np.where(np.isfinite(dense) & (np.abs(dense) > 1e-6), points[..., 2], np.nan).astype(np.float32)
    depth[~np.isfinite(depth)] = np.nan
    write_array_cog(ws.depth_path(), depth, nodata=float("nan"), compression=cfg.cog_compression)
    valid = np.isfinite(depth)
    return {
        "surface": "depth",
        "units": "the rig's (its calibration target's, e.g. mm), along the rectified left camera's axis",
        "depth_range": [float(np.nanmin(depth)), float(np.nanmax(depth))] if valid.any() else None,
        "valid_share": round(float(valid.mean()), 4),
    }
