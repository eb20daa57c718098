"""Stage ``orthorectify_frames``: every adjusted frame onto the ground, for ``compose_mosaic``.

Each frame is undistorted through its adjusted camera; the undistorted frame and the ground plane
``Z = z0`` are then related by a homography, so the composer's warping and blending apply unchanged.
With ``ortho_surface: tie_points`` each frame is first rendered as if its ground were that
plane: every pixel takes what the camera sees of the surface gridded from the adjusted tie points above or
below the plane point it stands for (``sfm.relief_maps``), so hills and hollows land at their map positions
instead of being displaced by their relief. With ``ortho_surface: dense`` (the default) that surface is refined
where frames overlap: neighbouring pairs are rectified through the adjusted cameras (``stereo.posed_pair``),
matched by semi-global matching at a reduced size (``disparity.match_pair``), triangulated, and their points
fused into a finer grid (``sfm.dense_surface``); the tie-point surface fills the rest. The surface used is
saved (``ortho_surface.npz``) and the report's ``surface`` says which it was; on a georeferenced job it is also
written as ``dsm.tif`` (float32 m in the GPS altitudes' datum, on the mosaic's grid coarsened to about the
surface's cell) with ``dsm_mask.tif`` (1 measured, 2 interpolated) and the shaded relief the viewer tiles, only
where it rests on measurements (``sfm.surface_raster``). Frames that see the horizon
are cut below it (and beyond ``max_ground_range`` flying heights), since ground far away is smeared over a
huge area by the projection.
"""

from __future__ import annotations

import shutil
import time
from typing import Any

import cv2
import numpy as np

from workers.algorithms.disparity import match_pair
from workers.algorithms.geometry import Camera
from workers.algorithms.mosaic import MAX_OUTPUT_PIXELS, map_grid, output_size_problem, pixel_grid
from workers.algorithms.sfm import (
    SURFACE_INTERPOLATED,
    SURFACE_MEASURED,
    GroundSurface,
    RasterGrid,
    cell_medians,
    dense_grid,
    dense_surface,
    ground_crop,
    ground_surface,
    relief_maps,
    surface_raster,
)
from workers.algorithms.stereo import (
    TERRAIN,
    disparity_range,
    grey8,
    ground_samples,
    legend,
    neighbour_pairs,
    posed_pair,
    reduced_view,
    remap_pair,
    shaded_relief,
    value_range,
    view_counts,
)
from workers.config import MosaicConfig
from workers.pipeline import PipelineError
from workers.raster_io import write_dsm
from workers.records import Alignment, Georef, RejectedFrame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

