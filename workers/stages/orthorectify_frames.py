"""Stage ``orthorectify_frames``: every adjusted frame onto the ground, for ``compose_mosaic``.

Each frame is undistorted through its adjusted camera; the undistorted frame and the ground plane
``Z = z0`` are then related by a homography, so the composer's warping and blending apply unchanged.
With ``ortho_surface: tie_points`` (the default) each frame is first rendered as if its ground were that
plane: every pixel takes what the camera sees of the surface gridded from the adjusted tie points above or
below the plane point it stands for (``sfm.relief_maps``), so hills and hollows land at their map positions
instead of being displaced by their relief. Frames that see the horizon are cut below it (and beyond
``max_ground_range`` flying heights), since ground far away is smeared over a huge area by the projection.
"""

from __future__ import annotations

import shutil
from typing import Any

import cv2
import numpy as np

from workers.algorithms.geometry import Camera
from workers.algorithms.mosaic import MAX_OUTPUT_PIXELS, map_grid, output_size_problem, pixel_grid
from workers.algorithms.sfm import GroundSurface, ground_crop, ground_surface, relief_maps
from workers.config import MosaicConfig
from workers.pipeline import PipelineError
from workers.records import Alignment, Georef, RejectedFrame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


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
    surface, surface_note = _surface(ws, cfg)
    homographies: dict[int, np.ndarray] = {}
    sizes: dict[int, tuple[int, int]] = {}
    rejected = [RejectedFrame.from_json(r) for r in adjusted["not_registered"]]
    for n, (k, (R, C)) in enumerate(sorted(poses.items())):
        progress(n / len(poses), f"frame {n + 1}/{len(poses)}")
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
    problem = output_size_problem(grid.width, grid.height, None, shutil.disk_usage(ws.root).free)
    if problem:
        raise PipelineError(problem)
    ws.save_georef(grid)
    progress(1.0, f"{len(homographies)} frames at {gsd * 100:.1f} cm/px")
    return {
        "frames": len(homographies),
        "rejected": len(rejected),
        "gsd_m": gsd,
        "ground_z": z0,
        "surface": surface_note,
    }


def _surface(ws: JobWorkspace, cfg: MosaicConfig) -> tuple[GroundSurface | None, dict[str, Any]]:
    """The surface frames are projected onto, and what the report says of it."""
    if cfg.ortho_surface == "plane":
        return None, {"kind": "plane", "why": "options.ortho_surface is 'plane'"}
    points = ws.load_tie_points()
    surface = ground_surface(points)
    if surface is None:
        return None, {"kind": "plane", "why": f"only {len(points)} tie points: too few for a surface"}
    heights = surface.heights
    return surface, {
        "kind": "tie_points",
        "points": len(points),
        "cell_m": round(surface.cell, 3),
        "size": [int(heights.shape[1]), int(heights.shape[0])],
        "height_range_m": [round(float(heights.min()), 3), round(float(heights.max()), 3)],
    }


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
