"""Stage ``write_report``: ``report.json`` (what was used, how well it fits), frame footprints (with each
photo's residuals and camera position), the ground control points as the map has them, and ``report.html``
with its pictures (``workers.report_html``)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from workers.algorithms.geometry import Camera, lonlat_to_utm, utm_to_lonlat
from workers.algorithms.mosaic import (
    TiePoints,
    apply_homography,
    frame_corners,
    photo_px_per_plane_px,
    tie_residuals_px,
    triple_overlap_share,
)
from workers.algorithms.sfm import LocalFrame, parse_gcp_file
from workers.config import MosaicConfig
from workers.pipeline import pipeline_key, stage_names
from workers.records import Alignment, Frame, Georef, PairRecord
from workers.report_html import FigureData, figures, report_page
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

COVERAGE_CELLS = 256  # the overlap map's cells along the mosaic's longer side


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``report.json`` and, for a georeferenced mosaic, ``footprints.geojson``."""
    progress(0.0, "report")
    frames = ws.load_composed_frames()
    align, geo = ws.load_alignment(), ws.load_georef()
    pairs = ws.load_pairs()
    homs = align.homographies
    to_out = np.linalg.inv(geo.output_to_plane)
    footprints = {
        k: _to_crs(geo, apply_homography(to_out @ H, frame_corners(frames[k].width, frames[k].height)))
        for k, H in homs.items()
    }
    coverage = ws.load_coverage()
    outline = [_to_crs(geo, ring) for ring in coverage.outline_px]
    ref = frames[align.reference]
    rms = align.tie_point_rms_px
    # the reference photo's px per plane px: measured through its homography on a plane the adjustment may have
    # scaled (a strip's GPS does); ortho frames' tie points are in their working copies' px
    photo_per_plane = 1.0 / ref.scale
    if cfg.mode != "ortho":
        photo_per_plane = photo_px_per_plane_px(homs[ref.index], ref.width, ref.height, ref.orig_width, ref.orig_height)
    report: dict[str, Any] = {
        "kind": "mosaic",
        "mode": cfg.mode,
        "config": cfg.model_dump(),
        "frames_used": [_frame_entry(frames[k], footprints[k]) for k in sorted(homs)],
        "frames_rejected": [r.to_json() for r in ws.load_rejected_frames() + align.rejected],
        "reference_frame": ref.name,
        "pairs": _pair_entries(pairs, frames, align),
        "tie_point_rms_px": rms,
        "tie_point_rms_px_original": rms * photo_per_plane if rms is not None else None,
        "tie_points": align.tie_points,
        "georeferenced": geo.georeferenced,
        "georeference_note": geo.reason,
        "crs": f"EPSG:{geo.epsg}" if geo.georeferenced else None,
        "gsd_m": geo.gsd_m,  # the mosaic's pixel size
        "gsd_original_m": geo.gsd_m * geo.output_scale / photo_per_plane if geo.gsd_m else None,  # the photos'
        "gps_residual_rms_m": geo.gps_residual_rms_m,
        "gps_drift_m": geo.gps_drift_m,  # the route's largest systematic miss, noise averaged over a tenth of it
        "mosaic": {
            "width": geo.width,
            "height": geo.height,
            "transform": geo.transform,
            "footprint": _polygon(outline, geo),
            "coverage_fraction": coverage.area_fraction,
            "blend": cfg.blend,
            # multiband: the colour step across the cut lines over the same 16 px beside them (1.0: invisible)
            "seam_visibility": (ws.load_stage_report("compose_mosaic") or {}).get("seam_visibility"),
            # "working" or "native", and how many of the reference photo's px one mosaic px spans
            "resolution": cfg.output_resolution if cfg.mode != "ortho" else "working",
            "photo_px_per_px": photo_per_plane / geo.output_scale,
        },
        "stage_seconds": _stage_seconds(ws, pipeline_key("mosaic", {"mode": cfg.mode})),
    }
    if cfg.mode == "ortho":
        report["triangulation"] = ws.load_cameras()["report"]
        # what the frames were projected onto: the tie points' surface, or the plane (and why)
        ortho = ws.load_stage_report("orthorectify_frames") or {}
        report["ortho_surface"] = ortho.get("surface")
        report["dsm"] = ortho.get("dsm")  # the surface as dsm.tif (None on the plane or without map coordinates)
    if cfg.mode == "strip":
        sizes = {k: (frames[k].width, frames[k].height) for k in homs}
        report["triple_overlap_share"] = triple_overlap_share(homs, sizes)
        report["corner_precision"] = _corner_precision(frames, align, geo)
    report["warnings"] = _warnings(report)
    ws.save_report(report)
    progress(0.5, "report pictures")
    data = _figure_data(ws, cfg, frames, align, geo, to_out, report)
    ws.save_report_html(report_page(report, data, svgs := figures(data), _advice(report, data, cfg)), svgs)
    if geo.georeferenced:
        per_photo = _photo_figures(frames, data, geo, (report.get("corner_precision") or {}).get("frames_m", {}))
        ws.save_footprints(_footprint_collection(frames, footprints, per_photo))
        gcps = _gcp_collection(ws, cfg, frames, align, geo, to_out, report)
        if gcps is not None:
            ws.save_gcp_points(gcps)
    seams = ws.load_seams()
    if seams is not None:
        ws.save_cutlines(_cutline_collection(frames, seams, geo))
    progress(1.0, "report")
    return {"frames_used": len(report["frames_used"]), "frames_rejected": len(report["frames_rejected"])}


