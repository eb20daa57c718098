"""Stage ``write_report``: ``report.json`` (what was used, how well it fits) and frame footprints."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.geometry import utm_to_lonlat
from workers.algorithms.mosaic import apply_homography, frame_corners
from workers.config import MosaicConfig
from workers.pipeline import pipeline_key, stage_names
from workers.records import Alignment, Frame, Georef, PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


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
    report: dict[str, Any] = {
        "kind": "mosaic",
        "mode": cfg.mode,
        "config": cfg.model_dump(),
        "frames_used": [_frame_entry(frames[k], footprints[k]) for k in sorted(homs)],
        "frames_rejected": [r.to_json() for r in ws.load_rejected_frames() + align.rejected],
        "reference_frame": ref.name,
        "pairs": _pair_entries(pairs, frames, align),
        "tie_point_rms_px": rms,
        "tie_point_rms_px_original": rms / ref.scale if rms is not None else None,
        "tie_points": align.tie_points,
        "georeferenced": geo.georeferenced,
        "georeference_note": geo.reason,
        "crs": f"EPSG:{geo.epsg}" if geo.georeferenced else None,
        "gsd_m": geo.gsd_m,  # the mosaic's pixel size
        "gsd_original_m": geo.gsd_m * geo.output_scale * ref.scale if geo.gsd_m else None,  # the photos' own
        "gps_residual_rms_m": geo.gps_residual_rms_m,
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
            "photo_px_per_px": 1.0 / (geo.output_scale * ref.scale),
        },
        "stage_seconds": _stage_seconds(ws, pipeline_key("mosaic", {"mode": cfg.mode})),
    }
    if cfg.mode == "ortho":
        report["triangulation"] = ws.load_cameras()["report"]
        # what the frames were projected onto: the tie points' surface, or the plane (and why)
        report["ortho_surface"] = (ws.load_stage_report("orthorectify_frames") or {}).get("surface")
    report["warnings"] = _warnings(report)
    ws.save_report(report)
    if geo.georeferenced:
        ws.save_footprints(_footprint_collection(frames, footprints))
    seams = ws.load_seams()
    if seams is not None:
        ws.save_cutlines(_cutline_collection(frames, seams, geo))
    progress(1.0, "report")
    return {"frames_used": len(report["frames_used"]), "frames_rejected": len(report["frames_rejected"])}


def _warnings(report: dict[str, Any]) -> list[str]:
    """What a user must know before trusting the map, in words (the viewer's quality card shows them)."""
    triangulation = report.get("triangulation", {})
    out = list(triangulation.get("warnings", []))
    named = {entry["name"] for entry in triangulation.get("not_registered", [])}  # its warnings name these
    rejected = [r["name"] for r in report["frames_rejected"] if r["name"] not in named]
    if rejected:
        total = len(report["frames_rejected"]) + len(report["frames_used"])
        out.insert(0, f"{len(rejected)} of {total} frames are not in the map: {', '.join(rejected)}")
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


def _footprint_collection(frames: dict[int, Frame], footprints: dict[int, np.ndarray]) -> dict[str, Any]:
    features = [
        {
            "type": "Feature",
            "properties": {"index": k, "name": frames[k].name},
            "geometry": {"type": "Polygon", "coordinates": [np.vstack([c, c[:1]]).round(8).tolist()]},
        }
        for k, c in sorted(footprints.items())
    ]
    return {"type": "FeatureCollection", "features": features}


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
