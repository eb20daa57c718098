"""Stage ``write_stereo_report``: ``report.json`` of a stereo DEM job, from what the other stages found."""

from __future__ import annotations

from typing import Any

from workers.config import StereoDemConfig
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

ROW_RESIDUAL_WARNING_PX = 1.0  # rows misaligned by more than this after rectification weaken the matching
CHECKED_WARNING = 0.5  # fewer checked disparities than this share of the pixels: a weak result
FILLED_WARNING = 0.3  # more filled DSM cells than this share: the DSM is mostly interpolated


def run(ws: JobWorkspace, cfg: StereoDemConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``report.json``: geometry, rectification, disparity and surface figures, outputs, warnings."""
    rectified = ws.load_stage_report("rectify_pair") or {}
    disparity = ws.load_stage_report("compute_disparity") or {}
    surface = ws.load_stage_report("build_dsm") or {}
    info = ws.load_rectification()
    report = {
        "kind": "stereo_dem",
        "geometry": info["geometry"],
        "method": cfg.method,
        "rectification": {
            "method": info["rectification"]["method"],
            "size": rectified.get("rectified_size"),
            "row_residual_px": rectified.get("row_residual_px"),
            "matches": rectified.get("matches"),
            "inliers": rectified.get("inliers"),
            "heights_m": info.get("heights_m"),
            "gsd_m": info.get("gsd_m"),
        },
        "disparity": {
            "min_disparity": info["min_disparity"],
            "num_disparities": info["num_disparities"],
            "range_source": info["range_source"],
            "checked_share": disparity.get("checked_share"),
            "filled_share": disparity.get("filled_share"),
            "device": disparity.get("device"),
            "seconds_per_megapixel": disparity.get("seconds_per_megapixel"),
            "legend": disparity.get("legend"),
        },
        "surface": {k: v for k, v in surface.items() if k != "wall_seconds"},
        "outputs": sorted({*ws.outputs(), "report.json"}),
        "warnings": _warnings(rectified, disparity, surface),
    }
    ws.save_report(report)
    return {"warnings": len(report["warnings"])}


def _warnings(rectified: dict[str, Any], disparity: dict[str, Any], surface: dict[str, Any]) -> list[str]:
    out = []
    residual = rectified.get("row_residual_px") or 0.0
    if residual > ROW_RESIDUAL_WARNING_PX:
        out.append(f"rows of the rectified pair still differ by up to {residual:.2f} px; matches may be missed")
    checked = disparity.get("checked_share")
    if checked is not None and checked < CHECKED_WARNING:
        out.append(f"only {100 * checked:.0f} % of the pixels have a checked disparity; the rest is filled or empty")
    filled = surface.get("filled_share")
    if filled is not None and filled > FILLED_WARNING:
        out.append(f"{100 * filled:.0f} % of the DSM's cells are filled, not measured (dsm_mask.tif says which)")
    return out
