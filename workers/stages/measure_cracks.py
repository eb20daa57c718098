"""Stage ``measure_cracks``: every crack of every load stage as polylines in the rectified plane's mm, its
length along the specimen's surface and its width (from its cross-section profile in the rectified image,
see :mod:`workers.algorithms.cracks.profile`)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from workers.algorithms.cracks import (
    Crack,
    ProfileFit,
    background_px,
    crack_coverage,
    crack_widths,
    darkening,
    line_like,
    measure_cracks,
    path_length,
    profile_widths,
    reference_contrast,
    sampling_across,
    summarise_cracks,
    to_gray,
    with_widths,
)
from workers.algorithms.specimen import Surface
from workers.config import CrackSurveyConfig
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN.json`` per load stage: its cracks and their totals."""
    counts, totals, dropped = [], [], []
    surface = ws.load_surface()
    mm = surface.mm_per_px
    n = len(cfg.stages)
    # the photos' sampling per load step (rectify_specimen), where the crack's own is not known
    photo_mm = (ws.load_stage_report("rectify_specimen") or {}).get("photo_mm_per_px") or [None] * n
    measured, fits = [], []
    for s in range(n):
        progress(0.8 * s / n, f"load step {s + 1}/{n}")
        cracks, step_fits = _measure_step(ws, cfg, s, mm, photo_mm[s] or mm)
        # blots of the coating's grain the detector took for short cracks: not lines
        kept = [
            (c, f)
            for c, f in zip(cracks, step_fits, strict=True)
            if line_like(f, c.length_mm / mm, c.mean_width_mm / mm)
        ]
        dropped.append(len(cracks) - len(kept))
        measured.append([c for c, _ in kept])
        fits.append([f for _, f in kept])
    photo_px = [[(c.photo_mm_per_px or mm) / mm for c in step] for step in measured]
    lengths = [[c.length_mm / mm for c in step] for step in measured]
    contrast = reference_contrast(fits, photo_px, lengths)  # the coating's cracks, all load steps together
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
    return {"cracks": counts, "total_length_mm": totals, "crack_contrast": contrast, "blots_dropped": dropped}


def _measure_step(
    ws: JobWorkspace, cfg: CrackSurveyConfig, s: int, mm: float, step_photo_mm: float
) -> tuple[list[Crack], list[ProfileFit | None]]:
    """Load step ``s``'s cracks measured on the detection raster (``mm`` per px), each with the photos'
    sampling across it (the load step's ``step_photo_mm`` where unknown), and their profile fits."""
    mask = ws.load_crack_mask(s)
    image, seen = ws.load_rectified(s)
    grey = to_gray(image)
    coverage = crack_coverage(darkening(grey, mask, background_px(mm)), mask)
    cracks = measure_cracks(mask, mm, coverage=coverage, min_length_mm=cfg.min_crack_length_mm)
    footprint = ws.load_photo_footprint(s)
    across = [sampling_across(c.paths_mm, *footprint) if footprint else None for c in cracks]
    cracks = [replace(c, photo_mm_per_px=a or step_photo_mm) for c, a in zip(cracks, across, strict=True)]
    paths = [[p / mm for p in c.paths_mm] for c in cracks]
    return cracks, profile_widths(grey, mask, paths, seen=seen, background_px=background_px(mm))


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
