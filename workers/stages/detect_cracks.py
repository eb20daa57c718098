"""Stage ``detect_cracks``: the crack mask of every load stage's rectified image."""

from __future__ import annotations

from functools import partial
from typing import Any

import cv2
import numpy as np
from scipy import ndimage as ndi

from workers.algorithms.crack_geometry import darkening
from workers.algorithms.cracks import (
    CrackModel,
    crack_probability,
    hysteresis_threshold,
    load_crack_model,
    remove_short_components,
    to_gray,
)
from workers.algorithms.tiling import map_in_tiles
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

# The detector runs over tiles of the rectified raster (its features hold ~200 B per pixel): 1024 px kept,
# 128 px of context around each, past the reach of its widest filter (3 sigma of the illumination model
# at half resolution, 120 px) and of its network's receptive field.
TILE_PX = 1024
TILE_MARGIN_PX = 128


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``cracks/stage_NN_mask.npy`` per load stage: (H, W) bool crack pixels inside what the photos see."""
    margin_px = int(np.ceil(cfg.edge_margin_mm / cfg.mm_per_px))
    try:
        model = load_crack_model()
    except (OSError, ValueError) as exc:
        raise PipelineError(f"the crack detector's weights cannot be used: {exc}") from None
    low = model.low if cfg.threshold_low is None else cfg.threshold_low
    high = model.high if cfg.threshold_high is None else cfg.threshold_high
    if low > high:
        raise PipelineError(f"options.threshold_low ({low}) is above threshold_high ({high})")
    pixels = []
    for s in range(len(cfg.stages)):
        progress(s / len(cfg.stages), f"stage {s + 1}/{len(cfg.stages)}")
        image, seen = ws.load_rectified(s)
        # unseen parts get the seen part's median: a hard black border would look like a crack to the detector
        filled = image.copy()
        filled[~seen] = np.median(image[seen], axis=0).astype(np.uint8)
        mask = dark_enough(filled, detect_in_tiles(filled, model, low, high) & _trusted(seen, margin_px),
                           cfg.min_crack_contrast, background_px(cfg.mm_per_px))
        ws.save_crack_mask(s, mask)
        pixels.append(int(mask.sum()))
    progress(1.0, f"{len(cfg.stages)} stage(s)")
    return {"stages": len(cfg.stages), "crack_pixels": pixels}


def detect_in_tiles(image: np.ndarray, model: CrackModel, low: float, high: float) -> np.ndarray:
    """(H, W) bool crack mask of (H, W, 3) BGR ``image``: the model's probability over tiles, then hysteresis
    and the model's minimum extent over the whole raster (a crack may cross tiles)."""
    probability = map_in_tiles(image, partial(crack_probability, model=model), TILE_PX, TILE_MARGIN_PX)
    return remove_short_components(hysteresis_threshold(probability, low, high), model.min_length_px)


def background_px(mm_per_px: float) -> float:
    """Scale of the coating's local grey level around a crack, px: 2 mm, at least 4 px."""
    return max(2.0 / mm_per_px, 4.0)


def _trusted(seen: np.ndarray, margin_px: int) -> np.ndarray:
    """(H, W) bool: seen pixels at least ``margin_px`` from the unseen part and from the specimen's edges,
    where the plate's own edge or the end of a photo would be found as a crack."""
    if margin_px <= 0:
        return seen
    padded = np.pad(seen, margin_px, constant_values=False).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    inner = cv2.erode(padded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return inner[margin_px:-margin_px, margin_px:-margin_px].astype(bool)


def dark_enough(image: np.ndarray, mask: np.ndarray, min_contrast: float, background_px: float) -> np.ndarray:
    """``mask`` without the 8-connected cracks whose median darkening is below ``min_contrast``.

    Parameters
    ----------
    image : (H, W, 3) uint8 BGR rectified image.
    mask : (H, W) bool detected crack pixels.
    min_contrast : least median of ``1 - grey / background`` over a crack's pixels.
    background_px : Gaussian scale of the coating's local grey level around a crack (crack pixels excluded), px.
    """
    if min_contrast <= 0 or not mask.any():
        return mask
    labels, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    medians = ndi.median(darkening(to_gray(image), mask, background_px), labels, index=np.arange(1, n + 1))
    keep = np.r_[False, np.asarray(medians) >= min_contrast]
    return np.asarray(keep[labels])