def _corner_precision(frames: dict[int, Frame], align: Alignment, geo: Georef) -> dict[str, Any] | None:
    """How well the adjustment knows the frames' corners (``align_frames``' standard errors, 1 sigma, the worst
    corner of each frame) in metres and in the photos' px: the median frame's, and the worst frame's with its
    name (its px its own); None without them (no GPS) or without map coordinates."""
    sigmas = {k: v for k, v in align.corner_sigma_px.items() if k in align.homographies}
    if not sigmas or not geo.georeferenced:
        return None
    metres_per_px = float(np.sqrt(abs(np.linalg.det(geo.plane_to_map[:2, :2]))))
    worst = max(sigmas, key=lambda k: sigmas[k])
    f = frames[worst]
    photo_per_plane = photo_px_per_plane_px(align.homographies[worst], f.width, f.height, f.orig_width, f.orig_height)
    return {
        "median_m": float(np.median(list(sigmas.values()))) * metres_per_px,
        "max_m": sigmas[worst] * metres_per_px,
        "max_photo_px": sigmas[worst] * photo_per_plane,
        "worst_frame": f.name,
        "frames_m": {frames[k].name: round(v * metres_per_px, 4) for k, v in sorted(sigmas.items())},
    }


def _warnings(report: dict[str, Any]) -> list[str]:
    """What a user must know before trusting the map, in words (the viewer's quality card shows them)."""
    triangulation = report.get("triangulation", {})
    out = list(triangulation.get("warnings", []))
    named = {entry["name"] for entry in triangulation.get("not_registered", [])}  # its warnings name these
    rejected = [r["name"] for r in report["frames_rejected"] if r["name"] not in named]
    if rejected:
        total = len(report["frames_rejected"]) + len(report["frames_used"])
        out.insert(0, f"{len(rejected)} of {total} frames are not in the map: {', '.join(rejected)}")
    share = report.get("triple_overlap_share")  # strips only
    if share is not None and share < 0.5:
        precision = report.get("corner_precision")
        known = (
            f" (corners known to {precision['max_m']:.2f} m, {precision['max_photo_px']:.1f} photo px, 1 sigma, "
            f"at {precision['worst_frame']})"
            if precision
            else ""
        )
        out.append(
            f"only {share:.0%} of the frames share ground with both neighbours: with 50 % forward overlap or less "
            "the scale is not carried from frame to frame and the frames' width rests on GPS and on their pixels "
            f"being square{known}; fly with 55-60 % forward overlap"
        )
    return out


def _to_crs(geo: Georef, out_px: np.ndarray) -> np.ndarray:
    """Output pixel coordinates -> lon/lat (georeferenced) or output pixels (not)."""
    if not geo.georeferenced or geo.epsg is None:
        return out_px
    a = np.array(geo.transform).reshape(2, 3)
    xy = out_px @ a[:, :2].T + a[:, 2]
    return utm_to_lonlat(xy, geo.epsg)


