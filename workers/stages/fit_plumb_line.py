"""Stage ``fit_plumb_line``: distortion terms from points along lines that are straight in the world."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.calibration import plumb_line
from workers.algorithms.geometry import Camera
from workers.config import CalibrationConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CalibrationConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``calibration.json``: the camera with the fitted terms and each line's residuals."""
    progress(0.0, "fitting lines")
    camera = _start_camera(cfg, ws.load_inputs())
    try:
        result = plumb_line([np.array(line, dtype=np.float64) for line in cfg.lines], camera, cfg.terms)
    except ValueError as exc:
        raise PipelineError(str(exc)) from None
    ws.save_calibration(
        {
            "kind": "calibration",
            "method": "plumb_line",
            "camera": result.camera.to_json(),
            "note": "distortion terms only; fx, fy, cx, cy are the given (or assumed) values and only normalise",
            "rms_px": result.rms_px,
            "std": result.std,
            "lines": [
                {"index": n, "points": len(res), "rms_px": float(rms), "residuals_px": res.tolist()}
                for n, (rms, res) in enumerate(zip(result.line_rms_px, result.residuals, strict=True))
            ],
        }
    )
    progress(1.0, f"RMS {result.rms_px:.3f} px")
    return {"lines": len(cfg.lines), "rms_px": result.rms_px}


def _start_camera(cfg: CalibrationConfig, frames: list[dict[str, Any]]) -> Camera:
    """The given camera, or a normal lens (focal = the longer side) centred on the frame."""
    if cfg.camera is not None:
        try:
            return Camera.from_json(cfg.camera).with_convention(cfg.convention)
        except ValueError as exc:
            raise PipelineError(f"camera: {exc}") from None
    width, height = (frames[0]["width"], frames[0]["height"]) if frames else cfg.image_size  # type: ignore[misc]
    f = float(max(width, height))
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2, convention=cfg.convention)
