"""Stage ``adjust_bundle`` (ortho mode): photo-triangulation of the flight.

Tracks from the pairwise matches, initial cameras (GPS + gimbal attitude, or incremental from the
essential matrix and PnP), then a bundle adjustment with GPS priors, ground control points and
self-calibration (``workers.algorithms.sfm.reconstruction``). Everything is in working-image pixels; the
report also gives the RMS in the photos' own pixels.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from workers.algorithms.geometry import Camera, lonlat_to_utm, utm_epsg
from workers.algorithms.sfm import (
    IMAGE_STATUSES,
    Attitude,
    GpsFix,
    GroundControlPoint,
    LocalFrame,
    Reconstruction,
    ReconstructionOptions,
    parse_gcp_file,
    reconstruct,
    scale_observations,
)
from workers.config import MosaicConfig
from workers.pipeline import PipelineError, option_camera
from workers.records import Frame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

DEFAULT_FOCAL = 0.85  # focal length / longest side when EXIF says nothing (a normal survey lens)


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cameras.json``: adjusted camera, poses by frame index, ground height and the report."""
    progress(0.0, "tracks and initial cameras")
    frames = ws.load_frames()
    rows = {f.index: r for r, f in enumerate(frames)}
    features = [ws.load_features(f.index)[0].astype(np.float64) for f in frames]
    pairs = [p for p in ws.load_pairs() if p.accepted]
    matches = {(rows[p.i], rows[p.j]): ws.load_match_indices(p.pair) for p in pairs}
    camera, camera_source = initial_camera(cfg, frames[0])
    world = local_frame(frames, cfg.min_gps_frames)
    gps = _gps(frames, world, cfg.gps_sigma_m) if world else None
    gcps = _gcps(ws, frames, world) if world else []
    # pixel thresholds for the working copies' size (MosaicConfig.threshold_scale)
    scale = cfg.threshold_scale(max(max(f.width, f.height) for f in frames))
    options = ReconstructionOptions(
        loss_scale_px=cfg.robust_loss_px * scale,
        outlier_threshold_px=cfg.outlier_px * scale,
        verify_threshold_px=ReconstructionOptions.verify_threshold_px * scale,
        pnp_threshold_px=ReconstructionOptions.pnp_threshold_px * scale,
        refine_focal="focal" in cfg.self_calibrate,
        refine_k1="k1" in cfg.self_calibrate,
        refine_k2="k2" in cfg.self_calibrate,
        gcp_sigma_m=cfg.gcp_sigma_m,
    )
    result = reconstruct(
        features,
        matches,
        camera,
        gps=gps,
        attitude=_attitudes(frames),
        gcps=gcps,
        checkpoints=cfg.checkpoints,
        frame_names=[f.name for f in frames],
        options=options,
    )
    if len(result.poses) < 2:
        reasons = "; ".join(f"{k}: {v}" for k, v in result.report["frames"]["not_registered"].items())
        # ground control held tighter than it is known pulls the cameras away from their fixes
        hint = (
            f" ({len(gcps)} ground control point(s) were held to gcp_sigma_m {cfg.gcp_sigma_m:g} m: if their "
            "positions are known less well, say so with gcp_sigma_m)"
            if gcps and "GPS position" in reasons
            else ""
        )
        raise PipelineError(f"photo-triangulation registered {len(result.poses)} frame(s): {reasons}{hint}")
    progress(0.95, "report")
    report = triangulation_report(result, frames, camera, camera_source)
    ground_z = float(np.median(result.points[:, 2])) if len(result.points) else 0.0
    ws.save_tie_points(result.points)  # orthorectify_frames grids its surface from them
    ws.save_cameras(
        {
            "world": _world_json(world),
            "camera": result.camera.to_json(),
            "camera_source": camera_source,
            "poses": {frames[r].index: {"R": R.tolist(), "C": C.tolist()} for r, (R, C) in result.poses.items()},
            "ground_z": ground_z,
            "not_registered": [
                {"index": f.index, "name": f.name, "reason": reason}
                for f in frames
                if (reason := result.report["frames"]["not_registered"].get(f.name))
            ],
            "report": report,
            "details": result.report,
        }
    )
    progress(1.0, f"{report['registered']}/{report['total']} frames, RMS {report['rms_px'] or 0.0:.2f} px")
    return {k: report[k] for k in ("registered", "total", "rms_px", "points", "datum")}


def initial_camera(cfg: MosaicConfig, frame: Frame) -> tuple[Camera, str]:
    """The starting camera in working pixels: the given calibration, else EXIF's 35 mm focal length."""
    scale, width, height = frame.scale, frame.width, frame.height
    if cfg.camera is not None:
        given = option_camera(cfg.camera, "camera")
        if (given.width, given.height) != (frame.orig_width, frame.orig_height):
            raise PipelineError(
                f"options.camera is for {given.width}x{given.height} px photos, but "
                f"{frame.name} is {frame.orig_width}x{frame.orig_height}"
            )
        return given.replace(
            width=width,
            height=height,
            fx=given.fx * scale,
            fy=given.fy * scale,
            cx=(given.cx + 0.5) * scale - 0.5,
            cy=(given.cy + 0.5) * scale - 0.5,
        ), "calibration"
    f35 = frame.focal_length_35mm
    f = f35 / 36.0 * max(width, height) if f35 else DEFAULT_FOCAL * max(width, height)
    source = f"EXIF 35 mm focal length {f35:g} mm" if f35 else f"assumed focal = {DEFAULT_FOCAL} x longest side"
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2), source