def _polygon(rings: list[np.ndarray], geo: Georef) -> dict[str, Any]:
    closed = [np.vstack([r, r[:1]]).round(8).tolist() for r in rings]
    return {
        "type": "MultiPolygon",
        "coordinates": [[ring] for ring in closed],
        "units": "lon/lat degrees" if geo.georeferenced else "mosaic pixels",
    }


def _frame_entry(frame: Frame, footprint: np.ndarray) -> dict[str, Any]:
    return {
        "index": frame.index,
        "name": frame.name,
        "gps": frame.gps,
        "size": [frame.orig_width, frame.orig_height],
        "working_scale": frame.scale,
        "footprint": np.vstack([footprint, footprint[:1]]).round(8).tolist(),
    }


def _pair_entries(pairs: list[PairRecord], frames: dict[int, Frame], align: Alignment) -> list[dict[str, Any]]:
    rms = {(p.i, p.j): p.rms_px for p in align.pair_residuals}
    dropped = {(p.i, p.j): p.reason for p in align.dropped_pairs}
    entries = []
    for p in pairs:
        pair = p.pair
        reason = dropped.get(pair) or ("" if p.accepted else "too few inliers of the pair's model")
        entries.append(
            {
                "frames": [frames[p.i].name, frames[p.j].name],
                "matches": p.matches,
                "inliers": p.inliers,
                "used": p.accepted and pair not in dropped,
                "reason_unused": reason,
                "tie_point_rms_px": rms.get(pair),
                "found_by": p.found_by,
            }
        )
    return entries


def _stage_seconds(ws: JobWorkspace, pipeline: str) -> dict[str, float]:
    out = {}
    for name in stage_names(pipeline):
        rep = ws.load_stage_report(name)
        if rep is not None:
            out[name] = rep.get("wall_seconds", 0.0)
    return out


def _footprint_collection(
    frames: dict[int, Frame], footprints: dict[int, np.ndarray], figures: dict[int, dict[str, Any]]
) -> dict[str, Any]:
    features = [
        {
            "type": "Feature",
            "properties": {"index": k, "name": frames[k].name, **figures.get(k, {})},
            "geometry": {"type": "Polygon", "coordinates": [np.vstack([c, c[:1]]).round(8).tolist()]},
        }
        for k, c in sorted(footprints.items())
    ]
    return {"type": "FeatureCollection", "features": features}


def _photo_figures(
    frames: dict[int, Frame], data: FigureData, geo: Georef, corner_sigma_m: dict[str, float]
) -> dict[int, dict[str, Any]]:
    """Per frame, what the viewer colours and shows its footprint by: ``rms_px`` (tie-point RMS in planar mode,
    reprojection RMS in ortho mode, working-copy px), ``gps_residual_m``, ``camera`` (lon, lat of the camera
    centre, or of the frame's centre in planar mode), ``gps`` (lon, lat of its fix) and, for a strip's frames,
    ``corner_sigma_m`` (its corners' standard error, by name in ``corner_sigma_m``)."""
    per_photo = {name: (rms, gps) for name, rms, gps in data.per_photo}
    out: dict[int, dict[str, Any]] = {}
    for k, frame in frames.items():
        rms, gps_residual = per_photo.get(frame.name, (None, None))
        camera = data.cameras.get(frame.name)
        fix = frame.gps or {}
        out[k] = {
            "rms_px": _rounded(rms, 4),
            "gps_residual_m": _rounded(gps_residual, 4),
            "camera": _to_crs(geo, camera[None, :])[0].round(8).tolist() if camera is not None else None,
            "gps": [fix["lon"], fix["lat"]] if fix.get("lon") is not None and fix.get("lat") is not None else None,
        }
        if frame.name in corner_sigma_m:
            out[k]["corner_sigma_m"] = corner_sigma_m[frame.name]
    return out


def _rounded(value: float | None, digits: int) -> float | None:
    return round(float(value), digits) if value is not None and np.isfinite(value) else None


