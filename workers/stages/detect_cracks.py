"""Stage ``detect_cracks``: the crack mask of every load step's rectified image."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from workers.algorithms.cracks import background_px, detect_cracks, load_crack_model
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

log = logging.getLogger(__name__)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN_mask.npy`` per load step: (H, W) bool crack pixels inside what the photos see."""
    try:
        model = load_crack_model()
    except (OSError, ValueError) as exc:
        # the reason (with the weights' path) is for the worker's log; the user can only ask ops to fix it
        log.error("crack detector weights unusable: %s", exc)
        raise PipelineError(
            "the crack detector's weights cannot be used; ask the operators to reinstall them"
        ) from None
    low = model.low if cfg.threshold_low is None else cfg.threshold_low
    high = model.high if cfg.threshold_high is None else cfg.threshold_high
    if low > high:
        raise PipelineError(f"options.threshold_low ({low}) is above threshold_high ({high})")
    mm_per_px = ws.load_surface().mm_per_px  # the detection raster's, set by the photos' sampling
    pixels = []
    for s in range(len(cfg.stages)):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        image, seen = ws.load_rectified(s)
        mask = detect_cracks(
            image,
            seen=seen,
            model=model,
            low=low,
            high=high,
            edge_margin_px=int(np.ceil(cfg.edge_margin_mm / mm_per_px)),
            min_contrast=cfg.min_crack_contrast,
            background_px=background_px(mm_per_px),
        )
        ws.save_crack_mask(s, mask)
        pixels.append(int(mask.sum()))
    progress(1.0, f"{len(cfg.stages)} load step(s)")
    return {"stages": len(cfg.stages), "crack_pixels": pixels}
