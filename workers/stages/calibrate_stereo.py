"""Stage ``calibrate_stereo``: both cameras (unless given) and the rig's rotation and baseline."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from workers.algorithms.calibration import (
    MIN_VIEWS,
    CalibrationResult,
    board_points,
    board_views,
    calibrate_camera,
    stereo_calibrate,
)
from workers.algorithms.geometry import Camera, vector_from_rotation
from workers.config import StereoCalibrationConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: StereoCalibrationConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``calibration.json`` with ``rig`` (the StereoRig JSON), both cameras and per-point errors."""
    frames = ws.load_inputs()
    corners, board = ws.load_corners()["images"], board_points(cfg.pattern, cfg.square_mm)
    sides = {side: board_views(frames, corners, {}, board, side) for side in ("left", "right")}
    cameras: dict[str, dict[str, Any]] = {}
    for n, side in enumerate(("left", "right")):
        progress(0.4 * n, f"{side} camera")
        cameras[side] = _camera(cfg, side, sides[side], frames)
    progress(0.8, "rig")
    pair_of = {f["name"]: f["pair"] for f in frames}
    left_names, left_views = sides["left"][0], sides["left"][1]
    right_by_pair = {pair_of[n]: (n, v) for n, v in zip(sides["right"][0], sides["right"][1], strict=True)}
    pairs = [
        (ln, right_by_pair[pair_of[ln]][0], lv[0], lv[1], right_by_pair[pair_of[ln]][1][1])
        for ln, lv in zip(left_names, left_views, strict=True)
        if pair_of[ln] in right_by_pair
    ]
    if len(pairs) < MIN_VIEWS:
        raise PipelineError(
            f"the board is found in both photos of only {len(pairs)} pair(s); a rig needs "
            f"{MIN_VIEWS}. Left out: {'; '.join(sides['left'][3] + sides['right'][3]) or 'none'}"
        )
    try:
        result = stereo_calibrate(
            cameras["left"]["camera"], cameras["right"]["camera"], [(obj, lpx, rpx) for _, _, obj, lpx, rpx in pairs]
        )
    except ValueError as exc:
        raise PipelineError(str(exc)) from None
    angle = math.degrees(float(np.linalg.norm(vector_from_rotation(result.R))))
    ws.save_calibration(
        {
            "kind": "stereo_calibration",
            "rig": result.rig.to_json(),
            "units": "mm (the board's square size)",
            "baseline_mm": result.baseline,
            "baseline_std_mm": result.baseline_std,
            "rotation_deg": angle,
            "rms_px": result.rms_px,
            "cameras": {
                side: {"camera": c["camera"].to_json(), "rms_px": c["rms_px"], "source": c["source"]}
                for side, c in cameras.items()
            },
            "pairs": [
                {
                    "left": ln,
                    "right": rn,
                    "errors_left_px": el.tolist(),
                    "errors_right_px": er.tolist(),
                    "rms_px": float(np.sqrt(np.mean(np.concatenate([el, er]) ** 2))),
                }
                for (ln, rn, *_), el, er in zip(pairs, result.errors_left, result.errors_right, strict=True)
            ],
            "left_out": sides["left"][3] + sides["right"][3],
        }
    )
    progress(1.0, f"baseline {result.baseline:.1f} mm")
    return {"pairs": len(pairs), "baseline_mm": result.baseline, "rotation_deg": angle, "rms_px": result.rms_px}


def _camera(
    cfg: StereoCalibrationConfig,
    side: str,
    views: tuple[list[str], list[Any], list[str], list[str]],
    frames: list[dict[str, Any]],
) -> dict[str, Any]:
    """The given camera of ``side``, or one calibrated from that side's board views."""
    given = getattr(cfg, f"{side}_camera")
    if given is not None:
        try:
            return {"camera": Camera.from_json(given), "rms_px": None, "source": "given"}
        except ValueError as exc:
            raise PipelineError(f"{side}_camera: {exc}") from None
    names, board_views_, _, missing = views
    if len(board_views_) < MIN_VIEWS:
        raise PipelineError(
            f"the board is found in {len(board_views_)} {side} photo(s); calibrating the {side} "
            f"camera needs {MIN_VIEWS}. Without a board: {'; '.join(missing)}"
        )
    first = next(f for f in frames if f["side"] == side)
    try:
        result: CalibrationResult = calibrate_camera(
            board_views_, first["width"], first["height"], cfg.convention, cfg.terms
        )
    except ValueError as exc:
        raise PipelineError(f"{side} camera: {exc}") from None
    return {"camera": result.camera, "rms_px": result.rms_px, "source": f"calibrated from {len(names)} photos"}