def _gcp_collection(
    ws: JobWorkspace,
    cfg: MosaicConfig,
    frames: dict[int, Frame],
    align: Alignment,
    geo: Georef,
    to_out: np.ndarray,
    report: dict[str, Any],
) -> dict[str, Any] | None:
    """``gcps.geojson``: each ground control point with a surveyed position, as a point there (lon/lat), with its
    ``role``, where the map puts it (``mapped``, lon/lat) and the difference (``error_m``, east and north, and up
    in ortho mode). Ortho mode: the adjustment's control points and checkpoints. Planar mode does not use them,
    so each is a checkpoint: its marks in the photos carried through their homographies onto the mosaic. None
    when the job has no GCP file (or one that no longer reads)."""
    path = ws.gcp_file()
    if path is None or geo.epsg is None:
        return None
    sizes = {f.name: (f.orig_width, f.orig_height) for f in frames.values()}
    try:
        points = parse_gcp_file(path.name, path.read_text(encoding="utf-8"), sizes, LocalFrame(geo.epsg, 0.0, 0.0))
    except (ValueError, OSError):
        return None
    adjusted = {str(g["id"]): g for g in report.get("triangulation", {}).get("gcps", [])}
    placed = {frames[k].name: k for k in align.homographies}
    to_utm = np.array(geo.transform, np.float64).reshape(2, 3)
    features = []
    for gcp in points:
        if gcp.position is None:
            continue
        known = np.asarray(gcp.position, np.float64)
        if cfg.mode == "ortho":
            entry = adjusted.get(gcp.id, {})
            role, error = str(entry.get("role", "unused")), entry.get("error_m")
        else:
            seen = [
                apply_homography(to_out @ align.homographies[placed[name]], xy[None, :] * frames[placed[name]].scale)[0]
                for name, xy in gcp.observations.items()
                if name in placed
            ]
            mapped_en = np.mean([to_utm[:, :2] @ px + to_utm[:, 2] for px in seen], axis=0) if seen else None
            role, error = "checkpoint", (mapped_en - known[:2]).tolist() if mapped_en is not None else None
        features.append(_gcp_feature(gcp.id, role, len(gcp.observations), known, error, geo.epsg))
    return {"type": "FeatureCollection", "features": features}


def _gcp_feature(
    gcp_id: str, role: str, observations: int, known: np.ndarray, error: list[float] | None, epsg: int
) -> dict[str, Any]:
    lonlat = utm_to_lonlat(known[None, :2], epsg)[0]
    valid = isinstance(error, list) and len(error) >= 2 and all(np.isfinite(e) for e in error)
    mapped = utm_to_lonlat((known[:2] + np.asarray(error[:2]))[None, :], epsg)[0] if valid and error else None
    return {
        "type": "Feature",
        "properties": {
            "id": gcp_id,
            "role": role,
            "observations": observations,
            "elevation_m": _rounded(known[2], 3) if known.size > 2 else None,
            "mapped": mapped.round(8).tolist() if mapped is not None else None,
            "error_m": [round(float(e), 4) for e in error] if valid and error else None,
            "error_horizontal_m": round(float(np.hypot(error[0], error[1])), 4) if valid and error else None,
        },
        "geometry": {"type": "Point", "coordinates": lonlat.round(8).tolist()},
    }


def _cutline_collection(frames: dict[int, Frame], seams: dict[int, list[np.ndarray]], geo: Georef) -> dict[str, Any]:
    """``cutlines.geojson``: the region each frame owns in a multiband mosaic (its cut lines are the borders
    between them), in lon/lat, or in mosaic px when the mosaic is not georeferenced."""
    features = [
        {
            "type": "Feature",
            "properties": {"index": k, "name": frames[k].name},
            "geometry": _polygon([_to_crs(geo, ring) for ring in rings], geo),
        }
        for k, rings in sorted(seams.items())
        if k in frames
    ]
    return {"type": "FeatureCollection", "features": features}


# -- report.html: what its pictures draw, in mosaic pixels ----------------------------------------------------


