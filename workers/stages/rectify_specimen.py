"""Stage ``rectify_specimen``: every load stage's photos rendered orthographically onto the specimen plane."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from workers.algorithms.camera import Camera
from workers.algorithms.resection import pose_from_json, rectification_maps
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError
from workers.stages.orient_camera import survey_camera
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json

# Lanczos rather than bilinear or bicubic: where the output is finer than the photo, those draw the photo's
# pixel lattice as streaks that the crack detector takes for hairline cracks
INTERPOLATION = cv2.INTER_LANCZOS4


def specimen_shape(cfg: CrackSurveyConfig) -> tuple[int, int]:
    """(rows, cols) of the rectified raster: pixel centres every ``mm_per_px`` from 0 to the specimen's edge."""
    step = cfg.mm_per_px
    return (math.floor(cfg.specimen.height_mm / step + 1e-9) + 1, math.floor(cfg.specimen.width_mm / step + 1e-9) + 1)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``rectified/stage_NN.npz`` per load stage: (H, W, 3) BGR image and the mask its photos see."""
    camera = survey_camera(cfg)
    poses = {p["image"]: pose_from_json(p) for p in read_json(ws.orientation_file())["photos"]}
    paths = {f["name"]: f["path"] for f in ws.load_inputs()}
    shape = specimen_shape(cfg)
    coverage = []
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"stage {s + 1}/{len(cfg.stages)}")
        views = [(_read(paths[p.image]), *poses[p.image]) for p in stage.photos]
        image, mask = compose_stage(camera, views, shape, cfg.mm_per_px, cfg.compose)
        if not mask.any():
            raise PipelineError(f"stage {stage.label!r}: its photos see no part of the specimen; "
                                "check the control points' model coordinates")
        ws.save_rectified(s, image, mask)
        coverage.append(round(float(mask.mean()), 4))
    progress(1.0, f"{len(cfg.stages)} stage(s) rectified")
    return {"stages": len(cfg.stages), "width_px": shape[1], "height_px": shape[0], "coverage": coverage}


def _read(path: str) -> np.ndarray:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise PipelineError(f"{path}: the photo could not be decoded")
    return image


def compose_stage(camera: Camera, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], shape: tuple[int, int],
                  mm_per_px: float, compose: str) -> tuple[np.ndarray, np.ndarray]:
    """One stage's photos ``(image, R, C)`` on the specimen raster of ``shape`` (rows, cols).

    ``best``: each output pixel from the photo with the highest sampling density there (the most frontal
    and nearest view); ``average``: the mean of all photos that see it.
    Returns (H, W, 3) uint8 BGR and (H, W) bool, True where at least one photo sees the specimen.
    """
    total = np.zeros((*shape, 3), np.float32)
    weight_sum = np.zeros(shape, np.float32)
    best = np.zeros(shape, np.float32)
    for image, R, C in views:
        map_x, map_y, density = rectification_maps(camera, R, C, shape, mm_per_px)
        warped = cv2.remap(image, map_x, map_y, INTERPOLATION, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        if compose == "average":
            seen = density > 0
            total[seen] += warped[seen]
            weight_sum[seen] += 1.0
        else:
            better = density > best
            total[better] = warped[better]
            weight_sum[better] = 1.0
            best = np.maximum(best, density)
    mask = weight_sum > 0
    image = np.zeros((*shape, 3), np.uint8)
    image[mask] = np.clip(np.rint(total[mask] / weight_sum[mask, None]), 0, 255).astype(np.uint8)
    return image, mask