DENSE_CELL_PX = 4  # the dense surface's cell, in pixels of the reduced frames matched
DENSE_STRIDE = 2  # every this many rows and columns of a disparity map are triangulated (neighbours correlate)
DENSE_SHARE = 0.3  # of the stage's time the dense pairs take (Brighton: 1.7 of 10.8 s; 12 small frames: 1.8 of 2.6)
COVERAGE_SAMPLES = 40_000  # cells the dense surface's coverage is measured on
Pose = tuple[np.ndarray, np.ndarray]


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``ortho/frame_NNNN.npy`` (undistorted), ``alignment.json`` and ``georef.json``."""
    frames = {f.index: f for f in ws.load_frames()}
    adjusted = ws.load_cameras()
    camera = Camera.from_json(adjusted["camera"])
    ideal = camera.replace(k1=0.0, k2=0.0, k3=0.0, t1=0.0, t2=0.0)
    z0 = adjusted["ground_z"] if cfg.ground_elevation_m is None else cfg.ground_elevation_m
    poses = {int(k): (np.array(p["R"]), np.array(p["C"])) for k, p in adjusted["poses"].items()}
    gsd = float(np.median([(C[2] - z0) / ideal.fx for _, C in poses.values()]))
    if not gsd > 0:
        raise PipelineError(f"the cameras are not above the ground plane at {z0:.1f} m; set ground_elevation_m")
    plane_from_ground = np.diag([1.0 / gsd, -1.0 / gsd, 1.0])  # plane px: x east, y south
    maps = camera.undistort_maps(ideal)
    surface, measured, surface_note = _surface(ws, cfg, camera, poses, z0, progress)
    ws.save_ortho_surface(surface)
    start = DENSE_SHARE if surface_note["kind"] == "dense" else 0.0  # of the progress bar
    homographies: dict[int, np.ndarray] = {}
    sizes: dict[int, tuple[int, int]] = {}
    rejected = [RejectedFrame.from_json(r) for r in adjusted["not_registered"]]
    for n, (k, (R, C)) in enumerate(sorted(poses.items())):
        progress(start + (1 - start) * n / len(poses), f"frame {n + 1}/{len(poses)}")
        image_from_ground = ideal.matrix() @ R @ np.array([[1, 0, -C[0]], [0, 1, -C[1]], [0, 0, z0 - C[2]]])
        crop = ground_crop(R, C, z0, ideal, cfg.max_ground_range)
        if crop is None:
            reason = f"looks at the horizon: too little ground within {cfg.max_ground_range:g} flying heights"
            rejected.append(RejectedFrame(k, frames[k].name, reason))
            continue
        x0, y0, x1, y1 = crop
        if surface is None:
            undistorted = cv2.remap(ws.load_working_image(k), maps[0], maps[1], cv2.INTER_LINEAR)[y0:y1, x0:x1]
        else:
            relief = relief_maps(R, C, camera, z0, crop, surface)
            undistorted = cv2.remap(
                ws.load_working_image(k), *relief, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        ws.save_ortho_image(k, undistorted)
        shift = np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]])  # cropped px -> full px
        homographies[k] = plane_from_ground @ np.linalg.inv(image_from_ground) @ shift
        sizes[k] = (x1 - x0, y1 - y0)
    if not homographies:
        raise PipelineError("no frame sees enough ground to orthorectify")
    report = adjusted["report"]
    ws.save_alignment(
        Alignment(
            mode="ortho",
            reference=min(homographies),
            homographies=homographies,
            frame_sizes=sizes,
            ground_z=z0,
            tie_point_rms_px=report["rms_px"],
            tie_points=report["observations"],
            rejected=rejected,
        )
    )
    grid = _grid(adjusted["world"], homographies, sizes, gsd, report["gps_residual_rms_m"])
    free = shutil.disk_usage(ws.root).free
    problem = output_size_problem(grid.width, grid.height, None, free, cfg.cog_compression)
    if problem:
        raise PipelineError(problem)
    ws.save_georef(grid)
    footprints = [_footprint(H, sizes[k], gsd) for k, H in homographies.items()]
    dsm = _dsm(ws, cfg, (surface, measured), footprints, grid, adjusted["world"])
    progress(1.0, f"{len(homographies)} frames at {gsd * 100:.1f} cm/px")
    return {
        "frames": len(homographies),
        "rejected": len(rejected),
        "gsd_m": gsd,
        "ground_z": z0,
        "surface": surface_note,
        "dsm": dsm,
    }


def _surface(
    ws: JobWorkspace, cfg: MosaicConfig, camera: Camera, poses: dict[int, Pose], z0: float, progress: ProgressFn
) -> tuple[GroundSurface | None, np.ndarray | None, dict[str, Any]]:
    """The surface frames are projected onto, the cells of it dense stereo measured (None: no dense surface),
    and what the report says of it."""
    if cfg.ortho_surface == "plane":
        return None, None, {"kind": "plane", "why": "options.ortho_surface is 'plane'"}
    points = ws.load_tie_points()
    surface = ground_surface(points)
    if surface is None:
        return None, None, {"kind": "plane", "why": f"only {len(points)} tie points: too few for a surface"}
    note = {"kind": "tie_points", "points": len(points), **_grid_note(surface)}
    if cfg.ortho_surface != "dense":
        return surface, None, note
    return _dense(ws, cfg.ortho_dense_px, camera, poses, z0, (surface, note), points, progress)


def _dense(
    ws: JobWorkspace,
    matched_px: int,
    camera: Camera,
    poses: dict[int, Pose],
    z0: float,
    base: tuple[GroundSurface, dict[str, Any]],
    points: np.ndarray,
    progress: ProgressFn,
) -> tuple[GroundSurface, np.ndarray | None, dict[str, Any]]:
    """The tie points' surface refined by dense stereo between neighbouring frames, its cells stereo measured,
    and its report; the tie points' surface (``base``), None and why, when no pair overlaps or matches."""
    started = time.perf_counter()
    surface, note = base
    pairs = neighbour_pairs(camera, poses, z0)
    if not pairs:
        return surface, None, {**note, "why": "no pair of frames overlaps enough for dense stereo"}
    scale = min(1.0, matched_px / max(camera.width, camera.height))
    gsd = float(np.median([C[2] - z0 for _, C in poses.values()])) / (camera.fx * scale)
    footprints = [ground_samples(camera, poses[k], z0)[:, :2] for k in sorted({k for p in pairs for k in p})]
    grid = dense_grid(surface, np.concatenate(footprints), DENSE_CELL_PX * gsd)
    cells, heights, matched, count = [], [], 0, 0
    for n, (i, j) in enumerate(pairs):
        progress(DENSE_SHARE * n / len(pairs), f"dense stereo: pair {n + 1}/{len(pairs)}")
        dense = _pair_points(ws, camera, poses[i], poses[j], (i, j), z0, scale, points)
        part = cell_medians(dense, grid)  # each pair reduced to the grid as it comes
        cells.append(part[0])
        heights.append(part[1])
        matched, count = matched + int(len(dense) > 0), count + len(dense)
    if count == 0:
        why = f"none of {len(pairs)} overlapping pairs of frames matched for dense stereo"
        return surface, None, {**note, "why": why}
    refined, measured = dense_surface(np.concatenate(cells), np.concatenate(heights), surface, grid)
    return (
        refined,
        measured,
        {
            "kind": "dense",
            "points": len(points),
            "pairs": matched,
            "pairs_overlapping": len(pairs),
            "dense_points": count,
            "coverage": _coverage(refined, measured, camera, poses),
            "matched_px": max(round(camera.width * scale), round(camera.height * scale)),
            "seconds": round(time.perf_counter() - started, 2),
            **_grid_note(refined),
        },
    )


