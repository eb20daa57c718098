"""GPS inside the planar adjustment: a long strip whose tie points carry a small systematic bias bends
without it and follows its fixes with it."""

from __future__ import annotations

import numpy as np

from workers.algorithms.mosaic import TiePoints, apply_homography, refine_homographies

SIZE = (600, 400)  # frame width, height, px
STEP = 300.0  # along-strip spacing of frame centres, px: 50 % forward overlap
FRAMES = 16


def _strip(bias_rad: float, seed: int = 3) -> tuple[dict[int, np.ndarray], dict, dict[int, np.ndarray]]:
    """True frame -> plane homographies (frame 0 is the plane), tie points of consecutive frames rotated by
    ``bias_rad`` about frame j's centre (a keypoint bias that chains into a bend), and the chained start."""
    rng = np.random.default_rng(seed)
    truth = {k: np.array([[1.0, 0, k * STEP], [0, 1.0, 0], [0, 0, 1]]) for k in range(FRAMES)}
    c, s = np.cos(bias_rad), np.sin(bias_rad)
    cx, cy = (SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2
    bias = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0, 0, 1]])
    ties, pairwise = {}, {}
    for i in range(FRAMES - 1):
        j = i + 1
        pts_i = np.column_stack([rng.uniform(STEP, SIZE[0] - 1, 300), rng.uniform(0, SIZE[1] - 1, 300)])
        pts_j = apply_homography(bias @ np.linalg.inv(truth[j]) @ truth[i], pts_i)
        pts_j += rng.normal(0, 0.2, pts_j.shape)
        ties[(i, j)] = TiePoints(pts_i, pts_j)
        pairwise[(i, j)] = bias @ np.linalg.inv(truth[j]) @ truth[i]
    start = {0: np.eye(3)}
    for k in range(1, FRAMES):
        start[k] = start[k - 1] @ np.linalg.inv(pairwise[(k - 1, k)])
    return truth, ties, start


def _centre_errors(homs: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> np.ndarray:
    centre = np.array([[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])
    return np.array(
        [np.linalg.norm(apply_homography(homs[k], centre) - apply_homography(truth[k], centre)) for k in truth]
    )


def test_gps_keeps_a_biased_strip_straight() -> None:
    truth, ties, start = _strip(bias_rad=np.deg2rad(0.05))
    sizes = {k: SIZE for k in truth}
    ties_only = refine_homographies(start, ties, 0, sizes)
    rng = np.random.default_rng(5)
    sigma_px = 2.0
    centre = np.array([[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])
    fixes = {k: (apply_homography(H, centre)[0] + rng.normal(0, sigma_px, 2), sigma_px) for k, H in truth.items()}
    with_gps = refine_homographies(start, ties, 0, sizes, positions=fixes)
    bent, held = _centre_errors(ties_only, truth), _centre_errors(with_gps, truth)
    assert bent.max() > 10.0, bent  # the bias chains into a bend the tie points cannot see
    assert held.max() < 2.0 * sigma_px, held  # within the fixes' noise, not the bend
    # the tie points still meet: the GPS moves frames along the strip's slack, not against the ties
    for (i, j), t in ties.items():
        moved = apply_homography(np.linalg.inv(with_gps[j]) @ with_gps[i], t.points_i)
        assert np.sqrt(np.mean(np.sum((moved - t.points_j) ** 2, axis=1))) < 1.5


def test_loose_fixes_leave_the_tie_point_solution_alone() -> None:
    truth, ties, start = _strip(bias_rad=0.0)
    sizes = {k: SIZE for k in truth}
    ties_only = refine_homographies(start, ties, 0, sizes)
    centre = np.array([[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])
    far = {k: (apply_homography(H, centre)[0] + np.array([40.0, -25.0]), 1e6) for k, H in truth.items()}
    loose = refine_homographies(start, ties, 0, sizes, positions=far)
    assert np.abs(_centre_errors(loose, truth) - _centre_errors(ties_only, truth)).max() < 0.01