def _figure_data(
    ws: JobWorkspace,
    cfg: MosaicConfig,
    frames: dict[int, Frame],
    align: Alignment,
    geo: Georef,
    to_out: np.ndarray,
    report: dict[str, Any],
) -> FigureData:
    homs = align.homographies
    corners = {
        frames[k].name: apply_homography(to_out @ H, frame_corners(frames[k].width, frames[k].height))
        for k, H in sorted(homs.items())
    }
    data = FigureData(geo.width, geo.height, geo.gsd_m, corners, _coverage(corners, geo.width, geo.height))
    if cfg.mode == "ortho":
        _ortho_geometry(ws, frames, align, geo, data, report)
    else:
        _planar_geometry(ws, frames, align, to_out, data, geo)
    if geo.georeferenced and geo.epsg is not None:
        to_px = np.linalg.inv(np.vstack([np.array(geo.transform).reshape(2, 3), [0, 0, 1]]))
        for k in homs:
            if (gps := frames[k].gps) and frames[k].name in data.cameras:
                en = lonlat_to_utm(np.array([[gps["lon"], gps["lat"]]]), geo.epsg)
                data.gps[frames[k].name] = apply_homography(to_px, en)[0]
    return data


def _coverage(corners: dict[str, np.ndarray], width: int, height: int) -> np.ndarray:
    """(gh, gw) uint8: how many footprints cover each cell of a grid over the mosaic."""
    cell = max(width, height) / COVERAGE_CELLS
    shape = (max(1, round(height / cell)), max(1, round(width / cell)))
    counts = np.zeros(shape, np.uint16)
    for c in corners.values():
        mask = np.zeros(shape, np.uint8)
        cv2.fillPoly(mask, [np.round(c / cell - 0.5).astype(np.int32)], 1)
        counts += mask
    return np.minimum(counts, 255).astype(np.uint8)


def _planar_geometry(
    ws: JobWorkspace, frames: dict[int, Frame], align: Alignment, to_out: np.ndarray, data: FigureData, geo: Georef
) -> None:
    """Camera positions (frame centres), tie points and their misfits, per-photo RMS and GPS residuals: of the
    pairs the adjustment kept (one it dropped does not fit by definition, and would blame its two photos)."""
    homs = align.homographies
    for k, H in sorted(homs.items()):
        centre = np.array([[(frames[k].width - 1) / 2, (frames[k].height - 1) / 2]])
        data.cameras[frames[k].name] = apply_homography(to_out @ H, centre)[0]
    dropped = {(p.i, p.j) for p in align.dropped_pairs}
    ties = {
        p.pair: TiePoints(*ws.load_matches(p.pair))
        for p in ws.load_pairs()
        if p.accepted and p.pair not in dropped and p.i in homs and p.j in homs
    }
    misfit = tie_residuals_px(homs, ties)
    points: list[np.ndarray] = []
    residuals: list[np.ndarray] = []
    per_frame: dict[int, list[np.ndarray]] = {k: [] for k in homs}
    for pair, r in misfit.items():
        points.append(apply_homography(to_out @ homs[pair[0]], ties[pair].points_i))
        residuals.append(r)
        per_frame[pair[0]].append(r)
        per_frame[pair[1]].append(r)
    if points:
        data.ties, data.tie_residuals_px = np.vstack(points), np.concatenate(residuals)
    data.per_photo = [
        (
            frames[k].name,
            float(np.sqrt(np.mean(np.concatenate(r) ** 2))) if r else None,
            geo.gps_residuals_m.get(frames[k].name),
        )
        for k, r in sorted(per_frame.items())
    ]


