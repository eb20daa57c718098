"""Stage ``detect_corners``: chessboard corners in every photo of a calibration or stereo job."""

from __future__ import annotations

from typing import Any

import cv2

from workers.algorithms.calibration import find_chessboard
from workers.config import CalibrationConfig, StereoCalibrationConfig
from workers.parallel import ordered_map, thread_count
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(
    ws: JobWorkspace, cfg: CalibrationConfig | StereoCalibrationConfig, *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """Write ``corners.json``: per photo, the corners in OpenCV's order, or why there are none."""
    frames = ws.load_inputs()
    if getattr(cfg, "method", "chessboard") != "chessboard":
        found: list[dict[str, Any]] = [{"points": None, "reason": "marked by hand"} for _ in frames]
    else:
        found = ordered_map(lambda f: _corners(f, cfg.pattern), frames, thread_count(0), progress, "photo")
    images = {f["name"]: entry for f, entry in zip(frames, found, strict=True)}
    ws.save_corners({"pattern": list(cfg.pattern), "images": images})
    with_board = sum(entry["points"] is not None for entry in found)
    return {"photos": len(frames), "with_board": with_board}


def _corners(frame: dict[str, Any], pattern: tuple[int, int]) -> dict[str, Any]:
    gray = cv2.imread(frame["path"], cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return {"points": None, "reason": "could not be decoded"}
    points = find_chessboard(gray, pattern)
    if points is None:
        return {"points": None, "reason": f"no {pattern[0]}x{pattern[1]} chessboard found"}
    return {"points": points.tolist(), "reason": ""}
