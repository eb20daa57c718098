"""Stage ``calibrate_stereo``: both cameras (unless given) and the rig's rotation and baseline."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.algorithms.calibration import (
    MIN_POINTS,
    MIN_VIEWS,
    BoardViews,
    CalibrationResult,
    StereoCalibrationResult,
    board_points,
    board_views,
    calibrate_camera,
    paired_points,
    stereo_calibrate,
    view_entry,
)
from workers.algorithms.geometry import Camera, vector_from_rotation
from workers.config import StereoCalibrationConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: StereoCalibrationConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``calibration.json`` with ``rig`` (the StereoRig JSON), both cameras, per-pair errors and, as a
    calibration does, every photo's marks with their errors (``views``) and the worst marks."""
    frames = ws.load_inputs()
    corners, board = ws.load_corners()["images"], board_points(cfg.pattern, cfg.square_mm)
    marks = {m.image: m for m in cfg.markers}
    sides = {side: board_views(frames, corners, marks, board, side) for side in ("left", "right")}
    cameras: dict[str, dict[str, Any]] = {}
    for n, side in enumerate(("left", "right")):
        progress(0.4 * n, f"{side} camera")
        cameras[side] = _camera(cfg, side, sides[side], frames)
    progress(0.8, "rig")
    pairs, short = _pairs(frames, sides, board.mean(axis=0))
    left_out = sides["left"][3] + sides["right"][3] + short
    if len(pairs) < MIN_VIEWS:
        raise PipelineError(
            f"the board is found in both photos of only {len(pairs)} pair(s); a rig needs "
            f"{MIN_VIEWS}. Left out: {'; '.join(left_out) or 'none'}"
        )
    try:
        result = stereo_calibrate(cameras["left"]["camera"], cameras["right"]["camera"], [p.view for p in pairs])
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
            **_pair_report(pairs, result),
            "left_out": left_out,
        }
    )
    progress(1.0, f"baseline {result.baseline:.1f} mm")
    return {"pairs": len(pairs), "baseline_mm": result.baseline, "rotation_deg": angle, "rms_px": result.rms_px}


@dataclass(frozen=True)
class _Pair:
    names: tuple[str, str]  # left photo, right photo
    sources: tuple[str, str]  # where each photo's points came from: "chessboard" or "markers"
    view: tuple[np.ndarray, np.ndarray, np.ndarray]  # board points (M, 3), left (M, 2), right (M, 2) pixels


def _pairs(
    frames: list[dict[str, Any]], sides: dict[str, BoardViews], centre: np.ndarray
) -> tuple[list[_Pair], list[str]]:
    """The pairs whose two photos both have a board, on the board points both have; and "names: why" of
    the pairs with too few of those."""
    pair_of = {f["name"]: f["pair"] for f in frames}
    right = {pair_of[n]: (n, v, s) for n, v, s in zip(*sides["right"][:3], strict=True)}
    pairs, short = [], []
    for ln, lv, ls in zip(*sides["left"][:3], strict=True):
        if pair_of[ln] not in right:
            continue
        rn, rv, rs = right[pair_of[ln]]
        # a board found in one photo may have come back in reverse order: keep the kept set half-turn symmetric
        view = paired_points(lv, rv, centre if "chessboard" in (ls, rs) else None)
        if len(view[0]) < MIN_POINTS:
            short.append(f"{ln} and {rn}: only {len(view[0])} marks in both photos, a pair needs {MIN_POINTS}")
        else:
            pairs.append(_Pair((ln, rn), (ls, rs), view))
    return pairs, short


def _pair_report(pairs: list[_Pair], result: StereoCalibrationResult) -> dict[str, Any]:
    """Per pair its errors; per photo its marks (a right photo turned round: its own board points)."""
    views = []
    for v, pair in enumerate(pairs):
        board, lpx, rpx = pair.view
        right_board = board[::-1] if v in result.reversed_views else board
        views.append(
            view_entry(pair.names[0], pair.sources[0], board, lpx, result.residuals_left[v], result.errors_left[v])
        )
        views.append(
            view_entry(
                pair.names[1], pair.sources[1], right_board, rpx, result.residuals_right[v], result.errors_right[v]
            )
        )
    worst = sorted(
        ({"image": v["image"], "index": p["index"], "error_px": p["error_px"]} for v in views for p in v["points"]),
        key=lambda w: -w["error_px"],
    )[:10]
    return {
        "pairs": [
            {
                "left": pair.names[0],
                "right": pair.names[1],
                "errors_left_px": el.tolist(),
                "errors_right_px": er.tolist(),
                "rms_px": float(np.sqrt(np.mean(np.concatenate([el, er]) ** 2))),
            }
            for pair, el, er in zip(pairs, result.errors_left, result.errors_right, strict=True)
        ],
        "views": views,
        "worst_points": worst,
    }


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
