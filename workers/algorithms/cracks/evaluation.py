"""Scoring a crack mask against a true one with a distance tolerance (the CrackForest evaluation)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class ToleranceCounts:
    """Pixel counts of a tolerant comparison of a predicted and a true crack mask (sum them over images)."""

    predicted_hit: int  # predicted pixels with a true pixel within the tolerance
    predicted: int
    truth_hit: int  # true pixels with a predicted pixel within the tolerance
    truth: int

    def __add__(self, other: ToleranceCounts) -> ToleranceCounts:
        return ToleranceCounts(
            self.predicted_hit + other.predicted_hit,
            self.predicted + other.predicted,
            self.truth_hit + other.truth_hit,
            self.truth + other.truth,
        )

    @property
    def precision(self) -> float:
        return self.predicted_hit / self.predicted if self.predicted else 0.0

    @property
    def recall(self) -> float:
        return self.truth_hit / self.truth if self.truth else 0.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0


def tolerance_counts(predicted: np.ndarray, truth: np.ndarray, tolerance_px: float = 2.0) -> ToleranceCounts:
    """Compare two (H, W) bool masks with a distance tolerance (the CrackForest evaluation, Shi et al. 2016).

    A predicted pixel counts as correct if a true pixel lies within ``tolerance_px`` (Euclidean, between
    pixel centres), and a true pixel as found if a predicted pixel does.
    """
    if predicted.shape != truth.shape:
        raise ValueError(f"mask shapes differ: {predicted.shape} vs {truth.shape}")

    def distance_to(mask: np.ndarray) -> np.ndarray:
        return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)

    predicted, truth = predicted.astype(bool), truth.astype(bool)
    return ToleranceCounts(
        int((distance_to(truth)[predicted] <= tolerance_px).sum()),
        int(predicted.sum()),
        int((distance_to(predicted)[truth] <= tolerance_px).sum()),
        int(truth.sum()),
    )
