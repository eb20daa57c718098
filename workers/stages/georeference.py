"""Stage ``georeference``: the output grid of the mosaic, in UTM when the frames carry GPS."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from workers.algorithms.alignment import apply_homography, frame_corners
from workers.algorithms.georef import FLIP_Y, fit_similarity, lonlat_to_utm, similarity_scale, utm_epsg
from workers.config import MosaicConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json, write_json

MAX_OUTPUT_PIXELS = 4_000_000_000  # a larger grid means a broken alignment, not a real flight
MIN_GPS_SPREAD_M = 3.0  # below this, consumer GPS noise would dominate the fitted scale and rotation


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``georef.json``: output pixel -> plane homography, CRS and pixel size."""
    progress(0.0, "fitting GPS")
    frames = {f["index"]: f for f in ws.load_frames()}
    homs = {int(k): np.array(H) for k, H in read_json(ws.alignment_file())["homographies"].items()}
    corners = np.concatenate([apply_homography(H, frame_corners(frames[k]["width"], frames[k]["height"]))
                              for k, H in homs.items()])
    fit, reason = _fit_gps(frames, homs, cfg.min_gps_frames)
    if fit is not None:
        grid = map_grid(corners, fit["plane_to_map"])
        result = {"georeferenced": True, "reason": "", **fit, **grid}
    else:
        grid = pixel_grid(corners)
        result = {"georeferenced": False, "reason": reason, "epsg": None, "plane_to_map": np.eye(3).tolist(),
                  "gsd_m": None, **grid}
    if result["width"] * result["height"] > MAX_OUTPUT_PIXELS:
        raise PipelineError(f"the mosaic would be {result['width']}x{result['height']} px; the alignment "
                            "is degenerate (frames do not lie in one plane)")
    write_json(ws.georef_file(), result)
    progress(1.0, "georeferenced" if fit else "local pixel grid")
    return {k: result[k] for k in ("georeferenced", "reason", "epsg", "gsd_m", "width", "height")}


def _fit_gps(frames: dict[int, dict[str, Any]], homs: dict[int, np.ndarray],
             min_frames: int) -> tuple[dict[str, Any] | None, str]:
    with_gps = [k for k in homs if frames[k].get("gps")]
    if len(with_gps) < min_frames:
        return None, f"{len(with_gps)} aligned frame(s) have GPS; georeferencing needs {min_frames}"
    lonlat = np.array([[frames[k]["gps"]["lon"], frames[k]["gps"]["lat"]] for k in with_gps])
    epsg = utm_epsg(float(lonlat[:, 1].mean()), float(lonlat[:, 0].mean()))
    utm = lonlat_to_utm(lonlat, epsg)
    spread = float(np.linalg.norm(utm - utm.mean(axis=0), axis=1).max())
    if spread < MIN_GPS_SPREAD_M:
        return None, f"the GPS positions lie within {spread:.1f} m of each other; too close to fit a scale"
    centre = {k: np.array([(frames[k]["width"] - 1) / 2, (frames[k]["height"] - 1) / 2]) for k in with_gps}
    centres = np.array([apply_homography(homs[k], centre[k])[0] for k in with_gps])
    S = fit_similarity(apply_homography(FLIP_Y, centres), utm)
    M = S @ FLIP_Y
    residuals = np.linalg.norm(apply_homography(M, centres) - utm, axis=1)
    return {"epsg": epsg, "plane_to_map": M.tolist(), "gsd_m": similarity_scale(M),
            "gps_frames": len(with_gps), "gps_residual_rms_m": float(np.sqrt(np.mean(residuals**2))),
            "gps_residuals_m": {frames[k]["name"]: float(r) for k, r in zip(with_gps, residuals, strict=True)}}, ""


def map_grid(plane_corners: np.ndarray, plane_to_map: list[list[float]]) -> dict[str, Any]:
    """A north-up grid in map units covering every frame, at the plane's own resolution."""
    M = np.array(plane_to_map)
    gsd = similarity_scale(M)
    xy = apply_homography(M, plane_corners)
    west, north = xy[:, 0].min(), xy[:, 1].max()
    width = math.ceil((xy[:, 0].max() - west) / gsd)
    height = math.ceil((north - xy[:, 1].min()) / gsd)
    affine = np.array([[gsd, 0.0, west], [0.0, -gsd, north], [0.0, 0.0, 1.0]])
    return {"width": width, "height": height, "transform": affine[:2].ravel().tolist(),
            "output_to_plane": (np.linalg.inv(M) @ affine).tolist()}


def pixel_grid(plane_corners: np.ndarray) -> dict[str, Any]:
    """The plane itself, shifted so the mosaic starts at pixel (0, 0); no map coordinates."""
    x0, y0 = np.floor(plane_corners.min(axis=0))
    x1, y1 = np.ceil(plane_corners.max(axis=0))
    shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    return {"width": int(x1 - x0), "height": int(y1 - y0), "transform": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            "output_to_plane": shift.tolist()}
