"""Stage ``rectify_specimen``: every load stage's photos rendered orthographically onto the specimen's plane
(a plate, or a mesh's best-fit or chosen plane with its heights and occlusions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from workers.algorithms.specimen import (
    Surface,
    best_fit_plane,
    compose_views,
    mesh_surface,
    plane_through,
    plate_surface,
    pose_from_json,
    raster_shape,
    read_mesh,
)
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError, option_camera
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

MAX_RASTER_PIXELS = 200_000_000  # a larger raster is refused before anything is allocated (~26 B/px held)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the surface (``rectified/surface.npz``) and per load stage ``rectified/stage_NN.npz``:
    (H, W, 3) BGR image and the mask its photos see."""
    camera = option_camera(cfg.camera, "camera")
    poses = {p["image"]: pose_from_json(p) for p in ws.load_orientation()}
    paths = {f["name"]: f["path"] for f in ws.load_inputs()}
    surface = build_surface(ws, cfg, np.mean([C for _, C in poses.values()], axis=0))
    ws.save_surface(surface)
    coverage: list[float] = []
    photo_mm_per_px: list[float] = []
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        views = [(_read(paths[p.image]), *poses[p.image]) for p in stage.photos]
        image, mask, density = compose_views(camera, views, surface, cfg.compose)
        if not mask.any():
            raise PipelineError(
                f"load step {stage.label!r}: its photos see no part of the specimen; "
                "check the control points' model coordinates"
            )
        ws.save_rectified(s, image, mask)
        coverage.append(round(float(mask.mean()), 4))
        # the photos' own sampling on the specimen: a raster much finer than this shows resampled grain
        photo_mm_per_px.append(round(float(np.median(1.0 / np.sqrt(density[mask]))), 4))
    progress(1.0, f"{len(cfg.stages)} load step(s) rectified")
    return {
        "stages": len(cfg.stages),
        "width_px": surface.shape[1],
        "height_px": surface.shape[0],
        "coverage": coverage,
        "photo_mm_per_px": photo_mm_per_px,
        "plane": surface.frame.to_json(),
    }


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
        raise PipelineError(
            f"the specimen is {cols} x {rows} px at {mm_per_px} mm/px, more than "
            f"{MAX_RASTER_PIXELS} px; choose a coarser mm_per_px"
        )


def _read(path: str) -> np.ndarray:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise PipelineError(f"{Path(path).name}: the photo could not be decoded")
    return image