def _ortho_geometry(
    ws: JobWorkspace, frames: dict[int, Frame], align: Alignment, geo: Georef, data: FigureData, report: dict[str, Any]
) -> None:
    """Camera centres, tie points traced through the adjusted cameras to the ground plane, ground control points
    at their known and adjusted positions; per photo, its reprojection RMS and GPS residual."""
    cameras = ws.load_cameras()
    world, t = cameras["world"], report["triangulation"]
    data.per_photo = [(i["name"], i.get("rms_px"), i.get("gps_residual_m")) for i in t.get("images", [])]
    if world.get("epsg") is None or not geo.georeferenced:
        return
    to_px = np.linalg.inv(np.vstack([np.array(geo.transform).reshape(2, 3), [0, 0, 1]]))
    shift = np.array([world["easting0"], world["northing0"]])

    def local_to_px(xy: np.ndarray) -> np.ndarray:
        return apply_homography(to_px, np.asarray(xy, np.float64).reshape(-1, 2) + shift)

    camera = Camera.from_json(cameras["camera"])
    poses = {int(k): (np.array(p["R"]), np.array(p["C"])) for k, p in cameras["poses"].items()}
    for k, (_, C) in poses.items():
        data.cameras[frames[k].name] = local_to_px(C[:2])[0]
    ground: list[np.ndarray] = []
    for p in ws.load_pairs():
        if p.accepted and p.i in poses and p.j in poses:
            R, C = poses[p.i]
            rays = camera.unproject(ws.load_matches(p.pair)[0]) @ R  # world directions: R^T d
            depth = (align.ground_z or 0.0) - C[2]
            ahead = rays[:, 2] * depth > 0
            ground.append(C[:2] + rays[ahead, :2] * (depth / rays[ahead, 2])[:, None])
    if ground:
        data.ties = local_to_px(np.vstack(ground))
    _gcp_positions(ws, frames, LocalFrame(world["epsg"], *shift), t, local_to_px, data)


def _gcp_positions(
    ws: JobWorkspace, frames: dict[int, Frame], world: LocalFrame, t: dict[str, Any], local_to_px: Any, data: FigureData
) -> None:
    path = ws.gcp_file()
    if path is None:
        return
    sizes = {f.name: (f.orig_width, f.orig_height) for f in frames.values()}
    try:
        known = {g.id: g.position for g in parse_gcp_file(path.name, path.read_text(encoding="utf-8"), sizes, world)}
    except (ValueError, OSError):
        return
    for entry in t.get("gcps", []):
        position, error = known.get(entry["id"]), entry.get("error_m")
        if position is None or not isinstance(error, list) or len(error) < 2:
            continue
        at = local_to_px(position[:2])[0]
        moved = local_to_px(np.asarray(position[:2]) + np.asarray(error[:2], np.float64))[0]
        data.gcps.append((str(entry["id"]), str(entry["role"]), at, moved))


def _advice(report: dict[str, Any], data: FigureData, cfg: MosaicConfig) -> list[str]:
    """Plain-language notes on what the pictures show: single coverage, photos that fit worse than the rest,
    GPS misfits beyond the fixes' accuracy and the U-shaped misfit of a strip that bends."""
    out = []
    covered = data.coverage > 0
    single = float((data.coverage[covered] == 1).mean()) if covered.any() else 0.0
    if single > 0.1:
        out.append(
            f"{single * 100:.0f} % of the mosaic is seen by one photo only: nothing checks the alignment "
            "there. More overlap between the flight lines would."
        )
    rms = {name: t for name, t, _ in data.per_photo if t is not None}
    if len(rms) >= 3:
        median = float(np.median(list(rms.values())))
        worse = [n for n, v in rms.items() if v > max(3 * median, 1.0)]
        if worse:
            out.append(
                f"{', '.join(worse[:8])} fit{'s' if len(worse) == 1 else ''} the other photos worse than the "
                f"rest (tie-point RMS over 3 times the median of {median:.2f} px): look for motion blur, "
                "moving objects or tall relief in them."
            )
    gps = [g for _, _, g in data.per_photo if g is not None]
    rms_gps = report.get("gps_residual_rms_m")
    if isinstance(rms_gps, int | float) and rms_gps > 3 * cfg.gps_sigma_m:
        out.append(
            f"The cameras lie {rms_gps:.2f} m (RMS) from their GPS fixes, over 3 times the GPS accuracy "
            f"assumed ({cfg.gps_sigma_m:g} m): check the GPS data and the photos' order."
        )
    if len(gps) >= 5:
        n = max(1, len(gps) // 5)
        ends, middle = float(np.mean(gps[:n] + gps[-n:])), float(np.min(gps[n:-n] or [np.inf]))
        if ends > 2 * middle and ends > 0.2:
            remedy = "Ground control points" if cfg.mode == "ortho" else "Ground control points or ortho mode"
            out.append(
                f"The GPS residuals grow toward both ends of the flight ({ends:.2f} m at the ends, "
                f"{middle:.2f} m in the middle): the model bends away from the GPS track. {remedy} "
                "would hold it straight."
            )
    return out
