"""Stage ``measure_cracks``: every crack of every load stage as polylines in the rectified plane's mm, its
length along the specimen's surface and its width."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from workers.algorithms.cracks import (
    Crack,
    background_px,
    crack_coverage,
    darkening,
    measure_cracks,
    path_length,
    summarise_cracks,
    to_gray,
)
from workers.algorithms.specimen import Surface
from workers.config import CrackSurveyConfig
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN.json`` per load stage: its cracks and their totals."""
    counts, totals = [], []
    surface = ws.load_surface()
    for s in range(len(cfg.stages)):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        mask = ws.load_crack_mask(s)
        image, _ = ws.load_rectified(s)
        coverage = crack_coverage(darkening(to_gray(image), mask, background_px(surface.mm_per_px)), mask)
        cracks = [
            along_surface(c, surface)
            for c in measure_cracks(mask, surface.mm_per_px, coverage=coverage, min_length_mm=cfg.min_crack_length_mm)
        ]
        summary = summarise_cracks(cracks)
        ws.save_measured_cracks(
            s,
            cracks,
            {
                "count": summary.count,
                "total_length_mm": summary.total_length_mm,
                "mean_width_mm": summary.mean_width_mm,
                "max_width_mm": summary.max_width_mm,
                # the last edge is +inf, which JSON cannot hold: null means "no upper bound"
                "histogram_edges_mm": [None if np.isinf(e) else float(e) for e in summary.histogram_edges_mm],
                "histogram_counts": summary.histogram_counts.tolist(),
            },
        )
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
    stretch = np.concatenate(
        [surface.width_stretch(p, np.gradient(p, axis=0)) for p in crack.paths_mm if len(p) > 1] or [np.ones(1)]
    )
    return replace(
        crack,
        length_mm=sum(path_length(surface.lift(p)) for p in crack.paths_mm),
        mean_width_mm=crack.mean_width_mm * float(stretch.mean()),
        max_width_mm=crack.max_width_mm * float(stretch.max()),
    )
