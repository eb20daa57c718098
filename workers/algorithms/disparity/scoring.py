"""Dense scoring of a disparity map against ground truth (the Middlebury bad-pixel rate)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Score:
    """``bad``: fraction of scored pixels whose error is over the threshold or that have no value;
    ``valid_bad``: the same over the pixels with a value only; ``density``: fraction with a value;
    ``pixels``: how many were scored (ground truth known, non-occluded where a mask was given)."""

    bad: float
    valid_bad: float
    density: float
    pixels: int


def score_disparity(
    disparity: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None, threshold: float = 1.0
) -> Score:
    """Score an (H, W) map (px, NaN = no value) against ``truth`` (H, W) px, NaN or <= 0 = unknown.

    ``mask`` (H, W) bool restricts the scored pixels (the non-occluded ones). A pixel is bad when
    |d - truth| > ``threshold`` or it has no value (Scharstein & Szeliski 2002, dense evaluation).
    """
    if disparity.shape != truth.shape or (mask is not None and mask.shape != truth.shape):
        raise ValueError("disparity, truth and mask must have the same shape")
    scored = np.isfinite(truth) & (truth > 0)
    if mask is not None:
        scored &= mask.astype(bool)
    n = int(scored.sum())
    if n == 0:
        return Score(float("nan"), float("nan"), float("nan"), 0)
    d, t = disparity[scored], truth[scored]
    has = np.isfinite(d)
    wrong = np.abs(d[has] - t[has]) > threshold
    valid_bad = float(wrong.mean()) if has.any() else float("nan")
    bad = (int(wrong.sum()) + int((~has).sum())) / n
    return Score(bad, valid_bad, float(has.mean()), n)
