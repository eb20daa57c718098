"""The source work's local matcher (``gpu_kernels.stereo_local``) with the same checks and filling
as the semi-global one: left-right consistency from the same costs, a uniqueness threshold, speckle
removal and background filling."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from gpu_kernels.backend import Device, to_device, to_host
from gpu_kernels.stereo_local import match_local
from workers.algorithms.disparity.postprocess import Disparity, finish, left_right_check


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an (H, W) or (H, W, 3) BGR image."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image.astype(np.float32)


def local(
    left: np.ndarray,
    right: np.ndarray,
    num_disparities: int = 64,
    min_disparity: int = 0,
    *,
    fundamental: np.ndarray | None = None,
    vertical_radius: int = 1,
    epipolar_weight: float = 0.5,
    window_radius: int = 6,
    truncate: float | None = 15.0,
    min_ratio: float = 1.05,
    lr_max_diff: float = 1.0,
    speckle_size: int = 100,
    speckle_diff: float = 2.0,
    fill: bool = True,
    device: Device = "cpu",
) -> Disparity:
    """Local 2-D window matching with a soft epipolar constraint, checked and filled.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) uint8 (BGR), near-rectified
    num_disparities, min_disparity : d = x_L - x_R in [min_disparity, min_disparity + num_disparities)
    fundamental : (3, 3) F, x_R^T F x_L = 0; default the rectified one
    vertical_radius, epipolar_weight, window_radius, truncate : see ``match_local`` (grey levels
        0-255; ``truncate`` clamps |I_L - I_R| so occluded window pixels do not dominate)
    min_ratio : a winner must beat the second best (more than 1 px away) by this factor
    lr_max_diff : largest disagreement (px) between the left and right views
    speckle_size, speckle_diff : blobs under ``speckle_size`` px are removed (see ``remove_speckles``)
    fill : fill invalid pixels from the background side (``filled``, confidence 0)
    device : ``cpu`` (NumPy) or ``cuda`` (CuPy), chosen by the caller

    Confidence is 1 - best / second-best cost on the pixels that pass the checks. The defaults were
    tuned on tsukuba and teddy (window radius 3/4/6, truncation 15/30, ratio 1/1.05; bench/stereo.py).
    """
    if left.shape != right.shape:
        raise ValueError("left and right must have the same shape")
    lg: Any = to_device(grey(left), device)
    rg: Any = to_device(grey(right), device)
    m = match_local(
        lg,
        rg,
        num_disparities,
        min_disparity,
        vertical_radius=vertical_radius,
        fundamental=fundamental,
        epipolar_weight=epipolar_weight,
        window_radius=window_radius,
        truncate=truncate,
    )
    disp, right_disp, ratio = to_host(m.disparity), to_host(m.right_disparity), to_host(m.ratio)
    ok = left_right_check(disp, right_disp, lr_max_diff) & (ratio >= min_ratio)
    with np.errstate(divide="ignore", invalid="ignore"):
        confidence = np.where(ok, 1.0 - 1.0 / np.maximum(ratio, 1.0), 0.0)
    disparity = np.where(ok, disp, np.nan).astype(np.float32)
    return finish(disparity, confidence, fill, speckle_size, speckle_diff)
