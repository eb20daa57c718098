"""Stage ``orient_camera``: each photo's pose from its control points (space resection on the plate or mesh)."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.specimen import Resection, pose_json, resect_plane, resect_points
from workers.config import CrackSurveyConfig, SurveyPhoto
from workers.pipeline import PipelineError, option_camera
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``orientation.json``: per photo, its pose and the residuals of its control points in px and mm."""
    camera = option_camera(cfg.camera, "camera")
    photos = [(s, photo) for s, stage in enumerate(cfg.stages) for photo in stage.photos]
    entries = []
    for n, (s, photo) in enumerate(photos):
        progress(n / len(photos), f"photo {n + 1}/{len(photos)}")
        model = np.array([p.model for p in photo.control_points], dtype=np.float64)
        pixels = np.array([p.pixel for p in photo.control_points], dtype=np.float64)
        try:
            result = (resect_plane if cfg.specimen.mesh is None else resect_points)(camera, model, pixels)
        except ValueError as exc:
            raise PipelineError(f"{photo.image}: {exc}") from None
        _check_fit(photo, result, cfg.max_rms_px)
        entries.append(_photo_entry(s, photo, result))
    ws.save_orientation(entries)
    progress(1.0, f"{len(photos)} photo(s) oriented")
    return {"photos": len(entries), "worst_rms_px": max(e["rms_px"] for e in entries)}


def _check_fit(photo: SurveyPhoto, result: Resection, max_rms_px: float) -> None:
    errors = np.linalg.norm(result.residuals_px, axis=1)
    worst = int(np.argmax(errors))
    if not np.isfinite(result.rms_px) or result.rms_px > max_rms_px:
        raise PipelineError(
            f"{photo.image}: the control points fit the camera with RMS {result.rms_px:.1f} px "
            f"(limit {max_rms_px} px); the worst is point {worst} at pixel "
            f"{list(photo.control_points[worst].pixel)} ({errors[worst]:.1f} px off). "
            "Check its marking and model coordinates, and that the camera is the one that took it"
        )
    if not np.all(np.isfinite(result.residuals_mm)):
        raise PipelineError(
            f"{photo.image}: some control point rays miss the specimen plane; check the model coordinates"
        )


def _photo_entry(stage: int, photo: SurveyPhoto, result: Resection) -> dict[str, Any]:
    points = [
        {
            "index": k,
            "pixel": list(p.pixel),
            "model": list(p.model),
            "residual_px": result.residuals_px[k].tolist(),
            "error_px": float(np.hypot(*result.residuals_px[k])),
            "residual_mm": result.residuals_mm[k].tolist(),
            "error_mm": float(np.linalg.norm(result.residuals_mm[k])),
        }
        for k, p in enumerate(photo.control_points)
    ]
    return {
        "image": photo.image,
        "stage": stage,
        **pose_json(result.R, result.C),
        "rms_px": result.rms_px,
        "rms_mm": result.rms_mm,
        "points": points,
    }
