"""Registration at reduced size: features on a shrunk copy given back in working pixels, tie points
refined on the working copies, mutual ratio matching, and window composition against the map-based
reference; seeded synthetic data with planted truth."""

from __future__ import annotations

import cv2
import numpy as np

from tests.scenes import make_texture
from workers.algorithms.mosaic import (
    apply_homography,
    compose_block,
    feather_weights,
    match_ratio,
    output_box,
    refine_tie_points,
    registration_copy,
    to_full_pixels,
    warp_maps,
)

PLANTED = np.array([[0.97, -0.08, 30.0], [0.07, 1.01, -20.0], [1e-5, -2e-5, 1.0]])


def _blob_centroid(image: np.ndarray) -> np.ndarray:
    w = image.astype(np.float64)
    ys, xs = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()


def test_points_on_the_registration_copy_map_back_to_the_same_ground() -> None:
    full = np.zeros((600, 1000), np.float32)
    truth = np.array([412.3, 251.7])
    ys, xs = np.mgrid[0:600, 0:1000]
    full[:] = 200 * np.exp(-((xs - truth[0]) ** 2 + (ys - truth[1]) ** 2) / (2 * 6.0**2))
    small, factors = registration_copy(full.astype(np.uint8), 250)
    assert max(small.shape) == 250 and factors[0] == small.shape[1] / 1000
    found = to_full_pixels(_blob_centroid(small)[None].astype(np.float32), factors)[0]
    assert np.linalg.norm(found - truth) < 0.1  # pixel-centre convention kept through the shrink
    same, unit = registration_copy(small, 4000)
    assert same is small and unit == (1.0, 1.0)


def test_ncc_refinement_recovers_tie_points_to_a_tenth_of_a_pixel() -> None:
    rng = np.random.default_rng(3)
    gray_i = cv2.cvtColor(make_texture(500, 700, seed=2), cv2.COLOR_BGR2GRAY)
    gray_j = cv2.warpPerspective(gray_i, PLANTED, (700, 500), flags=cv2.INTER_LINEAR)
    points_i = rng.uniform([120, 120], [520, 340], (150, 2))
    points_j = apply_homography(PLANTED, points_i) + rng.uniform(-1.5, 1.5, (150, 2))  # registration error
    out_i, out_j, refined = refine_tie_points(gray_i, gray_j, points_i, points_j, PLANTED)
    assert refined.mean() > 0.9
    assert np.all(out_i[refined] == np.rint(out_i[refined]))  # frame i's points sit on pixel centres
    error = np.linalg.norm(out_j[refined] - apply_homography(PLANTED, out_i[refined]), axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.1, error.max()
    assert np.array_equal(out_j[~refined], points_j[~refined])


def test_mutual_ratio_matching_recovers_a_planted_permutation() -> None:
    rng = np.random.default_rng(8)
    desc_a = rng.random((800, 128)).astype(np.float32)
    perm = rng.permutation(800)
    desc_b = desc_a[perm] + rng.normal(0, 0.01, (800, 128)).astype(np.float32)
    matches = match_ratio(desc_a, desc_b, 0.8)
    assert len(matches) > 700
    assert np.all(perm[matches[:, 1]] == matches[:, 0])


def _reference_block(images, sizes, to_frame, window, ramp):
    """The map-based composition: cv2.remap on warp_maps over the whole window, for every frame."""
    x, y, w, h = window
    acc, wsum = np.zeros((h, w, 3)), np.zeros((h, w))
    for k, image in images.items():
        map_x, map_y = warp_maps(to_frame[k], x, y, w, h)
        weight = feather_weights(map_x, map_y, *sizes[k], ramp)
        pixels = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        acc += weight[..., None] * pixels
        wsum += weight
    return acc / np.maximum(wsum, 1e-6)[..., None], wsum > 0


def test_window_composition_matches_the_map_based_reference() -> None:
    texture = make_texture(400, 600, seed=4)
    images = {0: texture[:300, :400].copy(), 1: texture[60:360, 150:550].copy()}
    sizes = {0: (400, 300), 1: (400, 300)}
    to_frame = {0: np.eye(3) @ np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1]])}
    to_frame[1] = np.array([[1.0, 0, -150.5], [0, 1.0, -60.5], [0, 0, 1]]) @ np.array(
        [[1.0, 0.02, 0], [-0.02, 1.0, 0], [0, 0, 1]]
    )
    boxes = {k: output_box(M, sizes[k], 600, 400) for k, M in to_frame.items()}
    gains = {k: np.ones(3) for k in images}
    for window in ((0, 0, 256, 256), (256, 128, 256, 256), (512, 256, 88, 144)):
        rgb, mask, _ = compose_block(images.__getitem__, sizes, to_frame, boxes, gains, window, 20.0)
        bgr, ref_mask = _reference_block(images, sizes, to_frame, window, 20.0)
        assert np.array_equal(mask, ref_mask)
        expected = np.clip(np.rint(bgr), 0, 255).astype(np.uint8)  # to nearest, ties to even, as OpenCV rounds
        diff = np.abs(rgb[..., ::-1].astype(int) - expected)[mask]
        assert diff.max() <= 1 and diff.mean() < 0.05
