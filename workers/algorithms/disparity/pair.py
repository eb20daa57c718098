"""One call for a rectified pair whatever the matcher: the local method run in strips within a memory
budget, and the result restricted to the pixels both photos cover (rectified photos have empty corners)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from gpu_kernels.backend import Device
from workers.algorithms.disparity.local import local
from workers.algorithms.disparity.postprocess import Disparity, fill_background, finish
from workers.algorithms.disparity.sgbm import sgbm

Method = Literal["sgbm", "local"]
LOCAL_BYTES_PER_CANDIDATE = 9  # the local matcher's cost slabs, per pixel and disparity (gpu_kernels.stereo_local)
SPECKLE_SIZE, SPECKLE_DIFF = 100, 2.0  # both matchers' speckle filter: blobs under 100 px, 2 px steps


def match_pair(
    left: np.ndarray,
    right: np.ndarray,
    method: Method,
    min_disparity: int,
    num_disparities: int,
    *,
    valid_left: np.ndarray | None = None,
    valid_right: np.ndarray | None = None,
    fundamental: np.ndarray | None = None,
    fill: bool = True,
    device: Device = "cpu",
    max_bytes: int = 1 << 30,
) -> Disparity:
    """The disparity of a rectified pair, checked, speckle-filtered and (with ``fill``) filled.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) uint8, rectified
    method : ``sgbm`` (``disparity.sgbm``) or ``local`` (``disparity.local``, the source work's method)
    min_disparity, num_disparities : d = x_L - x_R in [min, min + num)
    valid_left, valid_right : (H, W) bool, the pixels each photo covers; a left pixel outside its photo, or
        whose match falls outside the right one, has no disparity and is never filled
    fundamental : F of the rectified pair for the local method's soft epipolar constraint
    device : where the local method runs; max_bytes : its cost slabs' budget per strip of rows
    """
    if left.shape != right.shape:
        raise ValueError(f"the rectified photos differ in size: {left.shape[:2]} and {right.shape[:2]}")
    if method == "sgbm":
        raw = sgbm(left, right, num_disparities, min_disparity, fill=False)
    elif method == "local":
        raw = _local_in_strips(left, right, min_disparity, num_disparities, fundamental, device, max_bytes)
    else:
        raise ValueError(f"unknown method {method!r}; expected 'sgbm' or 'local'")
    return restrict(raw, valid_left, valid_right, fill)


def _local_in_strips(
    left: np.ndarray,
    right: np.ndarray,
    min_d: int,
    num_d: int,
    fundamental: np.ndarray | None,
    device: Device,
    max_bytes: int,
) -> Disparity:
    """``local`` over strips of rows that fit ``max_bytes``, each with a margin its windows reach into."""
    h, w = left.shape[:2]
    margin = 8  # >= window_radius (6) + vertical_radius (1) of ``local``'s defaults
    rows = max(16, int(max_bytes // (LOCAL_BYTES_PER_CANDIDATE * num_d * w)) - 2 * margin)
    disparity = np.full((h, w), np.nan, np.float32)
    confidence = np.zeros((h, w), np.float32)
    for top in range(0, h, rows):
        lo, hi = max(0, top - margin), min(h, top + rows + margin)
        with np.errstate(invalid="ignore"):  # the V fit meets inf - inf beside the range's ends; they are masked
            part = local(
                left[lo:hi],
                right[lo:hi],
                num_d,
                min_d,
                fundamental=_shifted_rows(fundamental, lo),
                speckle_size=0,
                fill=False,
                device=device,
            )
        keep = slice(top - lo, top - lo + min(rows, h - top))
        disparity[top : top + rows] = part.disparity[keep]
        confidence[top : top + rows] = part.confidence[keep]
    return finish(disparity, confidence, False, SPECKLE_SIZE, SPECKLE_DIFF)


def _shifted_rows(fundamental: np.ndarray | None, rows: int) -> np.ndarray | None:
    """F of a strip starting ``rows`` down: both photos' points move by the same row offset."""
    if fundamental is None or rows == 0:
        return fundamental
    shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, float(rows)], [0.0, 0.0, 1.0]])
    return np.asarray(shift.T @ fundamental @ shift)


def restrict(raw: Disparity, valid_left: np.ndarray | None, valid_right: np.ndarray | None, fill: bool) -> Disparity:
    """``raw`` without the pixels outside the left photo or matched outside the right one, then filled from
    the background side (within the left photo only) when ``fill``."""
    disparity = raw.disparity.copy()
    h, w = disparity.shape
    inside = np.ones((h, w), bool) if valid_left is None else valid_left.astype(bool)
    if valid_right is not None:
        xr = np.rint(np.arange(w)[None, :] - np.nan_to_num(disparity, nan=0.0)).astype(np.int64)
        on = (xr >= 0) & (xr < w)
        partner = np.take_along_axis(valid_right.astype(bool), np.clip(xr, 0, w - 1), axis=1)
        disparity[~(on & partner)] = np.nan
    disparity[~inside] = np.nan
    confidence = np.where(np.isfinite(disparity), raw.confidence, 0.0).astype(np.float32)
    if fill and np.isfinite(disparity).any():
        dense, filled = fill_background(disparity)
        dense[~inside] = np.nan
        filled &= inside
    else:
        dense, filled = disparity.copy(), np.zeros((h, w), bool)
    return Disparity(disparity, dense.astype(np.float32), filled, confidence)
