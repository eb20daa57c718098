"""Test inputs for the kernels, generated on the CPU (then moved to the device under test)."""

from __future__ import annotations

import cv2
import numpy as np


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """(H, W) uint8: blurred noise plus rectangles, rich in corners."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)).astype(np.float32), (0, 0), 2.0)
    for _ in range(max(4, height * width // 4000)):
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        cv2.rectangle(
            img, (x, y), (x + int(rng.integers(5, 40)), y + int(rng.integers(5, 40))), float(rng.uniform(0, 255)), -1
        )
    return np.clip(img, 0, 255).astype(np.uint8)
