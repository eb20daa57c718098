"""ORB features and their Hamming matching, on a planted homography (a real frame where present, a
synthetic texture always)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.scenes import make_texture
from workers.algorithms.mosaic import apply_homography, estimate_homography, match_ratio, registration_copy
from workers.algorithms.mosaic.binary_features import detect_orb
from workers.algorithms.mosaic.features import HammingIndex, OverlapGuide

BRIGHTON = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "drone_brighton_strip1"
PLANTED = np.array([[0.95, 0.12, 40.0], [-0.1, 0.97, 25.0], [2e-5, -1e-5, 1.0]])


def _registration_error(gray: np.ndarray) -> tuple[float, int]:
    warped = cv2.warpPerspective(gray, PLANTED, (gray.shape[1], gray.shape[0]))
    (pa, da), (pb, db) = detect_orb(gray, 2000), detect_orb(warped, 2000)
    assert da.dtype == np.uint8 and da.shape[1] == 32 and len(pa) > 500
    matches = match_ratio(da, db, 0.75)
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
    matches = match_ratio(a, b, 0.75)
    assert len(matches) == 300 and np.all(perm[matches[:, 1]] == matches[:, 0])
    assert len(match_ratio(a, rng.integers(0, 256, (300, 32), dtype=np.uint8), 0.75)) < 10  # unrelated: none


def test_guided_hamming_search_finds_the_overlap_matches_at_a_fraction_of_the_work() -> None:
    """Two frames overlapping by a third: searched only where the probe's homography says they overlap (on
    both sides), the matches are those of the full search inside the overlap, and every one is right."""
    texture = cv2.cvtColor(make_texture(600, 1800, seed=5), cv2.COLOR_BGR2GRAY)
    left, right = texture[:, :1000], texture[:, 700:1700]  # frame b = frame a shifted 700 px
    (pa, da), (pb, db) = detect_orb(left, 3000), detect_orb(right, 3000)
    full = match_ratio(da, db, 0.75)
    guided = match_ratio(da, db, 0.75, min_matches=25, guide=OverlapGuide(pa, pb, (1000, 600), 2.0, (1000, 600)))

    def right(m: np.ndarray) -> int:
        return int(np.all(np.abs(pb[m[:, 1]] - pa[m[:, 0]] - [-700.0, 0.0]) < 2.0, axis=1).sum())

    assert right(guided) >= 0.95 * right(full) and right(guided) > 200, (right(guided), right(full))
    assert right(guided) >= 0.95 * len(guided), (right(guided), len(guided))  # the ratio test still holds
    index = HammingIndex(db)
    cut = index.restricted(pb[:, 0] < 300)
    assert len(cut.data) == int((pb[:, 0] < 300).sum()) and np.all(pb[cut.rows, 0] < 300)
