"""ORB features and their Hamming matching, on a planted homography (a real frame where present, a
synthetic texture always)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.scenes import make_texture
from workers.algorithms.mosaic import apply_homography, estimate_homography, registration_copy
from workers.algorithms.mosaic.binary_features import detect_orb, match_hamming

BRIGHTON = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "drone_brighton_strip1"
PLANTED = np.array([[0.95, 0.12, 40.0], [-0.1, 0.97, 25.0], [2e-5, -1e-5, 1.0]])


def _registration_error(gray: np.ndarray) -> tuple[float, int]:
    warped = cv2.warpPerspective(gray, PLANTED, (gray.shape[1], gray.shape[0]))
    (pa, da), (pb, db) = detect_orb(gray, 2000), detect_orb(warped, 2000)
    assert da.dtype == np.uint8 and da.shape[1] == 32 and len(pa) > 500
    matches = match_hamming(da, db, 0.75)
    H, inliers = estimate_homography(pa[matches[:, 0]], pb[matches[:, 1]], 2.0)
    assert H is not None
    h, w = gray.shape
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    return float(np.linalg.norm(apply_homography(H, corners) - apply_homography(PLANTED, corners), axis=1).max()), int(
        inliers.sum()
    )


def test_orb_registers_a_synthetic_texture() -> None:
    gray = cv2.cvtColor(make_texture(576, 1024, seed=3), cv2.COLOR_BGR2GRAY)
    error, inliers = _registration_error(gray)
    assert error < 1.0 and inliers > 200, (error, inliers)


@pytest.mark.skipif(not BRIGHTON.is_dir(), reason="needs ../shared/data/drone_brighton_strip1 (see its MANIFEST.md)")
def test_orb_registers_a_real_frame() -> None:
    photo = sorted(BRIGHTON.glob("*.JPG"))[0]
    gray, _ = registration_copy(cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE), 1024)
    error, inliers = _registration_error(gray)
    assert error < 1.0 and inliers > 300, (error, inliers)


def test_hamming_matches_are_mutual_and_pass_the_ratio_test() -> None:
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    perm = rng.permutation(300)
    b = a[perm].copy()
    b[:, 0] ^= 1  # one bit off each: still far nearer its partner than any other row
    matches = match_hamming(a, b, 0.75)
    assert len(matches) == 300 and np.all(perm[matches[:, 1]] == matches[:, 0])
    assert len(match_hamming(a, rng.integers(0, 256, (300, 32), dtype=np.uint8), 0.75)) < 10  # unrelated: none
