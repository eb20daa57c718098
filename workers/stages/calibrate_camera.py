"""Stage ``calibrate_camera``: one camera from the board views (found corners, or marks by hand)."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.calibration import CalibrationResult, board_points, calibrate_camera
from workers.algorithms.camera import CONVENTIONS
from workers.config import CalibrationConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json, write_json

MIN_VIEWS = 3


def run(ws: JobWorkspace, cfg: CalibrationConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``calibration.json``: the camera, RMS, parameter sigmas and every point's reprojection error."""
    progress(0.0, "solving")
    frames = ws.load_inputs()
    names, views, sources, missing = board_views(ws, cfg, frames)
    if len(views) < MIN_VIEWS:
        raise PipelineError(f"only {len(views)} photo(s) have a usable board ({', '.join(names) or 'none'}); "
                            f"a calibration needs {MIN_VIEWS}. Without a board: {'; '.join(missing)}. "
                            "Add photos, or mark the corners by hand (PUT .../markers)")
    try:
        result = calibrate_camera(views, frames[0]["width"], frames[0]["height"], cfg.convention, cfg.terms)
    except ValueError as exc:
        raise PipelineError(str(exc)) from None
    write_json(ws.calibration_file(), calibration_report(result, names, views, sources, missing, cfg.method))
    progress(1.0, f"RMS {result.rms_px:.3f} px")
    return {"views": len(views), "rms_px": result.rms_px, "fx": result.camera.fx}


def board_views(ws: JobWorkspace, cfg: CalibrationConfig, frames: list[dict[str, Any]],
                side: str = "") -> tuple[list[str], list[tuple[np.ndarray, np.ndarray]], list[str], list[str]]:
    """Names, (board points, image points) views, their sources, and "name: reason" of photos left out."""
    corners = read_json(ws.corners_file())["images"]
    marks = {m.image: m for m in getattr(cfg, "markers", [])}
    board = board_points(cfg.pattern, cfg.square_mm)
    names, views, sources, missing = [], [], [], []
    for frame in frames:
        if frame.get("side", "") != side:
            continue
        name, mark = frame["name"], marks.get(frame["name"])
        if mark is not None and mark.remove:
            missing.append(f"{name}: removed by the user")
        elif mark is not None and mark.image_points:
            names.append(name)
            views.append((np.array(mark.board_points, float), np.array(mark.image_points, float)))
            sources.append("markers")
        elif corners[name]["points"] is not None:
            names.append(name)
            views.append((board, np.array(corners[name]["points"], float)))
            sources.append("chessboard")
        else:
            missing.append(f"{name}: {corners[name]['reason']}")
    return names, views, sources, missing


def calibration_report(result: CalibrationResult, names: list[str], views: list[tuple[np.ndarray, np.ndarray]],
                       sources: list[str], missing: list[str], method: str) -> dict[str, Any]:
    other = next(c for c in CONVENTIONS if c != result.camera.convention)
    return {
        "kind": "calibration",
        "method": method,
        "camera": result.camera.to_json(),
        "camera_in_other_convention": result.camera.with_convention(other).to_json(),  # type: ignore[arg-type]
        "rms_px": result.rms_px,
        "std": result.std,
        "views": [_view_entry(name, source, view, res, err)
                  for name, source, view, res, err in zip(names, sources, views, result.residuals, result.errors,
                                                          strict=True)],
        "worst_points": [{"image": names[v], "index": i, "error_px": e} for v, i, e in result.worst_points(10)],
        "left_out": missing,
    }


def _view_entry(name: str, source: str, view: tuple[np.ndarray, np.ndarray], residuals: np.ndarray,
                errors: np.ndarray) -> dict[str, Any]:
    board, image = view
    return {"image": name, "source": source, "rms_px": float(np.sqrt(np.mean(errors**2))),
            "points": [{"index": i, "image_xy": image[i].tolist(), "board_xyz": board[i].tolist(),
                        "residual_px": residuals[i].tolist(), "error_px": float(errors[i])}
                       for i in range(len(errors))]}
