"""Algorithm functions on seeded synthetic data with planted truth."""

from __future__ import annotations

import numpy as np
import pytest

from workers.algorithms.geometry import fit_similarity, lonlat_to_utm, utm_epsg, utm_to_lonlat
from workers.algorithms.mosaic import (
    TiePoints,
    apply_homography,
    candidate_pairs,
    chain_homographies,
    estimate_homography,
    feather_weights,
    frame_corners,
    gain_compensation,
    is_plausible,
    local_metres,
    match_ratio,
    overlap_statistics,
    refine_homographies,
    spanning_tree,
    spread_subset,
    warp_maps,
)

PLANTED = np.array([[0.95, -0.12, 40.0], [0.10, 1.02, -25.0], [2e-5, -1e-5, 1.0]])


def test_usac_recovers_a_planted_homography_among_outliers() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1000, (400, 2))
    b = apply_homography(PLANTED, a) + rng.normal(0, 0.3, (400, 2))
    outliers = rng.choice(400, 160, replace=False)  # 40 % gross outliers
    b[outliers] = rng.uniform(0, 1000, (160, 2))
    H, inliers = estimate_homography(a, b, threshold_px=2.0)
    assert H is not None
    corners = frame_corners(1000, 1000)
    assert np.abs(apply_homography(H, corners) - apply_homography(PLANTED, corners)).max() < 0.5
    truth = np.ones(400, bool)
    truth[outliers] = False
    assert (inliers == truth).mean() > 0.97


def test_estimate_homography_with_too_few_points_is_empty() -> None:
    H, inliers = estimate_homography(np.zeros((3, 2)), np.zeros((3, 2)), 2.0)
    assert H is None and inliers.shape == (3,) and not inliers.any()


def test_ratio_matching_pairs_identical_descriptors_and_rejects_ambiguous_ones() -> None:
    rng = np.random.default_rng(1)
    desc = rng.random((200, 128)).astype(np.float32)
    perm = rng.permutation(200)
    other = desc[perm] + rng.normal(0, 0.01, (200, 128)).astype(np.float32)
    matches = match_ratio(desc, other, 0.8)
    assert len(matches) > 190 and np.all(perm[matches[:, 1]] == matches[:, 0])
    twins = np.vstack([desc[:1], desc[:1] + 1e-4])  # two near-identical candidates: ambiguous
    assert len(match_ratio(desc[:1].repeat(2, 0), twins, 0.8)) == 0


def test_spread_subset_covers_the_image() -> None:
    rng = np.random.default_rng(2)
    clustered = np.vstack([rng.uniform(0, 100, (900, 2)), rng.uniform(0, 1000, (100, 2))])
    keep = spread_subset(clustered, (1000, 1000), 100)
    assert len(keep) == 100 and len(set(keep.tolist())) == 100
    assert (keep >= 900).sum() > 50  # most of the sparse, spread points are kept over the cluster


def test_spanning_tree_takes_the_strongest_edges_from_the_best_connected_frame() -> None:
    weights = {(0, 1): 100.0, (1, 2): 80.0, (0, 2): 10.0, (2, 3): 50.0, (4, 5): 500.0}
    root, parent = spanning_tree(6, weights)
    assert root == 1 and parent == {0: 1, 2: 1, 3: 2}  # {4, 5} is a smaller component


def test_refinement_closes_a_loop_of_noisy_pairwise_homographies() -> None:
    rng = np.random.default_rng(3)
    truth = {k: np.array([[1.0, 0.0, 300.0 * k], [0.0, 1.0, 20.0 * k], [0.0, 0.0, 1.0]]) for k in range(4)}
    ties, pairwise = {}, {}
    for i, j in [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3)]:
        rel = np.linalg.inv(truth[j]) @ truth[i]
        pts_i = rng.uniform(0, 500, (150, 2)) + [300 * (j - i), 0]
        pts_i = pts_i[(pts_i[:, 0] < 640)]
        pts_j = apply_homography(rel, pts_i)
        ties[(i, j)] = TiePoints(pts_i + rng.normal(0, 0.2, pts_i.shape), pts_j + rng.normal(0, 0.2, pts_j.shape))
        drift = np.array([[1.0, 0.002, 1.5], [-0.002, 1.0, -1.0], [0.0, 0.0, 1.0]])  # chained errors add up
        pairwise[(i, j)] = drift @ rel
    root, parent = spanning_tree(4, {p: float(len(t.points_i)) for p, t in ties.items()})
    initial = chain_homographies(root, parent, pairwise)
    refined = refine_homographies(initial, ties, root, {k: (640, 480) for k in range(4)})
    corners = frame_corners(640, 480)
    for k in range(4):
        want = apply_homography(np.linalg.inv(truth[root]) @ truth[k], corners)
        assert np.abs(apply_homography(refined[k], corners) - want).max() < 0.5


