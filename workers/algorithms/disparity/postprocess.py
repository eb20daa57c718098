"""Disparity post-processing shared by both matchers: the left-right check, speckle removal, filling
of occlusions and borders from the background side, and the result record.

All maps are (H, W) float32 left-view disparities in px, NaN where invalid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Disparity:
    """A matcher's output, every array (H, W), left view, pixels.

    ``disparity`` float32, NaN where invalid (failed the checks or unmatched); ``dense`` float32, the
    same with the invalid pixels filled (equal to ``disparity`` without filling); ``filled`` bool, the
    pixels ``dense`` filled; ``confidence`` float32 in [0, 1], 0 where filled or invalid.
    """

    disparity: np.ndarray
    dense: np.ndarray
    filled: np.ndarray
    confidence: np.ndarray


def left_right_check(left: np.ndarray, right: np.ndarray, max_diff: float = 1.0) -> np.ndarray:
    """(H, W) bool: left pixels whose disparity d the right view's map confirms within ``max_diff``.

    ``left`` is indexed by left pixels, ``right`` by right pixels (x_R = x_L - d), both in px with NaN
    invalid; the right value is read at the rounded x_R.
    """
    h, w = left.shape
    x = np.arange(w, dtype=np.float32)[None, :]
    xr = np.rint(x - np.nan_to_num(left, nan=-1e6))
    inside = np.isfinite(left) & (xr >= 0) & (xr < w)
    xr_i = np.clip(xr, 0, w - 1).astype(np.intp)
    partner = np.take_along_axis(right, xr_i, axis=1)
    return inside & np.isfinite(partner) & (np.abs(left - partner) <= max_diff)


def remove_speckles(disparity: np.ndarray, max_size: int = 100, max_diff: float = 2.0) -> np.ndarray:
    """NaN out connected blobs under ``max_size`` px (neighbours within ``max_diff`` px are connected).

    ``cv2.filterSpeckles`` on the map in 1/16 px, as StereoSGBM's own speckle window does.
    """
    if max_size <= 0:
        return disparity.copy()
    fixed = np.where(np.isfinite(disparity), np.rint(disparity * 16.0), -32768).clip(-32768, 32767)
    fixed = fixed.astype(np.int16)
    cv2.filterSpeckles(fixed, -32768, max_size, int(round(max_diff * 16)))
    return np.where(fixed == -32768, np.nan, disparity).astype(np.float32)


def _nearest_along_rows(valid: np.ndarray, values: np.ndarray, reverse: bool) -> np.ndarray:
    """Per pixel, the value of the nearest valid pixel to its left (right if ``reverse``); NaN if none."""
    v, val = (valid[:, ::-1], values[:, ::-1]) if reverse else (valid, values)
    w = v.shape[1]
    index = np.where(v, np.arange(w)[None, :], -1)
    np.maximum.accumulate(index, axis=1, out=index)
    out = np.where(index >= 0, np.take_along_axis(val, np.maximum(index, 0), axis=1), np.nan)
    return out[:, ::-1] if reverse else out


def _fill_rows(disparity: np.ndarray) -> np.ndarray:
    """NaN pixels of each row take the smaller of the nearest valid values on either side."""
    valid = np.isfinite(disparity)
    before = _nearest_along_rows(valid, disparity, reverse=False)
    after = _nearest_along_rows(valid, disparity, reverse=True)
    return np.where(valid, disparity, np.fmin(before, after)).astype(np.float32)


def fill_background(disparity: np.ndarray, smooth: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN pixels along scanlines from the background side; returns ``(dense, filled)``.

    An invalid run takes the smaller (farther) of the disparities at its two ends, since occlusions
    in the left view belong to the background beside a foreground edge; a run touching the image
    border takes its one end. A ``smooth`` px median over the filled pixels then removes the streaks
    of single wrong ends. Rows with no valid pixel are then filled down the columns the same way;
    only an image with no valid pixel at all stays NaN.
    """
    valid = np.isfinite(disparity)
    dense = _fill_rows(disparity)
    if not np.isfinite(dense).all():  # whole rows invalid: the same along columns
        dense = _fill_rows(dense.T).T
    filled = ~valid & np.isfinite(dense)
    if smooth > 1 and filled.any():
        med = cv2.medianBlur(np.nan_to_num(dense, nan=0.0).astype(np.float32), smooth)
        dense = np.where(filled, med, dense).astype(np.float32)
    return dense, filled


def finish(
    disparity: np.ndarray, confidence: np.ndarray, fill: bool, speckle_size: int, speckle_diff: float
) -> Disparity:
    """Speckle removal, then (with ``fill``) background filling, into a ``Disparity`` record."""
    disp = remove_speckles(disparity, speckle_size, speckle_diff)
    if fill:
        dense, filled = fill_background(disp)
    else:
        dense, filled = disp.copy(), np.zeros(disp.shape, dtype=bool)
    conf = np.where(np.isfinite(disp), np.clip(confidence, 0.0, 1.0), 0.0).astype(np.float32)
    return Disparity(disp, dense, filled, conf)
