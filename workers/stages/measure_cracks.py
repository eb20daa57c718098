"""Stage ``measure_cracks``: every crack of every load stage as polylines in the rectified plane's mm, its
length along the specimen's surface and its width (from its cross-section profile in the rectified image,
see :mod:`workers.algorithms.cracks.profile`)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from workers.algorithms.cracks import (
    Crack,
    background_px,
    crack_coverage,
    crack_widths,
    darkening,
    measure_cracks,
    path_length,
    profile_widths,
    reference_contrast,
    summarise_cracks,
    to_gray,
    with_widths,
)
from workers.algorithms.specimen import Surface
from workers.config import CrackSurveyConfig
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN.json`` per load stage: its cracks and their totals."""
    counts, totals = [], []
    surface = ws.load_surface()
    mm = surface.mm_per_px
    n = len(cfg.stages)
    # one photo pixel in raster px per load step (rectify_specimen): how narrow a profile tells its contrast
    photo_mm = (ws.load_stage_report("rectify_specimen") or {}).get("photo_mm_per_px") or [None] * n
    photo_px = [(p or mm) / mm for p in photo_mm]
    measured, fits = [], []
    for s in range(n):
        progress(0.8 * s / n, f"load step {s + 1}/{n}")
        mask = ws.load_crack_mask(s)
        image, seen = ws.load_rectified(s)
        grey = to_gray(image)
        coverage = crack_coverage(darkening(grey, mask, background_px(mm)), mask)
        measured.append(measure_cracks(mask, mm, coverage=coverage, min_length_mm=cfg.min_crack_length_mm))
        paths = [[p / mm for p in c.paths_mm] for c in measured[s]]
        fits.append(profile_widths(grey, mask, paths, seen=seen, background_px=background_px(mm)))
    contrast = reference_contrast(fits, photo_px)  # the coating's cracks, all load steps together
    for s in range(n):
        widths = crack_widths(fits[s], photo_px[s], contrast) * mm
        cracks = [along_surface(c, surface) for c in with_widths(measured[s], widths)]
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
    return {"cracks": counts, "total_length_mm": totals, "crack_contrast": contrast}


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