def test_plausibility_rejects_folded_and_stretched_frames() -> None:
    assert is_plausible(PLANTED, 640, 480)
    assert not is_plausible(np.diag([1.0, -1.0, 1.0]), 640, 480)  # mirrored
    assert not is_plausible(np.array([[1, 0, 0], [0, 1, 0], [-0.003, 0, 1.0]]), 640, 480)  # horizon inside: folded
    assert not is_plausible(np.diag([10.0, 1.0, 1.0]), 640, 480)


def test_similarity_fit_recovers_a_planted_one_without_reflection() -> None:
    rng = np.random.default_rng(4)
    angle, scale = np.radians(37.0), 0.031
    M = np.array(
        [
            [scale * np.cos(angle), -scale * np.sin(angle), 576000.0],
            [scale * np.sin(angle), scale * np.cos(angle), 5188000.0],
            [0, 0, 1.0],
        ]
    )
    src = rng.uniform(0, 4000, (6, 2))
    fitted = fit_similarity(src, apply_homography(M, src))
    assert np.allclose(fitted, M, atol=1e-6)
    collinear = np.column_stack([np.linspace(0, 4000, 5), np.zeros(5)])
    assert np.allclose(fit_similarity(collinear, apply_homography(M, collinear)), M, atol=1e-6)
    with pytest.raises(ValueError):
        fit_similarity(np.zeros((3, 2)), np.ones((3, 2)))


def test_utm_zones_and_round_trip() -> None:
    assert utm_epsg(46.84, -91.99) == 32615  # the Brighton flight
    assert utm_epsg(-33.9, 18.4) == 32734
    assert utm_epsg(51.5, -0.1) == 32630
    with pytest.raises(ValueError):
        utm_epsg(85.0, 0.0)
    lonlat = np.array([[-91.99, 46.84], [-91.98, 46.85]])
    assert np.allclose(utm_to_lonlat(lonlat_to_utm(lonlat, 32615), 32615), lonlat, atol=1e-9)


def test_gain_compensation_undoes_planted_exposure_differences() -> None:
    rng = np.random.default_rng(5)
    ground = rng.uniform(60, 200, (100, 300, 3))
    masks = [np.zeros((100, 300), bool) for _ in range(3)]
    for k, mask in enumerate(masks):
        mask[:, 100 * k : 100 * k + 150] = True
    planted = np.array([1.0, 1.25, 0.8])
    images = [np.clip(ground / g, 0, 255) for g in planted]  # frame k is 1/g_k as bright
    means, counts = overlap_statistics(images, masks)
    gains = gain_compensation(means, counts, sigma_g=1.0)
    ratio = gains[:, 0] / gains[0, 0]
    assert np.allclose(ratio, planted / planted[0], rtol=0.02)


def test_feathering_ramps_from_the_border_and_is_zero_outside() -> None:
    map_x, map_y = warp_maps(np.eye(3), -10, 50, 120, 1)  # one row across the middle of the frame
    w = feather_weights(map_x, map_y, 100, 100, ramp_px=20)[0]
    assert w[:10].max() == 0 and w[-10:].max() == 0  # outside the frame
    assert 0 < w[10] < w[15] < w[25] and w[40] == 1.0


def test_pair_selection() -> None:
    assert len(candidate_pairs(5, None, 2, 3, 30)) == 10  # exhaustive without GPS
    assert candidate_pairs(40, None, 2, 3, 30)[:3] == [(0, 1), (0, 2), (1, 2)]
    line = local_metres(np.array([[46.84, -91.99 + 1e-4 * k] for k in range(6)]))
    pairs = candidate_pairs(6, line, 1, 1, 30)
    assert all(i < j for i, j in pairs) and (0, 1) in pairs and (0, 5) not in pairs
