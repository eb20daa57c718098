"""Reading a Middlebury pair as laid out in ``../shared/data/stereo_middlebury`` (benchmark data).

This is file reading, which ``algorithms`` otherwise avoids; it sits beside the scorer so the tests
and ``bench/stereo.py`` share one decoding of each set's ground-truth scale factor and masks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

# folder -> (left, right, truth, truth scale (stored / px), non-occlusion mask or None)
LAYOUTS = {
    "tsukuba": ("tsukuba_l.png", "tsukuba_r.png", "groundtruth.png", 16.0, "nonocc.png"),
    "teddy": ("im2.png", "im6.png", "disp2.pgm", 4.0, None),
}


@dataclass(frozen=True)
class StereoPair:
    """``left``, ``right`` (H, W, 3) uint8 BGR; ``truth`` (H, W) float32 px, NaN unknown; ``mask``
    (H, W) bool non-occluded, or None when the set has none."""

    name: str
    left: np.ndarray
    right: np.ndarray
    truth: np.ndarray
    mask: np.ndarray | None


def read_pair(folder: Path) -> StereoPair:
    """The pair in ``folder`` (its name picks the layout); ``ValueError`` for an unknown set."""
    if folder.name not in LAYOUTS:
        raise ValueError(f"unknown Middlebury set {folder.name!r}; known: {sorted(LAYOUTS)}")
    left_name, right_name, truth_name, scale, mask_name = LAYOUTS[folder.name]
    left = cv2.imread(str(folder / left_name), cv2.IMREAD_COLOR)
    right = cv2.imread(str(folder / right_name), cv2.IMREAD_COLOR)
    raw = cv2.imread(str(folder / truth_name), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None or raw is None:
        raise ValueError(f"cannot read the images of {folder.name}")
    truth = np.where(raw > 0, raw.astype(np.float32) / scale, np.nan).astype(np.float32)
    mask = None
    if mask_name is not None:
        m = cv2.imread(str(folder / mask_name), cv2.IMREAD_GRAYSCALE)
        mask = None if m is None else m > 0
    return StereoPair(folder.name, left, right, truth, mask)
