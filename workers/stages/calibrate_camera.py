"""Stage ``calibrate_camera``: one camera from the board views (found corners, or marks by hand)."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.calibration import (
    MIN_VIEWS,
    CalibrationResult,
    board_points,
    board_views,
    calibrate_camera,
    view_entry,
)
from workers.algorithms.geometry import CONVENTIONS
from workers.config import CalibrationConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CalibrationConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``calibration.json``: the camera, RMS, parameter sigmas and every point's reprojection error."""
    progress(0.0, "solving")
    frames = ws.load_inputs()
    marks = {m.image: m for m in cfg.markers}
    names, views, sources, missing = board_views(
        frames, ws.load_corners()["images"], marks, board_points(cfg.pattern, cfg.square_mm)
    )
    if len(views) < MIN_VIEWS:
        raise PipelineError(
            f"only {len(views)} photo(s) have a usable board ({', '.join(names) or 'none'}); "
            f"a calibration needs {MIN_VIEWS}. Without a board: {'; '.join(missing)}. "
            "Add photos, or mark the corners by hand (PUT .../markers)"
        )
    try:
        result = calibrate_camera(views, frames[0]["width"], frames[0]["height"], cfg.convention, cfg.terms)
    except ValueError as exc:
        raise PipelineError(str(exc)) from None
    ws.save_calibration(calibration_report(result, names, views, sources, missing, cfg.method))
    progress(1.0, f"RMS {result.rms_px:.3f} px")
    return {"views": len(views), "rms_px": result.rms_px, "fx": result.camera.fx}


def calibration_report(
    result: CalibrationResult,
    names: list[str],
    views: list[tuple[np.ndarray, np.ndarray]],
    sources: list[str],
    missing: list[str],
    method: str,
) -> dict[str, Any]:
    other = next(c for c in CONVENTIONS if c != result.camera.convention)
    return {
        "kind": "calibration",
        "method": method,
        "camera": result.camera.to_json(),
        "camera_in_other_convention": result.camera.with_convention(other).to_json(),  # type: ignore[arg-type]
        "rms_px": result.rms_px,
        "std": result.std,
        "views": [
            view_entry(name, source, view[0], view[1], res, err)
            for name, source, view, res, err in zip(names, sources, views, result.residuals, result.errors, strict=True)
        ],
        "worst_points": [{"image": names[v], "index": i, "error_px": e} for v, i, e in result.worst_points(10)],
        "left_out": missing,
    }
