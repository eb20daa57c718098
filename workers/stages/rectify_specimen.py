"""Stage ``rectify_specimen``: every load stage's photos rendered orthographically onto the specimen's plane
(a plate, or a mesh's best-fit or chosen plane with its heights and occlusions)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from workers.algorithms.camera import Camera
from workers.algorithms.mesh import PlaneFrame, best_fit_plane, plane_through, read_mesh
from workers.algorithms.resection import pose_from_json
from workers.algorithms.specimen_surface import (
    Surface,
    mesh_surface,
    photo_depth,
    plate_surface,
    raster_shape,
    rectification_maps,
)
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError
from workers.stages.orient_camera import survey_camera
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json

# Lanczos rather than bilinear or bicubic: where the output is finer than the photo, those draw the photo's
# pixel lattice as streaks that the crack detector takes for hairline cracks
INTERPOLATION = cv2.INTER_LANCZOS4
BLOCK_PIXELS = 1 << 20  # raster pixels mapped at once: bounds the memory of the maps (~60 B per pixel)
MAX_RASTER_PIXELS = 200_000_000  # a larger raster is refused before anything is allocated (~26 B/px held)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the surface (``rectified/surface.npz``) and per load stage ``rectified/stage_NN.npz``:
    (H, W, 3) BGR image and the mask its photos see."""
    camera = survey_camera(cfg)
    poses = {p["image"]: pose_from_json(p) for p in read_json(ws.orientation_file())["photos"]}
    paths = {f["name"]: f["path"] for f in ws.load_inputs()}
    surface = build_surface(ws, cfg, np.mean([C for _, C in poses.values()], axis=0))
    ws.save_surface(surface.frame.origin, surface.frame.axes, surface.height, surface.mm_per_px)
    coverage: list[float] = []
    photo_mm_per_px: list[float] = []
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"stage {s + 1}/{len(cfg.stages)}")
        views = [(_read(paths[p.image]), *poses[p.image]) for p in stage.photos]
        image, mask, density = compose_stage(camera, views, surface, cfg.compose)
        if not mask.any():
            raise PipelineError(f"stage {stage.label!r}: its photos see no part of the specimen; "
                                "check the control points' model coordinates")
        ws.save_rectified(s, image, mask)
        coverage.append(round(float(mask.mean()), 4))
        # the photos' own sampling on the specimen: a raster much finer than this shows resampled grain
        photo_mm_per_px.append(round(float(np.median(1.0 / np.sqrt(density[mask]))), 4))
    progress(1.0, f"{len(cfg.stages)} stage(s) rectified")
    return {"stages": len(cfg.stages), "width_px": surface.shape[1], "height_px": surface.shape[0],
            "coverage": coverage, "photo_mm_per_px": photo_mm_per_px, "plane": surface.frame.to_json()}


def build_surface(ws: JobWorkspace, cfg: CrackSurveyConfig, camera_side: np.ndarray) -> Surface:
    """The plate, or the mesh rasterised onto its chosen or best-fit plane on the cameras' side."""
    specimen = cfg.specimen
    if specimen.mesh is None:
        assert specimen.width_mm is not None and specimen.height_mm is not None  # the config's validator
        _check_size(specimen.width_mm, specimen.height_mm, cfg.mm_per_px)
        return plate_surface(specimen.width_mm, specimen.height_mm, cfg.mm_per_px)
    try:
        mesh = read_mesh(ws.specimen_model_file(specimen.mesh).read_bytes(), specimen.mesh)
        frame = best_fit_plane(mesh) if specimen.plane is None else plane_through(mesh, np.array(specimen.plane))
    except (OSError, ValueError) as exc:
        raise PipelineError(f"specimen model: {exc}") from None
    extent = frame.to_plane(mesh.vertices).max(axis=0)
    _check_size(float(extent[0]), float(extent[1]), cfg.mm_per_px)
    return mesh_surface(mesh, frame, cfg.mm_per_px, camera_side)


def _check_size(width_mm: float, height_mm: float, mm_per_px: float) -> None:
    rows, cols = raster_shape(width_mm, height_mm, mm_per_px)
    if rows * cols > MAX_RASTER_PIXELS:
        raise PipelineError(f"the specimen is {cols} x {rows} px at {mm_per_px} mm/px, more than "
                            f"{MAX_RASTER_PIXELS} px; choose a coarser mm_per_px")


def load_surface(ws: JobWorkspace) -> Surface:
    """The surface ``run`` wrote (without the mesh: heights and plane are all later stages need)."""
    origin, axes, height, mm_per_px = ws.load_surface()
    return Surface(PlaneFrame(origin, axes), height, mm_per_px)


def _read(path: str) -> np.ndarray:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise PipelineError(f"{path}: the photo could not be decoded")
    return image


def compose_stage(camera: Camera, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], surface: Surface,
                  compose: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One stage's photos ``(image, R, C)`` on the raster of ``surface``, in blocks of rows.

    ``best``: each output pixel from the photo with the highest sampling density there (the most frontal
    and nearest view); ``average``: the mean of all photos that see it.
    Returns (H, W, 3) uint8 BGR, (H, W) bool True where at least one photo sees the specimen, and (H, W)
    float32 the highest sampling density there (photo pixels per mm^2).
    """
    shape = surface.shape
    image = np.zeros((*shape, 3), np.uint8)
    best = np.zeros(shape, np.float32)  # the highest density of a photo at each pixel
    count = np.zeros(shape, np.float32) if compose == "average" else None
    total = np.zeros((*shape, 3), np.float32) if compose == "average" else None
    step = max(1, BLOCK_PIXELS // shape[1])
    for photo, R, C in views:
        depth = photo_depth(surface.mesh, camera, R, C) if surface.mesh is not None else None
        for top in range(0, shape[0], step):
            rows = slice(top, min(top + step, shape[0]))
            map_x, map_y, density = rectification_maps(camera, R, C, surface, rows, depth)
            warped = cv2.remap(photo, map_x, map_y, INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
            if total is None or count is None:
                np.copyto(image[rows], warped, where=(density > best[rows])[..., None])
            else:
                seen = density > 0
                np.add(total[rows], warped, out=total[rows], where=seen[..., None])
                count[rows] += seen
            np.maximum(best[rows], density, out=best[rows])
    if total is not None and count is not None:
        for top in range(0, shape[0], step):  # the mean, block by block: no full-size temporaries
            rows = slice(top, min(top + step, shape[0]))
            mean = total[rows] / np.maximum(count[rows], 1.0)[..., None]
            image[rows] = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return image, best > 0, best