def local_frame(frames: list[Frame], min_frames: int) -> LocalFrame | None:
    """The job's metric frame around the GPS positions (UTM, shifted to a round origin), if enough have GPS."""
    lonlat = np.array([[gps["lon"], gps["lat"]] for f in frames if (gps := f.gps)])
    if len(lonlat) < min_frames:
        return None
    epsg = utm_epsg(float(lonlat[:, 1].mean()), float(lonlat[:, 0].mean()))
    origin = np.round(lonlat_to_utm(lonlat, epsg).mean(axis=0), -2)
    return LocalFrame(epsg, float(origin[0]), float(origin[1]))


def _gps(frames: list[Frame], world: LocalFrame, sigma: float) -> dict[int, GpsFix]:
    out = {}
    for r, f in enumerate(frames):
        g = f.gps
        if g and g.get("alt") is not None:
            xyz = world.from_lonlat(np.array([[g["lon"], g["lat"], g["alt"]]]))[0]
            out[r] = GpsFix(tuple(map(float, xyz)), sigma_h=sigma, sigma_v=2.0 * sigma)  # type: ignore[arg-type]
    return out


def _attitudes(frames: list[Frame]) -> dict[int, Attitude] | None:
    angles = [(f.yaw, f.pitch, f.roll or 0.0) for f in frames]
    if any(yaw is None or pitch is None for yaw, pitch, _ in angles):
        return None
    return {
        r: Attitude(float(yaw or 0.0), float(pitch or 0.0), float(roll)) for r, (yaw, pitch, roll) in enumerate(angles)
    }


def _gcps(ws: JobWorkspace, frames: list[Frame], world: LocalFrame) -> list[GroundControlPoint]:
    """The job's GCPs with observations in working pixels (every frame of a job has one scale)."""
    path = ws.gcp_file()
    if path is None:
        return []
    sizes = {f.name: (f.orig_width, f.orig_height) for f in frames}
    try:
        gcps = parse_gcp_file(path.name, path.read_text(encoding="utf-8"), sizes, world)
    except ValueError as exc:
        raise PipelineError(f"{path.name}: {exc}") from None
    return scale_observations(gcps, frames[0].scale)


def _world_json(world: LocalFrame | None) -> dict[str, Any]:
    if world is None:
        return {"epsg": None, "note": "no GPS: arbitrary datum, scale set by the first baseline"}
    return {
        "epsg": world.epsg,
        "easting0": world.easting0,
        "northing0": world.northing0,
        "note": "x = UTM easting - easting0, y = northing - northing0, z = GPS altitude (m)",
    }


def triangulation_report(
    result: Reconstruction, frames: list[Frame], start: Camera, camera_source: str
) -> dict[str, Any]:
    """The report's ``triangulation`` section (what the viewer's quality card shows)."""
    rep, scale = result.report, frames[0].scale
    per_frame = rep.get("per_frame", {})
    gps = [e["gps_residual_m"] for e in per_frame.values() if e.get("gps_residual_m") is not None]
    adjusted = result.camera
    rms = rep["rms_reprojection_px"]
    return {
        "registered": rep["frames"]["registered"],
        "total": rep["frames"]["total"],
        "not_registered": [{"name": k, "reason": v} for k, v in rep["frames"]["not_registered"].items()],
        "rms_px": rms,
        "rms_px_original": rms / scale if rms is not None else None,
        "observations": rep["observations"],
        "points": rep["points"],
        "outliers_dropped": rep.get("rejected_observations", 0),
        "datum": rep["datum"],
        "initialisation": rep["initialisation"],
        "camera_source": camera_source,
        "self_calibration": {
            "focal_px_original": {"initial": start.fx / scale, "adjusted": adjusted.fx / scale},
            "k1": {"initial": start.k1, "adjusted": adjusted.k1},
            "k2": {"initial": start.k2, "adjusted": adjusted.k2},
        },
        "images": [
            {
                "name": f.name,
                "rms_px": per_frame.get(f.name, {}).get("rms_px"),
                "observations": per_frame.get(f.name, {}).get("observations", 0),
                "gps_residual_m": per_frame.get(f.name, {}).get("gps_residual_m"),
                "tie_points_offered": per_frame.get(f.name, {}).get("tie_points_offered", 0),
                "status": per_frame.get(f.name, {}).get("status", IMAGE_STATUSES[2]),
                "attitude": per_frame.get(f.name, {}).get("attitude"),
            }
            for f in frames
        ],
        "gps_residual_rms_m": math.sqrt(float(np.mean(np.square(gps)))) if gps else None,
        "gcps": [
            {
                "id": gid,
                "role": e["role"],
                "observations": e["observations"],
                "residual_px": e.get("rms_px"),
                "error_m": e.get("residual_enu_m"),
                "error_3d_m": e.get("residual_m"),
            }
            for gid, e in rep.get("gcps", {}).items()
        ],
        "checkpoint_rmse_m": rep.get("checkpoint_rmse_m"),
        "warnings": rep.get("warnings", []),
        "notes": rep.get("notes", []),
        "seconds": rep.get("seconds"),
    }