def _footprint(H: np.ndarray, size: tuple[int, int], gsd: float) -> np.ndarray:
    """(4, 2) world x, y of an orthorectified frame's corners on the ground plane (plane px: x east, y south)."""
    w, h = size
    plane = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float) @ H.T
    return plane[:, :2] / plane[:, 2:] * [gsd, -gsd]


def _dsm(
    ws: JobWorkspace,
    cfg: MosaicConfig,
    surface: tuple[GroundSurface | None, np.ndarray | None],
    footprints: list[np.ndarray],
    grid: Georef,
    world: dict[str, Any],
) -> dict[str, Any] | None:
    """Write the surface as the job's DSM on the mosaic's grid, coarsened to about the surface's cell, and say
    what it holds; None (and no DSM left from an earlier run) without a surface or map coordinates."""
    heights, measured = surface
    if heights is None or not grid.georeferenced or grid.epsg is None or grid.gsd_m is None:
        ws.remove_dsm()
        return None
    step = max(1, round(heights.cell / grid.gsd_m))
    cell = step * grid.gsd_m
    west, north = grid.transform[2], grid.transform[5]
    raster = RasterGrid(
        west - world["easting0"], north - world["northing0"], cell, -(-grid.height // step), -(-grid.width // step)
    )
    height, state = surface_raster(heights, measured, ws.load_tie_points(), footprints, raster)
    has = state > 0
    lo, hi = value_range(height, has)
    write_dsm(
        (ws.dsm_path(), ws.dsm_mask_path(), ws.dsm_view_path(), ws.view_scratch_path("dsm")),
        height,
        state,
        shaded_relief(height, cell, lo, hi, TERRAIN),
        transform=(cell, 0.0, west, 0.0, -cell, north),
        epsg=grid.epsg,
        compression="deflate" if cfg.cog_compression == "jpeg" else cfg.cog_compression,
        description="DSM, heights in the photos' GPS altitude datum (m), the surface the ortho frames went onto",
    )
    cells = int(has.sum())
    return {
        "surface": "dsm",
        "epsg": grid.epsg,
        "resolution_m": round(cell, 4),
        "size": [int(state.shape[1]), int(state.shape[0])],
        "cells": cells,
        "measured_share": round(int((state == SURFACE_MEASURED).sum()) / max(cells, 1), 4),
        "filled_share": round(int((state == SURFACE_INTERPOLATED).sum()) / max(cells, 1), 4),
        "height_range_m": [round(float(height[has].min()), 3), round(float(height[has].max()), 3)] if cells else None,
        "legend": {"units": "m", "stops": legend(lo, hi, TERRAIN)},
    }


def _coverage(surface: GroundSurface, measured: np.ndarray, camera: Camera, poses: dict[int, Pose]) -> float:
    """Share of the surface's cells that two or more frames see (where dense stereo can reach) that it measured,
    from at most about ``COVERAGE_SAMPLES`` cells (every frame is traced to each: a long flight's grid is large)."""
    step = max(1, int(np.sqrt(measured.size / COVERAGE_SAMPLES)))
    rows, cols = np.arange(0, measured.shape[0], step), np.arange(0, measured.shape[1], step)
    x, y = np.meshgrid(surface.x0 + cols * surface.cell, surface.y0 + rows * surface.cell)
    z = surface.heights[np.ix_(rows, cols)]
    counts = view_counts(camera, poses, np.column_stack([x.ravel(), y.ravel(), z.ravel()]))
    overlap = counts.reshape(z.shape) >= 2
    return round(float(measured[np.ix_(rows, cols)][overlap].mean()), 4) if overlap.any() else 0.0


def _grid_note(surface: GroundSurface) -> dict[str, Any]:
    heights = surface.heights
    return {
        "cell_m": round(surface.cell, 3),
        "size": [int(heights.shape[1]), int(heights.shape[0])],
        "height_range_m": [round(float(heights.min()), 3), round(float(heights.max()), 3)],
    }


def _pair_points(
    ws: JobWorkspace,
    camera: Camera,
    left: Pose,
    right: Pose,
    frames: tuple[int, int],
    z0: float,
    scale: float,
    tie_points: np.ndarray,
) -> np.ndarray:
    """(N, 3) world points of one pair's dense disparities (SGBM, checked, unfilled); none when the pair cannot
    be rectified or no tie point shows its disparity range."""
    pair = posed_pair(camera, left, right, z0, camera.fx * scale)
    if pair is None:
        return np.zeros((0, 3))
    left_px, right_px, front = pair.project(tie_points)
    inside = front & _on_canvas(left_px, pair.width, pair.height) & _on_canvas(right_px, pair.width, pair.height)
    span = disparity_range(left_px[inside], right_px[inside])
    if span is None:
        return np.zeros((0, 3))
    views = [reduced_view(grey8(ws.load_working_image(k)), camera, scale) for k in frames]
    maps = (*pair.maps(views[0][1], left[0], "left"), *pair.maps(views[1][1], right[0], "right"))
    image_l, image_r, valid_l, valid_r = remap_pair(maps, views[0][0], views[1][0])
    result = match_pair(image_l, image_r, "sgbm", *span, valid_left=valid_l, valid_right=valid_r, fill=False)
    sampled = result.disparity[::DENSE_STRIDE, ::DENSE_STRIDE]
    rows, cols = np.nonzero(np.isfinite(sampled))
    return pair.triangulate(cols * DENSE_STRIDE, rows * DENSE_STRIDE, sampled[rows, cols])


def _on_canvas(px: np.ndarray, width: int, height: int) -> np.ndarray:
    return np.asarray((px[:, 0] >= 0) & (px[:, 0] <= width - 1) & (px[:, 1] >= 0) & (px[:, 1] <= height - 1))


def _grid(
    world: dict[str, Any],
    homographies: dict[int, np.ndarray],
    sizes: dict[int, tuple[int, int]],
    gsd: float,
    gps_residual_rms_m: float | None,
) -> Georef:
    corners = []
    for k, H in homographies.items():
        w, h = sizes[k]
        pts = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float) @ H.T
        corners.append(pts[:, :2] / pts[:, 2:])
    plane = np.concatenate(corners)
    if world.get("epsg"):
        plane_to_map = np.array([[gsd, 0.0, world["easting0"]], [0.0, -gsd, world["northing0"]], [0.0, 0.0, 1.0]])
        grid = Georef(
            georeferenced=True,
            reason="",
            epsg=world["epsg"],
            plane_to_map=plane_to_map,
            gsd_m=gsd,
            gps_residual_rms_m=gps_residual_rms_m,
            **map_grid(plane, plane_to_map),
        )
    else:
        reason = world.get("note", "no GPS or GCPs: arbitrary datum")
        grid = Georef(
            georeferenced=False,
            reason=reason,
            epsg=None,
            plane_to_map=np.eye(3),
            gsd_m=None,
            gps_residual_rms_m=gps_residual_rms_m,
            **pixel_grid(plane),
        )
    if grid.width * grid.height > MAX_OUTPUT_PIXELS:
        raise PipelineError(f"the orthomosaic would be {grid.width}x{grid.height} px; lower max_ground_range")
    return grid
