"""Guided matching: tie points correlated where a homography predicts, on a planted homography."""

from __future__ import annotations

import cv2
import numpy as np

from tests.scenes import make_texture
from workers.algorithms.mosaic import apply_homography, guided_tie_points, overlap_share, tie_corners

SIZE = (640, 480)  # frame width, height, px
# frame i px -> frame j px: rotated 8 degrees, scaled 1.05, shifted so about half of frame i is in frame j
C, S = 1.05 * np.cos(np.deg2rad(8)), 1.05 * np.sin(np.deg2rad(8))
TRUE_H = np.array([[C, -S, -300.0], [S, C, 20.0], [1e-5, 0.0, 1.0]])


def _pair() -> tuple[np.ndarray, np.ndarray]:
    texture = cv2.cvtColor(make_texture(1200, 1600, seed=8), cv2.COLOR_BGR2GRAY)
    gray_i = np.ascontiguousarray(texture[200:680, 300:940])
    to_texture_i = np.array([[1.0, 0, 300], [0, 1, 200], [0, 0, 1]])  # frame i px -> texture px
    gray_j = cv2.warpPerspective(
        texture, np.linalg.inv(to_texture_i @ np.linalg.inv(TRUE_H)), SIZE, flags=cv2.INTER_LINEAR
    )
    return gray_i, gray_j


def test_overlap_share_of_a_shift() -> None:
    shift = np.array([[1.0, 0, -192.0], [0, 1, 0], [0, 0, 1]])  # 30 % of the width leaves frame j
    assert overlap_share(shift, SIZE, SIZE) == np.float64(0.7) or abs(overlap_share(shift, SIZE, SIZE) - 0.7) < 1e-6
    away = np.array([[1.0, 0, -2000.0], [0, 1, 0], [0, 0, 1]])
    assert overlap_share(away, SIZE, SIZE) == 0.0
    mirrored = np.diag([-1.0, 1.0, 1.0])
    assert overlap_share(mirrored, SIZE, SIZE) == 0.0  # a folded model overlaps nothing


def test_guided_tie_points_find_the_truth_from_a_prediction_off_by_pixels() -> None:
    gray_i, gray_j = _pair()
    off = np.array([[1.0, 0, 5.0], [0, 1, -4.0], [0, 0, 1]]) @ TRUE_H  # the prediction misses by 6.4 px
    corners = tie_corners(gray_i)
    pts_i, pts_j = guided_tie_points(gray_i, gray_j, corners, off, max_points=300, search_px=12)
    errors = np.linalg.norm(apply_homography(TRUE_H, pts_i) - pts_j, axis=1)
    assert len(pts_i) > 150, len(pts_i)
    assert np.median(errors) < 0.1 and np.percentile(errors, 95) < 0.3, (np.median(errors), errors.max())
    # spread over the overlap: the points' hull covers most of what frame i shares with frame j
    hull = cv2.contourArea(cv2.convexHull(pts_i.astype(np.float32)))
    assert hull > 0.6 * overlap_share(TRUE_H, SIZE, SIZE) * SIZE[0] * SIZE[1]


def test_guided_tie_points_find_nothing_where_the_prediction_is_too_far() -> None:
    gray_i, gray_j = _pair()
    off = np.array([[1.0, 0, 40.0], [0, 1, 0], [0, 0, 1]]) @ TRUE_H  # 40 px: beyond a 12 px search
    pts_i, pts_j = guided_tie_points(gray_i, gray_j, tie_corners(gray_i), off, max_points=300, search_px=12)
    errors = np.linalg.norm(apply_homography(TRUE_H, pts_i) - pts_j, axis=1)
    assert len(pts_i) < 20 or np.median(errors) > 5  # no false tie points passed off as true ones


def test_a_frame_in_many_overlaps_measures_fewer_tie_points_a_pair() -> None:
    """tie_points_per_frame is shared among the pairs of the less busy frame of each pair, at most
    max_tie_points_per_pair: a strip's end pair keeps the most, a pair between two busy frames the fewest."""
    from workers.config import MosaicConfig
    from workers.stages.measure_ties import tie_budgets

    cfg = MosaicConfig(tie_points_per_frame=600, max_tie_points_per_pair=400)
    assert tie_budgets([(0, 1), (1, 2)], cfg) == {(0, 1): 400, (1, 2): 400}  # a 3-frame strip: 600 and 300
    # five frames that all overlap (4 pairs each), and frame 5 overlapping frame 0 alone
    block = [(i, j) for i in range(5) for j in range(i + 1, 5)] + [(0, 5)]
    budgets = tie_budgets(block, cfg)
    assert budgets[(0, 5)] == 400  # frame 5's only pair: 600, capped
    assert {budgets[p] for p in block if p != (0, 5)} == {150}  # 600 / 4 (frame 0's 5 pairs: the other has 4)
    triangle_and_tail = tie_budgets([(0, 1), (1, 2), (0, 2), (2, 3)], MosaicConfig(tie_points_per_frame=300))
    assert triangle_and_tail == {(0, 1): 150, (1, 2): 150, (0, 2): 150, (2, 3): 300}
