"""Stage ``measure_cracks``: every crack of every load stage as polylines in the rectified plane's mm, its
length along the specimen's surface and its width."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from workers.algorithms.crack_geometry import (
    Crack,
    crack_coverage,
    darkening,
    measure_cracks,
    path_length,
    summarise_cracks,
)
from workers.algorithms.cracks import to_gray
from workers.algorithms.specimen_surface import Surface
from workers.config import CrackSurveyConfig
from workers.stages.detect_cracks import background_px
from workers.stages.rectify_specimen import load_surface
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, read_json, write_json


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN.json`` per load stage: its cracks and their totals."""
    counts, totals = [], []
    surface = load_surface(ws)
    for s in range(len(cfg.stages)):
        progress(s / len(cfg.stages), f"stage {s + 1}/{len(cfg.stages)}")
        mask = ws.load_crack_mask(s)
        image, _ = ws.load_rectified(s)
        coverage = crack_coverage(darkening(to_gray(image), mask, background_px(cfg.mm_per_px)), mask)
        cracks = [along_surface(c, surface) for c in measure_cracks(mask, cfg.mm_per_px, coverage=coverage,
                                                                    min_length_mm=cfg.min_crack_length_mm)]
        summary = summarise_cracks(cracks)
        write_json(ws.measured_cracks_file(s), {
            "cracks": [crack_to_json(c) for c in cracks],
            "summary": {"count": summary.count, "total_length_mm": summary.total_length_mm,
                        "mean_width_mm": summary.mean_width_mm, "max_width_mm": summary.max_width_mm,
                        # the last edge is +inf, which JSON cannot hold: null means "no upper bound"
                        "histogram_edges_mm": [None if np.isinf(e) else float(e) for e in summary.histogram_edges_mm],
                        "histogram_counts": summary.histogram_counts.tolist()},
        })
        counts.append(summary.count)
        totals.append(round(summary.total_length_mm, 2))
    progress(1.0, f"{sum(counts)} crack(s)")
    return {"cracks": counts, "total_length_mm": totals}


def along_surface(crack: Crack, surface: Surface) -> Crack:
    """``crack`` (measured on the plane) measured along the specimen's surface: its paths lifted to their
    height above the plane for the length, its widths stretched by the surface's slope across it, averaged
    along the crack (no change on a plate)."""
    if surface.flat:
        return crack
    stretch = np.concatenate([surface.width_stretch(p, np.gradient(p, axis=0)) for p in crack.paths_mm
                              if len(p) > 1] or [np.ones(1)])
    return replace(crack, length_mm=sum(path_length(surface.lift(p)) for p in crack.paths_mm),
                   mean_width_mm=crack.mean_width_mm * float(stretch.mean()),
                   max_width_mm=crack.max_width_mm * float(stretch.max()))


def crack_to_json(crack: Crack) -> dict[str, Any]:
    return {"paths_mm": [p.tolist() for p in crack.paths_mm], "length_mm": crack.length_mm,
            "mean_width_mm": crack.mean_width_mm, "max_width_mm": crack.max_width_mm,
            "orientation_deg": crack.orientation_deg, "endpoints_mm": crack.endpoints_mm.tolist(),
            "bbox_mm": list(crack.bbox_mm)}


def crack_from_json(data: dict[str, Any]) -> Crack:
    return Crack(paths_mm=tuple(np.array(p, dtype=np.float64).reshape(-1, 2) for p in data["paths_mm"]),
                 length_mm=float(data["length_mm"]), mean_width_mm=float(data["mean_width_mm"]),
                 max_width_mm=float(data["max_width_mm"]), orientation_deg=float(data["orientation_deg"]),
                 endpoints_mm=np.array(data["endpoints_mm"], dtype=np.float64).reshape(-1, 2),
                 bbox_mm=(float(data["bbox_mm"][0]), float(data["bbox_mm"][1]), float(data["bbox_mm"][2]),
                          float(data["bbox_mm"][3])))


def load_stage_cracks(ws: JobWorkspace, stage: int) -> tuple[list[Crack], dict[str, Any]]:
    """The measured cracks of load stage ``stage`` and its summary."""
    data = read_json(ws.measured_cracks_file(stage))
    return [crack_from_json(c) for c in data["cracks"]], dict(data["summary"])
