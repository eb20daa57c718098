"""Stage ``orthorectify_frames``: every adjusted frame onto the ground plane, for ``compose_mosaic``.

Each frame is undistorted through its adjusted camera; the undistorted frame and the ground plane
``Z = z0`` are then related by a homography, so the composer's warping and blending apply unchanged.
Frames that see the horizon are cut below it (and beyond ``max_ground_range`` flying heights), since
ground far away is smeared over a huge area by the projection.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from workers.algorithms.geometry import Camera
from workers.algorithms.mosaic import MAX_OUTPUT_PIXELS, map_grid, pixel_grid
from workers.config import MosaicConfig
from workers.pipeline import PipelineError
from workers.records import Alignment, Georef, RejectedFrame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

MIN_KEPT_ROWS = 0.1  # a frame cut to less than this share of its rows (or columns) is left out


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
        undistorted = cv2.remap(ws.load_working_image(k), maps[0], maps[1], cv2.INTER_LINEAR)[y0:y1, x0:x1]
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
    ws.save_georef(_grid(adjusted["world"], homographies, sizes, gsd, report["gps_residual_rms_m"]))
    progress(1.0, f"{len(homographies)} frames at {gsd * 100:.1f} cm/px")
    return {"frames": len(homographies), "rejected": len(rejected), "gsd_m": gsd, "ground_z": z0}


def ground_crop(
    R: np.ndarray, C: np.ndarray, z0: float, camera: Camera, max_range: float
) -> tuple[int, int, int, int] | None:
    """The part of the frame, ``(x0, y0, x1, y1)`` px (end exclusive), that sees the ground nearby.

    A pixel qualifies if its ray meets the plane ``z0`` in front of the camera within ``max_range``
    flying heights of the nadir point. That region of the plane is a disk, so its image is convex and
    a rectangle whose four corners qualify lies wholly inside it. The whole frame when it qualifies;
    else the frame with one edge moved in as little as needed; None when less than
    ``MIN_KEPT_ROWS`` of the frame would remain.
    """
    height = C[2] - z0
    to_world = R.T @ np.linalg.inv(camera.matrix())  # pixel -> ray direction in the world

    def corners_ok(x0: float, y0: float, x1: float, y1: float) -> bool:
        px = np.array([[x0, y0, 1], [x1 - 1, y0, 1], [x1 - 1, y1 - 1, 1], [x0, y1 - 1, 1]], float)
        rays = px @ to_world.T
        if np.any(rays[:, 2] >= -1e-9):  # level or upwards: never meets the ground in front
            return False
        reach = height / -rays[:, 2]  # ray length to the plane
        return bool(np.all(np.linalg.norm(rays[:, :2] * reach[:, None], axis=1) <= max_range * height))

    w, h = camera.width, camera.height
    if corners_ok(0, 0, w, h):
        return 0, 0, w, h
    best: tuple[int, int, int, int] | None = None
    for edge in range(4):  # move the top, bottom, left or right edge inwards
        size = h if edge < 2 else w
        lo, hi = 0, int(size * (1 - MIN_KEPT_ROWS))
        if not corners_ok(*_moved(edge, hi, w, h)):
            continue
        while hi - lo > 1:  # smallest move that qualifies
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if corners_ok(*_moved(edge, mid, w, h)) else (mid, hi)
        crop = _moved(edge, hi, w, h)
        if best is None or _area(crop) > _area(best):
            best = crop
    return best


def _moved(edge: int, by: int, w: int, h: int) -> tuple[int, int, int, int]:
    return [(0, by, w, h), (0, 0, w, h - by), (by, 0, w, h), (0, 0, w - by, h)][edge]


def _area(crop: tuple[int, int, int, int]) -> int:
    return (crop[2] - crop[0]) * (crop[3] - crop[1])


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
